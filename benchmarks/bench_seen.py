"""What the render's shortcut to the anisotropy costs in quality and saves in time.

A render computes the anisotropy only of the particles its camera may see
(``pipeline.surface.seen_kernels``: those within a depth margin under the particles' spheres, then
those the seen ellipsoids show); the dataset, and so the evaluation, computes every particle's.
This renders the refined method both ways on views of the config's scenes (the validation scene
by default, which may choose the margin; ``--scenes`` adds others, e.g. the held-out ones, to report
on) and scores each against the mesh as the evaluation does: a missed pixel counts 90 degrees, IoU
over the union. For each first-pass margin (in particle radii) it prints the change against every
particle's anisotropy, and the seen particles' anisotropy time on bench_scale's 1M-particle frame at
1920 x 1080. ``--reveal-passes 0`` measures the spheres' surface alone.

    .venv/bin/python benchmarks/bench_seen.py [--config configs/generalize.yaml] [--sizes 256 512]
                                              [--margins 11 7 5 3] [--scenes ...] [--frames 6]
                                              [--reveal-passes N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_scale import SPLITS, split_frame  # noqa: E402
from tune_inference import scene_views  # noqa: E402

import pipeline.surface as surface  # noqa: E402
from pipeline.camera import framing_cameras  # noqa: E402
from pipeline.config import DatasetConfig  # noqa: E402
from pipeline.frames import frame_name, load_frame  # noqa: E402
from pipeline.methods import refine  # noqa: E402
from pipeline.metrics import errors_over_reference, iou  # noqa: E402
from pipeline.parallel import Launcher  # noqa: E402
from pipeline.screen import ScreenSpace  # noqa: E402
from pipeline.surface import anisotropic_kernels, kernel_densities, kernel_ellipsoids, seen_kernels  # noqa: E402
from pipeline.views import screen_space_inputs  # noqa: E402
from stages import render  # noqa: E402
from stages.common import StageOptions, make_run  # noqa: E402

FULL = "every particle"


def refined_inputs(x: np.ndarray, radius: float, cam, p: DatasetConfig, ss: ScreenSpace, launch: Launcher,
                   margin_radii: float | None) -> tuple[dict, float]:
    """The refiner's ellipsoid channels of one view from every particle's anisotropy (None) or the
    seen shell's of ``margin_radii``, and the share of particles that got theirs; the particles'
    densities come with them (the refined mask's gate)."""
    if margin_radii is None:
        kernels, share = anisotropic_kernels(x, radius, p, launch, launch.device), 1.0
        density = kernel_densities(x, radius, p, launch, launch.device, kernels)
    else:
        kernels, seen, density = seen_kernels(x, radius, p, cam, launch, launch.device, margin_radii * radius,
                                              densities=True)
        share = len(seen) / len(x)
    ellipsoids = kernel_ellipsoids(kernels, p, None, density)
    ch = screen_space_inputs(x, radius, cam, p, ss, filters=None, ellipsoids=ellipsoids, aniso_filters=("bilateral",),
                             raw_normals=False)
    return ch, share


def anisotropy_ms(margins: list[float]) -> dict[float, float]:
    """Seconds of the seen shell's anisotropy on bench_scale's 1M frame at 1920 x 1080, per margin."""
    x, _, r = split_frame(SPLITS["1022k"])
    cam = framing_cameras(x.min(0) - r, x.max(0) + r, 1920, 1080, 1)[0]
    p, launch = DatasetConfig(), Launcher("cpu")
    seen_kernels(x, r, p, cam, launch, "cpu")  # compile
    out = {}
    for m in margins:
        best = float("inf")
        for _ in range(2):
            start = time.perf_counter()
            seen_kernels(x, r, p, cam, launch, "cpu", m * r)
            best = min(best, time.perf_counter() - start)
        out[m] = 1000 * best
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "generalize.yaml"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512])
    parser.add_argument("--margins", type=float, nargs="+", default=[11.0, 7.0, 5.0, 3.0],
                        help="depth margins in particle radii")
    parser.add_argument("--scenes", nargs="*", default=[], help="scenes besides the validation scenes")
    parser.add_argument("--frames", type=int, default=6, help="views per camera")
    parser.add_argument("--no-timing", action="store_true", help="skip the 1M frame's anisotropy timing")
    parser.add_argument("--reveal-passes", type=int, default=surface.REVEAL_PASSES,
                        help="seen_kernels' passes behind the ellipsoids (0: the spheres' surface alone)")
    args = parser.parse_args()
    wp.config.quiet = True
    surface.REVEAL_PASSES = args.reveal_passes
    variants: list[float | None] = [None, *args.margins]
    scores: dict = {}
    for size in args.sizes:
        run = make_run(StageOptions(config=args.config), {"dataset": {"width": size, "height": size}})
        refiner = render.networks(run, ("refined",))[0]
        p, threshold = run.config.dataset, run.config.render.normal_threshold
        ss, launch = ScreenSpace("cpu"), Launcher("cpu")
        names = [*run.config.train.validation_scenes, *args.scenes]
        for view in scene_views(run, names, args.frames, size):
            x = np.asarray(load_frame(view.sim_dir / frame_name(view.record["frame"]))[0], np.float32)
            cam, radius, t_mask = view.camera, view.radius, view.target_mask
            for v in variants:
                inputs, share = refined_inputs(x, radius, cam, p, ss, launch, v)
                n, mask, _ = refine(refiner, inputs, threshold, cam.focal_px, radius)
                e, _, missed = errors_over_reference(n, view.target, mask, t_mask)
                got = scores.setdefault((size, view.scene, v), {"errors": [], "missed": 0, "extra": 0, "iou": [],
                                                                "share": []})
                got["errors"].append(e)
                got["missed"] += missed
                got["extra"] += int((mask & ~t_mask).sum())
                got["iou"].append(iou(mask, t_mask))
                got["share"].append(share)
        print(f"  {size} px done", flush=True)
    timing = {} if args.no_timing else anisotropy_ms(args.margins)
    print(f"\nrefined against the mesh (mean / median deg, missed and extra pixels as shares of the mesh's, IoU; "
          f"a missed pixel scores 90 deg), with "
          f"every particle's anisotropy and with the seen particles' (first-pass margin in particle radii, "
          f"default {surface.SEEN_DEPTH_RADII:g}; {args.reveal_passes} reveal passes)")
    names = dict.fromkeys(name for (_, name, _) in scores)
    for size in args.sizes:
        for name in names:
            base = np.concatenate(scores[(size, name, None)]["errors"])
            print(f"\n{size} px, {name}:")
            print(f"{'anisotropy of':>16s} {'particles':>9s} {'mean':>7s} {'median':>7s} {'missed':>7s} {'extra':>7s} "
                  f"{'IoU':>7s} {'d mean':>7s} {'d IoU':>8s} {'1M frame':>9s}")
            for v in variants:
                got = scores[(size, name, v)]
                e = np.concatenate(got["errors"])
                label = FULL if v is None else f"margin {v:g} r"
                ms = f"{timing[v]:7.0f} ms" if v in timing else ""
                d_iou = np.mean(got["iou"]) - np.mean(scores[(size, name, None)]["iou"])
                missed, extra = 100 * got["missed"] / e.size, 100 * got["extra"] / e.size
                print(f"{label:>16s} {np.mean(got['share']):9.2f} {e.mean():7.3f} {np.median(e):7.3f} "
                      f"{missed:6.2f}% {extra:6.2f}% {np.mean(got['iou']):7.4f} "
                      f"{e.mean() - base.mean():+7.3f} {d_iou:+8.4f} {ms:>9s}")


if __name__ == "__main__":
    main()
