"""The metaball network's input on its own, on the validation scene: how far each input's normals are
from the ray-marched metaball surface before any network, how well its splat covers that surface,
and what it costs. This chose ``metaball.splat_radius`` and ``metaball.field_steps``.

Views: the validation scene's dataset views (``fluid_cameras`` of ``metaball.seed``, drawn at the
working scale), every ``--stride``-th simulated frame. Rows: the spheres' own normals, and the
field's normal at the front of spheres of each splat radius after 0, 1 or 2 Newton steps. Errors
are over the pixels both the splat and the surface cover, pooled over the views.

With ``metaball.anisotropic`` (the default) the balls are the particles' ellipsoids, as the dataset
draws them.

    .venv/bin/python benchmarks/bench_metaball_input.py [--config configs/metaball.yaml] [--radii 0.8 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from datetime import date
from pathlib import Path

import numpy as np
import warp as wp

from pipeline.frames import frame_name, load_frame, read_sequence_info, select_frames
from pipeline.metaball import kernels as metaball_kernels
from pipeline.metaball.dataset import fluid_cameras
from pipeline.metaball.views import fluid_view
from pipeline.metrics import angular_errors, iou
from pipeline.parallel import Launcher, init_warp
from pipeline.surface import particle_ellipsoids
from stages import simulate
from stages.common import StageOptions, make_run

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "metaball.yaml"))
    ap.add_argument("--scene", default="validation_drop")
    ap.add_argument("--stride", type=int, default=12, help="every n-th simulated frame")
    ap.add_argument("--radii", type=float, nargs="+", default=[0.6, 0.7, 0.8, 1.0, 1.5])
    ap.add_argument("--steps", type=int, nargs="+", default=[0, 1, 2])
    args = ap.parse_args()
    wp.config.quiet = True
    run = make_run(StageOptions(config=args.config))
    m, d = run.config.metaball, run.config.dataset
    sim = simulate.ensure(run, run.loaded.scene(args.scene))
    info = read_sequence_info(sim.dir)
    launch = Launcher("cpu")
    init_warp((metaball_kernels,), "cpu")
    rows = [("spheres' own normals", 1.0, None)] + [("field", s, k) for s in args.radii for k in args.steps]
    pooled: dict[int, list] = {k: [] for k in range(len(rows))}
    views = 0
    for frame in select_frames(info.frames, args.stride):
        x = load_frame(sim.dir / frame_name(frame))[0]
        ell = particle_ellipsoids(x, info.particle_radius, d, launch) if m.anisotropic else None
        for cam in fluid_cameras(args.scene, frame, x, info.particle_radius, m, d):
            view = fluid_view(x, info.particle_radius, cam, m, ell)
            target = view.targets(launch)
            surface = target["mask"] > 0
            views += 1
            for k, (_, radius, steps) in enumerate(rows):
                v = dataclasses.replace(view, splat_radius=radius, field_steps=steps)
                start = time.perf_counter()
                layers = v.layers(launch)
                ms = 1000 * (time.perf_counter() - start)
                splat = layers["front"] > 0
                pooled[k].append((angular_errors(layers["normals"], target["normals"], splat & surface),
                                  iou(splat, surface), ms))
    launch.close()
    print(f"# bench_metaball_input: {date.today()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores; {views} views of {args.scene} at the working scale "
          f"({m.working_radius_px:g} px), {'ellipsoids' if m.anisotropic else 'spheres'} of "
          f"{m.ball_radius_radii:g} particle radii, against the ray-marched metaball surface, no network\n")
    print("| normals | splat radius (minimal radii) | Newton steps | mean (deg) | median (deg) | splat IoU "
          "| ms a view |")
    print("|---|---|---|---|---|---|---|")
    for k, (name, radius, steps) in enumerate(rows):
        e = np.concatenate([p[0] for p in pooled[k]])
        print(f"| {name} | {radius:g} | {'' if steps is None else steps} | {e.mean():.2f} | {np.median(e):.2f} | "
              f"{np.mean([p[1] for p in pooled[k]]):.3f} | {np.mean([p[2] for p in pooled[k]]):.1f} |")


if __name__ == "__main__":
    main()
