"""The refiner's training loop: epochs of random crops, validation, checkpoints that resume.

Writes into one folder: ``last.pt`` and ``best.pt`` (weights, model arguments, config, epoch,
optimiser state; atomic), ``metrics.jsonl``, ``sheets/epoch_NNN.png`` (input | refined | target |
error), ``loss_curve.png`` and TensorBoard scalars when installed. Each epoch draws from its own
seeds, so a resumed run makes the same draws a straight one would. Crops come from frames held in
memory or read from disk (``train.data``); under ``torchrun`` the processes share each global
batch (``pipeline.model.distributed``) and rank 0 alone writes.
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
from pipeline.model import SHIPPED_WEIGHTS, distributed
from pipeline.model.data import CropDataset, DiskBatches, Frame, InputSpec, MemoryBatches, held_window, load_frame
from pipeline.model.trainer import Refiner, seed_everything, validation_metrics
from pipeline.plots import error_sheet, loss_curves

log = logging.getLogger("deep_ssfr")

MEMORY_WINDOW_PX = 384
"""Memory training holds each frame (at the working scale) as at most a window of this side around a
random fluid pixel, in float16: about 2.7 MiB a frame instead of up to 38 MiB for a 1024 px view."""


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
    """Train (or resume) until ``cfg.epochs``; returns the best validation mean error (degrees).

    Under ``torchrun`` every process runs this: they join one process group, train the same
    networks (DistributedDataParallel) on slices of each global batch of ``cfg.batch_size`` crops,
    and rank 0 alone validates and writes; the others wait for it at the end of each epoch."""
    folder = Path(folder)
    world = distributed.start(device)
    device = world.device(device)
    main = world.is_main
    last = folder / "last.pt"
    refiner = Refiner(cfg, device, seed=seed)
    start_epoch, best, history = load_checkpoint(refiner, last) if last.exists() else (0, math.inf, [])
    if start_epoch >= cfg.epochs:
        return best
    if not start_epoch and cfg.init_from:
        init_generator(refiner, cfg.init_from)
        if main:
            log.info("train: generator initialised from %s", cfg.init_from)
    if cfg.batch_size % world.size:
        raise TrainingError(f"train.batch_size is {cfg.batch_size}, which does not split over {world.size} "
                            f"processes; set it to a multiple of {world.size} or change --nproc_per_node")
    if start_epoch and main:
        log.info("train: resuming after epoch %d", start_epoch)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    steps = max(1, math.ceil(len(train_paths) * cfg.crops_per_frame / cfg.batch_size))
    source = _crop_source(cfg, seed, train_paths, steps, world, refiner.device)
    val_frames: list[Frame] = []
    if main:
        val_frames = [load_frame(p, InputSpec.of(cfg)) for p in spread(val_paths, cfg.val_frames) or train_paths[:2]]
    height, width = source.frame_size
    if cfg.crop > min(height, width):
        raise TrainingError(f"train.crop is {cfg.crop} px but the dataset's views are at most {width}x{height} at "
                            f"the working scale; set train.crop to at most {min(height, width)} or render a larger "
                            "dataset (dataset.width/height)")
    if main:
        log.info("train: generator %.2f M parameters, %d steps/epoch of %d crops of %d px on %s (%s data, "
                 "%d process%s)", sum(p.numel() for p in refiner.generator.parameters()) / 1e6, steps,
                 cfg.batch_size, cfg.crop, device, cfg.data, world.size, "es" if world.size > 1 else "")
    if world.size > 1:
        refiner.distribute()
    board = _tensorboard(folder / "tensorboard") if main else None
    began = time.perf_counter()
    for epoch in tqdm(range(start_epoch + 1, cfg.epochs + 1), desc="train", unit="epoch",
                      initial=start_epoch, total=cfg.epochs, disable=not main):
        seed_everything(seed * 100_003 + epoch)
        sums: dict[str, float] = {}
        t0 = time.perf_counter()
        for x, y in tqdm(source.batches(epoch, steps), desc=f"epoch {epoch}", unit="step", total=steps,
                         leave=False, disable=not main):
            for k, v in refiner.train_step(x, y).items():
                sums[k] = sums.get(k, 0.0) + v / steps
        refiner.end_epoch()
        sums = world.mean(sums)
        seconds = time.perf_counter() - t0
        with world.while_main_works(f"validating and writing epoch {epoch}"):  # the others wait
            if main:
                metrics, preds = validation_metrics(refiner.generator, val_frames, refiner.device)
                record = {"epoch": epoch, **sums, "val": metrics, "train_seconds": round(seconds, 2),
                          "images_per_second": round(steps * cfg.batch_size / seconds, 2),
                          "lr": refiner.opt_g.param_groups[0]["lr"], "processes": world.size}
                history.append(record)
                best = _write_epoch(folder, refiner, history, best, val_frames, preds)
                _log_epoch(board, record)
        # rank 0's clock decides for every rank: each one's own could fall either side of the limit
        if (cfg.time_limit_minutes and epoch < cfg.epochs
                and world.share(time.perf_counter() - began > 60 * cfg.time_limit_minutes)):
            if main:
                log.info("train: time limit of %g minutes reached after epoch %d of %d; last.pt is written and "
                         "the next run resumes", cfg.time_limit_minutes, epoch, cfg.epochs)
            raise TimeLimitReached(epoch)
    if main:
        loss_curves(folder / "loss_curve.png", history)
    return world.share(best)


class TimeLimitReached(Exception):
    """Training stopped at an epoch boundary on ``train.time_limit_minutes``; ``last.pt`` is written."""

    def __init__(self, epoch: int):
        super().__init__(f"stopped after epoch {epoch}")
        self.epoch = epoch


def init_path(source: str) -> Path:
    """The checkpoint ``train.init_from`` names: the shipped weights or a path."""
    return SHIPPED_WEIGHTS if source == "shipped" else Path(source)


def init_generator(refiner: Refiner, source: str) -> None:
    """Load the generator weights of ``source`` ('shipped' or a checkpoint path) into ``refiner``;
    the checkpoint must describe the same architecture and input."""
    path = init_path(source)
    try:
        state = torch.load(path, map_location=refiner.device, weights_only=True)
    except FileNotFoundError:
        raise TrainingError(f"train.init_from: no checkpoint at {path}") from None
    except Exception as exc:
        raise TrainingError(f"train.init_from: cannot read {path} ({exc})") from None
    want = dict(refiner.generator.args)
    got = {"residual": False, "out_channels": 3, **state.get("generator_args", {})}
    weights = state["generator"]
    if InputSpec.of(refiner.cfg).density and got["in_channels"] == want["in_channels"] - 1:
        # weights without the density feature: it enters with zero weights, so training starts from
        # their output and learns what the feature adds
        got["in_channels"] += 1
        stem = weights["stem.0.weight"]
        weights = {**weights, "stem.0.weight": torch.cat([stem, stem.new_zeros(stem.shape[0], 1, *stem.shape[2:])], 1)}
    if got != want:
        raise TrainingError(f"train.init_from: {path} holds a generator {got}, but this config builds {want}; "
                            "set the train.gen_* keys, input_features, density_feature and residual to match it")
    refiner.generator.load_state_dict(weights)


def _crop_source(cfg: TrainConfig, seed: int, paths: list[Path], steps: int, world: distributed.World,
                 device: torch.device) -> MemoryBatches | DiskBatches:
    """This process's batches: every frame decoded into memory, or crops read from disk by DataLoader workers."""
    if cfg.data == "disk":
        dataset = CropDataset(paths, cfg.crop, seed, InputSpec.of(cfg), cfg.cached_frames, rotate=cfg.rotations)
        return DiskBatches(dataset, steps, cfg.batch_size, cfg.loader_workers, world.rank, world.size,
                           pin_memory=device.type == "cuda")
    if world.is_main:
        log.info("train: loading %d training frames", len(paths))
    spec = InputSpec.of(cfg)
    rng = np.random.default_rng([seed, 7])
    frames = [held_window(load_frame(p, spec), MEMORY_WINDOW_PX, rng)
              for p in tqdm(paths, desc="load", unit="frame", leave=False, disable=not world.is_main)]
    return MemoryBatches(frames, cfg.crop, cfg.batch_size, seed, world.rank, world.size, rotate=cfg.rotations)


def _write_epoch(folder: Path, refiner: Refiner, history: list[dict], best: float, val_frames: list[Frame],
                 preds: list[np.ndarray]) -> float:
    """Checkpoints (``best.pt`` too when the epoch improved), metrics and sheet of the last epoch of
    ``history``; returns the best validation score so far."""
    record = history[-1]
    score = record["val"]["refined"]["mean_deg"]
    improved, best = score < best, min(best, score)
    state = refiner.state(record["epoch"], {"best": best, "history": history, "metrics": record["val"]})
    for name in ("last.pt", "best.pt") if improved else ("last.pt",):
        with atomic_path(folder / name) as tmp:
            torch.save(state, tmp)
    with atomic_path(folder / "metrics.jsonl") as tmp:
        tmp.write_text("".join(json.dumps(h) + "\n" for h in history))
    error_sheet(folder / f"sheets/epoch_{record['epoch']:03d}.png", val_frames[:3], preds[:3])
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
