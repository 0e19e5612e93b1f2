"""``make train``: train the refiner on the cached dataset, validating every epoch.

Writes ``data/train/<config>-<key>/`` (checkpoints, metrics, sheets: ``pipeline.model.train``).
A killed run resumes from ``last.pt``; raising ``train.epochs`` continues a finished run. Under
``torchrun`` (``make train-ddp``) rank 0 alone claims, checks and finishes the cache entry (its lock
would make the others queue behind the training they are part of) and tells the others the folder.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

from pipeline import cache
from pipeline.config import ConfigError, to_dict
from pipeline.model import distributed
from pipeline.model.train import TimeLimitReached, TrainingError, fit, init_path
from stages import dataset, simulate
from stages.common import Run, StageError, StageOptions, make_run, train_scenes

log = logging.getLogger("deep_ssfr")


def collect(run: Run) -> tuple[dict[str, str], list[Path], list[Path]]:
    """Dataset keys and the train / validation EXR paths (building the dataset if needed)."""
    keys, train, val = {}, [], []
    chosen = set(train_scenes(run))
    held_out = set(run.config.dataset.holdout_scenes)
    validating = set(run.config.train.validation_scenes) or held_out
    for name in validating - held_out:
        raise StageError(f"train.validation_scenes names {name!r}, which is not in dataset.holdout_scenes")
    read = [s for s in run.loaded.scenes.values() if s.name not in held_out or s.name in validating]
    simulate.ahead(run, read)  # evaluated only: training never reads the others
    for scene in read:
        entry = dataset.ensure(run, scene)
        keys[scene.name] = entry.key
        for rec in entry.manifest()["frames"]:
            if scene.name in held_out or rec["split"] == "val":
                val.append(entry.path(rec["file"]))
            elif scene.name in chosen:
                train.append(entry.path(rec["file"]))
    if not train:
        raise StageError("no training frames: check train.train_scenes, dataset.holdout_scenes and "
                         "dataset.validation_camera")
    return keys, train, val


def train_entry(run: Run, dataset_keys: dict[str, str]) -> cache.CacheEntry:
    """Keyed on the training config (except ``epochs``: more epochs continue a run) and the data."""
    config = to_dict(run.config.train)
    # these change how long or how a run goes, not its weights
    for how_not_what in ("epochs", "loader_workers", "cached_frames", "time_limit_minutes"):
        config.pop(how_not_what)
    config["seed"] = run.config.seed
    if run.config.train.init_from:  # a fine-tune depends on the weights it starts from
        start = init_path(run.config.train.init_from)
        config["init_from_weights"] = cache.file_hash(start) if start.exists() else "missing"
    config["holdout_scenes"] = list(run.config.dataset.holdout_scenes)
    name = Path(run.loaded.path).stem
    return cache.entry(run.data_dir, "train", name, config, dataset_keys, run.device)


def ensure(run: Run, force: bool = False) -> cache.CacheEntry:
    """Train (or resume) until ``train.epochs``; returns the entry holding the checkpoints."""
    cfg = run.config.train
    if cfg.input_splat == "sphere" and run.config.dataset.random_views and not run.config.dataset.random_view_spheres:
        raise ConfigError(run.loaded.path, "dataset.random_view_spheres", "must be true to train on the sphere "
                          "splat (train.input_splat: sphere): the random views carry only the ellipsoid splat")
    world = distributed.start(run.device)
    if not world.is_main:
        logging.getLogger("deep_ssfr").setLevel(logging.WARNING)  # rank 0 tells the story
    keys, train_paths, val_paths = collect(run)  # concurrent ranks queue on the dataset entries' locks
    entry = train_entry(run, keys)
    folder = None
    with _peer_lost_hint(world):
        with world.while_main_works("waiting for the training entry's lock"):  # another run may hold it
            if world.is_main:
                entry.begin(force=force, reopen=True)  # a finished run with fewer epochs continues
                if not force and entry.is_complete() and entry.manifest().get("epochs", 0) >= cfg.epochs:
                    entry.release()
                    log.info("train: cached (%d epochs) in %s", cfg.epochs, entry.dir)
                else:
                    folder = str(entry.dir)  # a forced run's folder is rank 0's own (named by its pid)
        folder = world.share(folder)
    if folder is None:
        return entry
    try:
        with _peer_lost_hint(world):
            best = fit(Path(folder), cfg, run.config.seed, train_paths, val_paths, run.device)
    except TimeLimitReached as stop:
        if world.is_main:
            entry.release()
            log.info("train: %d of %d epochs done in %s; run the same command again to continue", stop.epoch,
                     cfg.epochs, folder)
        return entry
    with _peer_lost_hint(world), world.while_main_works("writing the training entry's manifest"):
        if world.is_main:  # every rank returns once it is written
            entry.finish(["last.pt", "best.pt", "metrics.jsonl", "loss_curve.png"], {}, epochs=cfg.epochs,
                         best_val_mean_deg=best, processes=world.size)
    return entry


@contextlib.contextmanager
def _peer_lost_hint(world: distributed.World) -> Iterator[None]:
    """A collective's failure (a plain RuntimeError) of a run of several processes gains the rank and
    what to do on a cluster; a training error and one process's errors pass as they are."""
    try:
        yield
    except TrainingError:
        raise
    except RuntimeError as exc:
        if world.size == 1:
            raise
        raise RuntimeError(f"{exc} (rank {world.rank} of {world.size}). {distributed.PEER_HINT}") from exc


def main(opts: StageOptions) -> None:
    """``deep-ssfr train``."""
    run = make_run(opts)
    entry = ensure(run, force=run.force)
    log.info("train: checkpoints in %s", entry.dir)
