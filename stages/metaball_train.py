"""``make metaball-train``: train the metaball pix2pix pair on the cached metaball views.

Writes ``data/metaball_train/<config>-<key>/`` (``pipeline.metaball.train``). A killed run resumes
from ``last.pt``; raising ``metaball.epochs`` continues a finished run; ``metaball.time_limit_minutes``
stops it between epochs (the next run goes on).
"""

from __future__ import annotations

import logging
from pathlib import Path

from pipeline import cache
from pipeline.config import to_dict
from pipeline.metaball.train import fit
from pipeline.model.train import TimeLimitReached
from stages import metaball_dataset
from stages.common import Run, StageError, StageOptions, make_run

log = logging.getLogger("deep_ssfr")


def collect(run: Run) -> tuple[dict[str, str], list[Path], list[Path]]:
    """Dataset keys and the training and validation views (building what is missing)."""
    train_scenes, val_scenes = metaball_dataset.roles(run)
    keys, train, val = {}, [], []
    for scenes, paths in ((train_scenes, train), (val_scenes, val)):
        for scene in scenes:
            entry = metaball_dataset.ensure(run, scene)
            keys[scene.name] = entry.key
            paths += [entry.path(r["file"]) for r in entry.manifest()["views"]]
    sets = metaball_dataset.ensure_random_sets(run)
    if sets is not None:
        keys[metaball_dataset.RANDOM_SETS] = sets.key
        train += [sets.path(r["file"]) for r in sets.manifest()["views"]]
    if not train:
        raise StageError("no metaball training views")
    return keys, train, val


def entry_of(run: Run, keys: dict[str, str]) -> cache.CacheEntry:
    """Keyed on the metaball config (less what changes how long a run goes) and the data."""
    config = to_dict(run.config.metaball)
    for how_not_what in ("epochs", "time_limit_minutes", "weights", "target_stride"):
        config.pop(how_not_what)
    config["seed"] = run.config.seed
    return cache.entry(run.data_dir, "metaball_train", Path(run.loaded.path).stem, config, keys, run.device)


def ensure(run: Run, force: bool = False) -> cache.CacheEntry:
    """Train (or resume) until ``metaball.epochs``; returns the entry holding the checkpoints."""
    m = run.config.metaball
    keys, train, val = collect(run)
    entry = entry_of(run, keys)
    entry.begin(force=force, reopen=True)  # a finished run with fewer epochs continues
    if not force and entry.is_complete() and entry.manifest().get("epochs", 0) >= m.epochs:
        entry.release()
        log.info("metaball train: cached (%d epochs) in %s", m.epochs, entry.dir)
        return entry
    try:
        best = fit(entry.dir, m, run.config.seed, train, val, run.device)
    except TimeLimitReached as stop:
        entry.release()
        log.info("metaball train: %d of %d epochs done in %s; run the same command again to continue", stop.epoch,
                 m.epochs, entry.dir)
        return entry
    entry.finish(["last.pt", "best.pt", "metrics.jsonl", "loss_curve.png"], {}, epochs=m.epochs,
                 best_val_score_deg=best, training_views=len(train), validation_views=len(val))
    return entry


def main(opts: StageOptions) -> None:
    """``deep-ssfr metaball-train``."""
    run = make_run(opts)
    entry = ensure(run, force=run.force)
    log.info("metaball train: checkpoints in %s", entry.dir)
