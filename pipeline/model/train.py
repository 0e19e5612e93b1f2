"""The refiner's training loop: epochs of random crops, validation, checkpoints that resume.

Writes into one folder: ``last.pt`` and ``best.pt`` (weights, model arguments, config, epoch,
optimiser state; atomic), ``metrics.jsonl``, ``sheets/epoch_NNN.png`` (input | refined | target |
error), ``loss_curve.png`` and TensorBoard scalars when installed. Each epoch draws from its own
seeds, so a resumed run makes the same draws a straight one would.
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from pipeline.cache import atomic_path
from pipeline.config import TrainConfig
from pipeline.frames import spread
from pipeline.model.data import Frame, load_frame, random_crops
from pipeline.model.trainer import Refiner, seed_everything, validation_metrics
from pipeline.plots import error_sheet, loss_curves

log = logging.getLogger("deep_ssfr")


class TrainingError(RuntimeError):
    """Training cannot start: a damaged checkpoint or data that does not fit the config."""


def load_checkpoint(refiner: Refiner, path: Path) -> tuple[int, float, list]:
    """Restore ``last.pt`` into ``refiner``: (epochs done, best validation score, history)."""
    try:
        state = torch.load(path, map_location=refiner.device, weights_only=True)
    except Exception as exc:
        raise TrainingError(f"corrupt checkpoint {path} ({exc}); delete it or run `make train FORCE=1` (with the "
                            "same CONFIG) to train again") from None
    refiner.load_state(state)
    return int(state["epoch"]), float(state["best"]), list(state["history"])


def fit(folder: Path, cfg: TrainConfig, seed: int, train_paths: list[Path], val_paths: list[Path],
        device: str) -> float:
    """Train (or resume) until ``cfg.epochs``; returns the best validation mean error (degrees)."""
    folder = Path(folder)
    last = folder / "last.pt"
    refiner = Refiner(cfg, device, seed=seed)
    start_epoch, best, history = load_checkpoint(refiner, last) if last.exists() else (0, math.inf, [])
    if start_epoch >= cfg.epochs:
        return best
    if start_epoch:
        log.info("train: resuming after epoch %d", start_epoch)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    log.info("train: loading %d training and %d validation frames", len(train_paths), len(val_paths))
    frames = [load_frame(p, cfg.auxiliary_features, cfg.input_splat)
              for p in tqdm(train_paths, desc="load", unit="frame", leave=False)]
    val_frames: list[Frame] = [load_frame(p, cfg.auxiliary_features, cfg.input_splat)
                               for p in spread(val_paths, cfg.val_frames)] or frames[:2]
    height, width = frames[0].inputs.shape[1:]
    if cfg.crop > min(height, width):
        raise TrainingError(f"train.crop is {cfg.crop} px but the dataset's images are {width}x{height}; set "
                            f"train.crop to at most {min(height, width)} or render a larger dataset "
                            "(dataset.width/height)")
    steps = max(1, math.ceil(len(frames) * cfg.crops_per_frame / cfg.batch_size))
    log.info("train: generator %.2f M parameters, %d steps/epoch of %d crops of %d px on %s",
             sum(p.numel() for p in refiner.generator.parameters()) / 1e6, steps, cfg.batch_size, cfg.crop, device)
    board = _tensorboard(folder / "tensorboard")
    for epoch in tqdm(range(start_epoch + 1, cfg.epochs + 1), desc="train", unit="epoch",
                      initial=start_epoch, total=cfg.epochs):
        rng = np.random.default_rng([seed, epoch])
        seed_everything(seed * 100_003 + epoch)
        sums: dict[str, float] = {}
        t0 = time.perf_counter()
        for _ in tqdm(range(steps), desc=f"epoch {epoch}", unit="step", leave=False):
            x, y = random_crops(frames, cfg.crop, cfg.batch_size, rng)
            for k, v in refiner.train_step(x, y).items():
                sums[k] = sums.get(k, 0.0) + v / steps
        refiner.end_epoch()
        seconds = time.perf_counter() - t0
        metrics, preds = validation_metrics(refiner.generator, val_frames, refiner.device)
        record = {"epoch": epoch, **sums, "val": metrics, "train_seconds": round(seconds, 2),
                  "images_per_second": round(steps * cfg.batch_size / seconds, 2),
                  "lr": refiner.opt_g.param_groups[0]["lr"]}
        history.append(record)
        score = metrics["refined"]["mean_deg"]
        improved, best = score < best, min(best, score)
        state = refiner.state(epoch, {"best": best, "history": history, "metrics": metrics})
        for name in ("last.pt", "best.pt") if improved else ("last.pt",):
            with atomic_path(folder / name) as tmp:
                torch.save(state, tmp)
        with atomic_path(folder / "metrics.jsonl") as tmp:
            tmp.write_text("".join(json.dumps(h) + "\n" for h in history))
        error_sheet(folder / f"sheets/epoch_{epoch:03d}.png", val_frames[:3], preds[:3])
        _log_epoch(board, record)
    loss_curves(folder / "loss_curve.png", history)
    return best


def _log_epoch(board, record: dict) -> None:
    """One log line per epoch, and the scalars to TensorBoard when it is installed."""
    val = record["val"]
    if board is not None:
        for k in ("loss_g", "loss_content", "loss_normal", "loss_adv", "loss_d"):
            board.add_scalar(f"train/{k}", record[k], record["epoch"])
        for k in ("mean_deg", "median_deg", "under_10"):
            board.add_scalar(f"val/refined_{k}", val["refined"][k], record["epoch"])
            board.add_scalar(f"val/bilateral_{k}", val["bilateral"][k], record["epoch"])
    log.info("epoch %d: G %.4f (content %.4f, normal %.4f, adv %.3f) D %.3f | val mean %.2f deg "
             "(bilateral %.2f), <10 deg %.1f%%, IoU %.3f | %.1f img/s", record["epoch"], record["loss_g"],
             record["loss_content"], record["loss_normal"], record["loss_adv"], record["loss_d"],
             val["refined"]["mean_deg"], val["bilateral"]["mean_deg"], 100 * val["refined"]["under_10"],
             val["refined_iou"], record["images_per_second"])


def _tensorboard(folder: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(folder))
