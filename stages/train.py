"""``make train``: train the refiner on the cached dataset, validating every epoch.

Writes ``data/train/<config>-<key>/``: ``last.pt`` and ``best.pt`` checkpoints (weights, model
arguments, config, epoch, optimiser state; atomic), ``metrics.jsonl``, ``sheets/epoch_NNN.png``
(input | refined | target | error), ``loss_curve.png`` and TensorBoard scalars when installed.
A killed run resumes from ``last.pt``; raising ``train.epochs`` continues a finished run.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pipeline import cache
from pipeline.config import to_dict
from pipeline.model.data import Frame, load_frame, random_crops
from pipeline.model.trainer import Refiner, seed_everything, validation_metrics
from pipeline.plots import error_sheet, loss_curves
from stages import dataset
from stages.common import Run, StageError, make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")


def train_scenes(run: Run) -> list[str]:
    """Scenes whose training split is used."""
    cfg = run.config
    chosen = cfg.train.train_scenes or tuple(s for s in cfg.scenes if s not in cfg.dataset.holdout_scenes)
    for s in chosen:
        if s not in cfg.scenes:
            raise StageError(f"train.train_scenes names {s!r}, which is not in scenes {list(cfg.scenes)}")
    return [s for s in chosen if s in run.loaded.scenes]


def collect(run: Run) -> tuple[dict[str, str], list[Path], list[Path]]:
    """Dataset keys and the train / validation EXR paths (building the dataset if needed)."""
    keys, train, val = {}, [], []
    chosen = set(train_scenes(run))
    held_out = set(run.config.dataset.holdout_scenes)
    for scene in run.loaded.scenes.values():
        entry = dataset.ensure(run, scene)
        keys[scene.name] = entry.key
        for rec in entry.manifest()["frames"]:
            if rec["split"] == "val" or scene.name in held_out:
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
    config.pop("epochs")
    config["seed"] = run.config.seed
    config["holdout_scenes"] = list(run.config.dataset.holdout_scenes)
    name = Path(run.loaded.path).stem
    return cache.entry(run.data_dir, "train", name, config, dataset_keys, run.device)


def _spread(items: list, k: int) -> list:
    if len(items) <= k:
        return items
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, k).round()]


def ensure(run: Run, force: bool = False) -> cache.CacheEntry:
    """Train (or resume) until ``train.epochs``; returns the entry holding the checkpoints."""
    cfg = run.config.train
    keys, train_paths, val_paths = collect(run)
    entry = train_entry(run, keys)
    last = entry.path("last.pt")
    if force and entry.dir.exists():
        entry.begin(force=True)
    entry.begin()
    start_epoch, best, history = 0, math.inf, []
    refiner = Refiner(cfg, run.device, seed=run.config.seed)
    if last.exists():
        try:
            state = torch.load(last, map_location=run.device, weights_only=True)
        except Exception as exc:
            raise StageError(f"corrupt checkpoint {last} ({exc}); delete it or run `make train FORCE=1` (with the "
                             "same CONFIG) to train again") from None
        refiner.load_state(state)
        start_epoch, best, history = int(state["epoch"]), float(state["best"]), list(state["history"])
        if start_epoch >= cfg.epochs:
            log.info("train: cached (%d epochs) in %s", start_epoch, entry.dir)
            return entry
        log.info("train: resuming after epoch %d", start_epoch)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    aux = cfg.auxiliary_features
    log.info("train: loading %d training and %d validation frames", len(train_paths), len(val_paths))
    splat = cfg.input_splat
    frames = [load_frame(p, aux, splat) for p in tqdm(train_paths, desc="load", unit="frame", leave=False)]
    val_frames: list[Frame] = [load_frame(p, aux, splat) for p in _spread(val_paths, cfg.val_frames)] or frames[:2]
    crop = cfg.crop
    height, width = frames[0].inputs.shape[1:]
    if crop > min(height, width):
        raise StageError(f"train.crop is {crop} px but the dataset's images are {width}x{height}; set train.crop "
                         f"to at most {min(height, width)} or render a larger dataset (dataset.width/height)")
    steps = max(1, math.ceil(len(frames) * cfg.crops_per_frame / cfg.batch_size))
    g_params = sum(p.numel() for p in refiner.generator.parameters())
    log.info("train: generator %.2f M parameters, %d steps/epoch of %d crops of %d px on %s",
             g_params / 1e6, steps, cfg.batch_size, crop, run.device)
    writer = _tensorboard(entry.dir / "tensorboard")
    for epoch in tqdm(range(start_epoch + 1, cfg.epochs + 1), desc="train", unit="epoch",
                      initial=start_epoch, total=cfg.epochs):
        # every epoch has its own seeds, so a resumed run draws what a straight one would
        rng = np.random.default_rng([run.config.seed, epoch])
        seed_everything(run.config.seed * 100_003 + epoch)
        sums: dict[str, float] = {}
        t0 = time.perf_counter()
        for _ in tqdm(range(steps), desc=f"epoch {epoch}", unit="step", leave=False):
            x, y = random_crops(frames, crop, cfg.batch_size, rng)
            for k, v in refiner.train_step(x, y).items():
                sums[k] = sums.get(k, 0.0) + v / steps
        refiner.end_epoch()
        train_seconds = time.perf_counter() - t0
        metrics, preds = validation_metrics(refiner.generator, val_frames, refiner.device)
        record = {"epoch": epoch, **sums, "val": metrics, "train_seconds": round(train_seconds, 2),
                  "images_per_second": round(steps * cfg.batch_size / train_seconds, 2),
                  "lr": refiner.opt_g.param_groups[0]["lr"]}
        history.append(record)
        score = metrics["refined"]["mean_deg"]
        improved = score < best
        best = min(best, score)
        state = refiner.state(epoch, {"best": best, "history": history, "metrics": metrics})
        with cache.atomic_path(last) as tmp:
            torch.save(state, tmp)
        if improved:
            with cache.atomic_path(entry.path("best.pt")) as tmp:
                torch.save(state, tmp)
        with cache.atomic_path(entry.path("metrics.jsonl")) as tmp:
            tmp.write_text("".join(json.dumps(h) + "\n" for h in history))
        error_sheet(entry.path(f"sheets/epoch_{epoch:03d}.png"), val_frames[:3], preds[:3])
        if writer is not None:
            for k, v in sums.items():
                writer.add_scalar(f"train/{k}", v, epoch)
            for k in ("mean_deg", "median_deg", "under_10"):
                writer.add_scalar(f"val/refined_{k}", metrics["refined"][k], epoch)
                writer.add_scalar(f"val/bilateral_{k}", metrics["bilateral"][k], epoch)
        log.info("epoch %d: G %.4f (content %.4f, normal %.4f, adv %.3f) D %.3f | val mean %.2f deg "
                 "(bilateral %.2f), <10 deg %.1f%%, IoU %.3f | %.1f img/s", epoch, sums["loss_g"],
                 sums["loss_content"], sums["loss_normal"], sums["loss_adv"], sums["loss_d"], score,
                 metrics["bilateral"]["mean_deg"], 100 * metrics["refined"]["under_10"],
                 metrics["refined_iou"], record["images_per_second"])
    loss_curves(entry.path("loss_curve.png"), history)
    entry.finish(["last.pt", "best.pt", "metrics.jsonl", "loss_curve.png"], {}, epochs=cfg.epochs,
                 best_val_mean_deg=best)
    return entry


def _tensorboard(folder: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(folder))


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make train``."""
    run = make_run(parse_args("train", argv))
    entry = ensure(run, force=run.force)
    log.info("train: checkpoints in %s", entry.dir)


if __name__ == "__main__":
    sys.exit(stage_main("train", main))
