"""``make ship``: make a config's trained refiner the shipped one.

Copies the best checkpoint of ``make train`` (weights and construction arguments only, no optimiser
state) over ``pipeline/weights/refiner.pt``, writes its card ``refiner.json`` (training config,
data, device, time, held-out metrics, history) and ``docs/loss_curve.png``. The weights are
replaced in place: every clone carries the repository's history.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

import torch

from pipeline import cache
from pipeline.model import SHIPPED_WEIGHTS as SHIPPED
from stages import train
from stages.common import StageOptions, make_run, train_scenes

log = logging.getLogger("deep_ssfr")
ROOT = Path(__file__).resolve().parents[1]


def card(run, entry: cache.CacheEntry, state: dict) -> dict:
    """What the shipped weights are: recipe, data, where and how long they trained, how well."""
    cfg = run.config
    history = [json.loads(line) for line in entry.path("metrics.jsonl").read_text().splitlines() if line]
    manifest = entry.manifest()
    config = Path(run.loaded.path).resolve()
    config = config.relative_to(ROOT) if config.is_relative_to(ROOT) else config
    return {
        "what": f"Generator of the cGAN normal-map refiner (Choi et al. 2021) trained by `make train` on {config}",
        "epoch": int(state["epoch"]),
        "epochs_run": len(history),
        "generator_args": dict(state["generator_args"]),
        "train_config": state["config"],
        "data": {
            "scenes_trained": train_scenes(run),
            "held_out_scenes": list(cfg.dataset.holdout_scenes),
            "validation": (f"best epoch chosen on {', '.join(cfg.train.validation_scenes)} (held out, not reported "
                           "by evaluate)" if cfg.train.validation_scenes else
                           f"{cfg.dataset.validation_camera} camera of every scene + all of the held-out scenes"),
            "frames": f"{cfg.simulate.frames} simulated frames per scene, every {cfg.dataset.frame_stride}, "
                      f"{cfg.dataset.width}x{cfg.dataset.height} from the scenes' two cameras, plus "
                      f"{cfg.dataset.random_views} random views a frame (sides {cfg.dataset.random_size[0]}-"
                      f"{cfg.dataset.random_size[1]} px, particles {cfg.dataset.random_radius_px[0]:g}-"
                      f"{cfg.dataset.random_radius_px[1]:g} px on screen) of the simulated training scenes; "
                      f"filters '{cfg.dataset.filter_mode}'",
            "training_views": len(train.collect(run)[1]),
            "input_features": cfg.train.input_features,
            "working_radius_px": cfg.train.working_radius_px,
            "input_splat": cfg.train.input_splat,
            "particle_radius_m": cfg.simulate.particle_radius,
            "dataset_keys": manifest.get("inputs", {}),
        },
        "device": run.device,
        "train_seconds": round(sum(h.get("train_seconds", 0.0) for h in history), 1),
        "held_out": state["metrics"],
        "history": [{"epoch": h["epoch"], "val_refined_mean_deg": round(h["val"]["refined"]["mean_deg"], 3),
                     "loss_content": round(h["loss_content"], 5), "loss_normal": round(h["loss_normal"], 5)}
                    for h in history],
    }


def main(opts: StageOptions, out: str = "") -> None:
    """``deep-ssfr ship``; ``out``: write refiner.pt, refiner.json and loss_curve.png there instead."""
    run = make_run(opts)
    entry = train.ensure(run)
    state = torch.load(entry.path("best.pt"), map_location="cpu", weights_only=True)
    shipped = {k: state[k] for k in ("generator", "generator_args", "config", "epoch", "metrics")}
    weights = Path(out) / SHIPPED.name if out else SHIPPED
    curve = Path(out) / "loss_curve.png" if out else ROOT / "docs" / "loss_curve.png"
    with cache.atomic_path(weights) as tmp:
        torch.save(shipped, tmp)
    digest = hashlib.sha256(weights.read_bytes()).hexdigest()  # checked on every load
    cache.write_json_atomic(weights.with_suffix(".json"), {**card(run, entry, state), "sha256": digest})
    with cache.atomic_path(curve) as tmp:
        shutil.copyfile(entry.path("loss_curve.png"), tmp)
    log.info("ship: epoch %d of %s (held-out mean %.2f deg) -> %s (%.1f MB)", state["epoch"], entry.dir,
             state["metrics"]["refined"]["mean_deg"], weights, weights.stat().st_size / 2**20)
