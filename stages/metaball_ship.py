"""``make metaball-ship``: make a config's trained metaball generator the shipped one.

Copies the generator of ``make metaball-train``'s best checkpoint (weights, construction arguments
and the metaball config it was trained with) over ``pipeline/weights/metaball.pt``, writes its card
``metaball.json`` and ``docs/metaball_loss_curve.png``; replaced in place, like the refiner's.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path

import torch

from pipeline import cache
from pipeline.metaball.train import SHIPPED_WEIGHTS
from pipeline.plots import metaball_curves
from stages import metaball_train
from stages.common import StageOptions, make_run

log = logging.getLogger("deep_ssfr")
ROOT = Path(__file__).resolve().parents[1]


def card(run, entry: cache.CacheEntry, state: dict, history: list[dict]) -> dict:
    """What the shipped metaball weights are: recipe, data, where and how long they trained, how well."""
    m = run.config.metaball
    keys, train, val = metaball_train.collect(run)
    config = Path(run.loaded.path).resolve()
    return {
        "what": f"{'ResNet' if m.architecture == 'resnet' else 'U-Net'} generator of the image-space metaballs "
                f"(Horvath 2019) on the {m.input} input, trained by `make metaball-train` on "
                f"{config.relative_to(ROOT) if config.is_relative_to(ROOT) else config}",
        "epoch": int(state["epoch"]),
        "epochs_run": len(history),
        "generator_args": dict(state["generator_args"]),
        "metaball_config": state["config"],
        "data": {"training_views": len(train), "validation_views": len(val), "dataset_keys": keys,
                 "views": f"every {m.frame_stride}th frame of each training scene from {m.views_per_frame} random "
                          f"cameras at {m.size} x {m.size}, plus {m.random_sets} random ball sets x {m.repeats}, drawn "
                          + (f"with the median ball at {m.working_radius_px:g} px" if m.working_radius_px
                             else "at the cameras' size"),
                 "held_out_scenes": list(run.config.dataset.holdout_scenes)},
        "device": run.device,
        "train_seconds": round(sum(h.get("train_seconds", 0.0) for h in history), 1),
        "validation": state["metrics"],
        "history": [{"epoch": h["epoch"], "val_mean_deg": round(h["val"]["mean_deg"], 3),
                     "val_iou": round(h["val"]["iou"], 4), "loss_l1": round(h["loss_l1"], 5),
                     "loss_gan": round(h["loss_gan"], 4), "loss_d": round(h["loss_d"], 4)} for h in history],
    }


def main(opts: StageOptions, out: str = "") -> None:
    """``deep-ssfr metaball-ship``; ``out``: write metaball.pt, metaball.json and the curve there instead."""
    run = make_run(opts)
    entry = metaball_train.ensure(run)
    state = torch.load(entry.path("best.pt"), map_location="cpu", weights_only=True)
    history = [json.loads(line) for line in entry.path("metrics.jsonl").read_text().splitlines() if line]
    weights = Path(out) / SHIPPED_WEIGHTS.name if out else SHIPPED_WEIGHTS
    curve = Path(out) / "metaball_loss_curve.png" if out else ROOT / "docs" / "metaball_loss_curve.png"
    with cache.atomic_path(weights) as tmp:
        torch.save({k: state[k] for k in ("generator", "generator_args", "config", "epoch", "metrics")}, tmp)
    digest = hashlib.sha256(weights.read_bytes()).hexdigest()  # checked on every load
    cache.write_json_atomic(weights.with_suffix(".json"), {**card(run, entry, state, history), "sha256": digest})
    metaball_curves(curve, history)
    log.info("metaball ship: epoch %d of %s (validation %.2f deg) -> %s (%.1f MB)", state["epoch"], entry.dir,
             state["metrics"]["mean_deg"], weights, weights.stat().st_size / 2**20)
