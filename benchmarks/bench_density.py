"""What the particles' own density tells about the refined mask's surplus, and why it is an input.

The refined mask keeps spray and thin sheets at the splat's extent where the mesh's iso-surface
opens holes in them (docs/evaluation.md). The splat's ``aniso.density`` map holds, at each pixel,
the largest mesh density at the kernel centre of a particle drawn there (in iso-levels:
``surface.KernelMaker.densities``). On the camera paths of the validation and training scenes
(never the reported held-out ones) this prints, for refined weights that do not see the map (the
shipped weights before the feature, or ``--weights``), how well the map tells the refined pixels
the mesh leaves open (surplus) from those it keeps: the ROC AUC of a low density, and what a hard
gate (drop a pixel whose nearest splat pixel's density is under ``--gates``) does to missed pixels
and IoU. A gate removes surplus and also mesh pixels (each then scores 90 degrees), which is why
the density is the network's input (``train.density_feature``) rather than a rule.

    .venv/bin/python benchmarks/bench_density.py [--config configs/generalize.yaml] [--sizes 256]
        [--scenes validation_drop sph_slosh ...] [--frames 8] [--gates 0.8 1.0] [--weights PATH]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import warp as wp
from scipy.stats import rankdata

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from tune_inference import scene_views  # noqa: E402

from pipeline.ellipsoids import DENSITY_CHANNEL  # noqa: E402
from pipeline.masks import NearestFluid  # noqa: E402
from pipeline.methods import refine  # noqa: E402
from pipeline.metrics import iou  # noqa: E402
from pipeline.model.inference import load_refiner  # noqa: E402
from stages import render  # noqa: E402
from stages.common import StageOptions, make_run  # noqa: E402

SCENES = ["validation_drop", "sph_slosh", "sph_pool_drop", "crossing_jets", "splash_drops"]


def auc(low_is_positive: np.ndarray, negative: np.ndarray) -> float:
    """ROC AUC of a low value marking the positives (Mann-Whitney U over the ranks)."""
    scores = -np.concatenate([low_is_positive, negative])
    ranks = rankdata(scores)
    n_pos, n_neg = len(low_is_positive), len(negative)
    return float((ranks[:n_pos].sum() - n_pos * (n_pos + 1) / 2) / max(n_pos * n_neg, 1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "generalize.yaml"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[256])
    parser.add_argument("--scenes", nargs="+", default=SCENES)
    parser.add_argument("--frames", type=int, default=8, help="views per camera")
    parser.add_argument("--gates", type=float, nargs="+", default=[0.8, 1.0])
    parser.add_argument("--weights", default="", help="refiner checkpoint (default: the config's shipped weights)")
    args = parser.parse_args()
    wp.config.quiet = True
    config = make_run(StageOptions(config=args.config), {}).config
    reported = set(args.scenes) & (set(config.dataset.holdout_scenes) - set(config.train.validation_scenes))
    if reported:
        raise SystemExit(f"bench_density: {', '.join(sorted(reported))} are reported held-out scenes")
    print(f"{'size':>5s} {'scene':>16s} {'surplus':>8s} {'AUC':>6s}  IoU plain / gated " +
          " ".join(f"{g:g}" for g in args.gates) + "  (missed % of the mesh's pixels)")
    for size in args.sizes:
        run = make_run(StageOptions(config=args.config), {"dataset": {"width": size, "height": size}})
        refiner = load_refiner(args.weights) if args.weights else render.networks(run, ("refined",))[0]
        if refiner.spec.density:
            raise SystemExit("bench_density: these weights see the density already; pass --weights of ones "
                             "that do not")
        threshold = run.config.render.normal_threshold
        for name in args.scenes:
            surplus, kept, mesh = [], [], 0
            ious: dict[float, list[float]] = {g: [] for g in (0.0, *args.gates)}
            missed = dict.fromkeys(ious, 0)
            for view in scene_views(run, [name], args.frames, size):
                ch, cam = view.channels, view.camera
                _, mask, _ = refine(refiner, ch, threshold, cam.focal_px, view.radius)
                fluid, density, t_mask = ch["aniso.A"] > 0, ch[DENSITY_CHANNEL], view.target_mask
                surplus.append(density[mask & ~t_mask & fluid])
                kept.append(density[mask & t_mask & fluid])
                mesh += int(t_mask.sum())
                spread = NearestFluid.of(fluid, 4.0).spread(density, mask) if fluid.any() else density
                for g in ious:
                    gated = mask & (spread >= g) if g > 0 else mask
                    ious[g].append(iou(gated, t_mask))
                    missed[g] += int((t_mask & ~gated).sum())
            s, k = np.concatenate(surplus), np.concatenate(kept)
            cells = " ".join(f"{np.mean(ious[g]):.4f} ({100 * missed[g] / mesh:.2f}%)" for g in ious)
            print(f"{size:5d} {name:>16s} {100 * s.size / mesh:7.2f}% {auc(s, k):6.3f}  {cells}", flush=True)


if __name__ == "__main__":
    main()
