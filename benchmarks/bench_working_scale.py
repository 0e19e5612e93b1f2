"""Quality per millisecond of the refiner's working scale for small particles.

The refiner sees every view with particles of about ``working_radius_px`` (3 px): frames of
smaller particles are interpolated up (at most 4x), which costs the square of the factor in network
time. ``MAX_WORKING_PIXELS`` bounds that upscale by the fluid's bounding box. This prints, for the
split SPlisHSPlasH frames of ``bench_scale.py`` at several image sizes (so several projected particle
sizes), the refiner's time and its normal error against the mesh with each bound: none (4x at
most), 1 MP, 0.5 MP (the default's bound) and no upscale at all, each for every particle size (the
default also has ``UPSCALE_BELOW_PX``, a bound on the particle size, which ``tune_inference.py``
chooses on the validation scene; none for the shipped weights).

    .venv/bin/python benchmarks/bench_working_scale.py [--counts 38k 303k 1022k]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from datetime import date
from pathlib import Path

import numpy as np
import warp as wp

wp.config.quiet = True  # the table goes to stdout
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scale import SPLITS, split_frame  # noqa: E402

import pipeline.methods as methods  # noqa: E402
from pipeline.camera import framing_cameras  # noqa: E402
from pipeline.config import DatasetConfig  # noqa: E402
from pipeline.device import warp_device  # noqa: E402
from pipeline.methods import normal_source  # noqa: E402
from pipeline.metrics import angular_errors, iou  # noqa: E402
from pipeline.model import SHIPPED_WEIGHTS  # noqa: E402
from pipeline.model.inference import load_weights  # noqa: E402
from pipeline.model.scale import median_radius_px, working_scale  # noqa: E402
from pipeline.parallel import Launcher  # noqa: E402
from pipeline.screen import ScreenSpace  # noqa: E402
from pipeline.timing import Timings  # noqa: E402

BOUNDS = {"none (4x)": 1 << 40, "1 MP": 1 << 20, "0.5 MP": 1 << 19, "no upscale": 1}
SIZES = ((1920, 1080), (960, 540), (480, 270))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--counts", nargs="+", default=list(SPLITS), choices=list(SPLITS))
    ap.add_argument("--repeat", type=int, default=2, help="timed refiner runs per case (median)")
    args = ap.parse_args()
    refiner = load_weights(SHIPPED_WEIGHTS)[0]
    p, ss, launch = DatasetConfig(), ScreenSpace("cpu"), Launcher(warp_device("cpu"))
    print(f"# bench_working_scale: {date.today()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, device cpu; error of the refined normals against the mesh\n")
    print("| particles | size | particle radius (px) | upscale bound | scale | refiner (ms) | mean (deg) | "
          "median (deg) | IoU |")
    print("|---|---|---|---|---|---|---|---|---|")
    for count in args.counts:
        x, _, r = split_frame(SPLITS[count])
        for w, h in SIZES:
            cam = framing_cameras(x.min(0) - r, x.max(0) + r, w, h, 1)[0]
            cache: dict = {}
            mesh = normal_source("mesh", x, r, cam, p, ss, launch, refiner, frame_cache=cache)
            mesh_mask = mesh["mask"] > 0
            raw = ss.splat(x, r, cam).depth
            methods.UPSCALE_BELOW_PX = float("inf")  # each bound at every particle size
            for name, bound in BOUNDS.items():
                methods.MAX_WORKING_PIXELS = bound  # what refine() reads
                times = []
                for _ in range(args.repeat + 1):  # the first warms up
                    t = Timings()
                    src = normal_source("refined", x, r, cam, p, ss, launch, refiner, frame_cache=cache, timings=t)
                    times.append(t.per_call_ms()["refiner"])
                mask = src["mask"] > 0
                e = angular_errors(src["normals"], mesh["normals"], mask & mesh_mask)
                scale = working_scale(raw, cam.focal_px, r, refiner.spec.working_radius_px, bound)
                print(f"| {len(x):,} | {w}x{h} | {median_radius_px(raw, cam.focal_px, r):.2f} | {name} | {scale:.2f} | "
                      f"{np.median(times[1:]):.0f} | {e.mean():.2f} | {np.median(e):.2f} | "
                      f"{iou(mask, mesh_mask):.4f} |", flush=True)


if __name__ == "__main__":
    main()
