"""Which metaball field comes closest to the mesh, on the validation scene: the ray-marched surface of
the thesis' spheres and of the particles' ellipsoids (the mesh's own anisotropic kernels), for ball
sizes and cut-offs, against the anisotropic marching-cubes mesh, with the bilateral and narrow-range
filters beside them. This chose ``metaball.anisotropic``, ``ball_radius_radii`` and
``kernel_radius_radii``: a network that reproduced its surface exactly would score its row.

Views: both cameras of the scene at ``--size``, ``--frames`` frames spread over the sequence. Errors
are over every pixel where the mesh shows fluid, a missed pixel 90 degrees (the report's rule).

    .venv/bin/python benchmarks/bench_metaball_field.py [--size 256] [--frames 4] \
        [--fields spheres:1:4 ellipsoids:1.4:4 ...]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pipeline.methods as methods  # noqa: E402
from pipeline.camera import camera_for_frame  # noqa: E402
from pipeline.frames import frame_name, load_frame, read_sequence_info  # noqa: E402
from pipeline.metaball import MetaballParams, metaball_targets  # noqa: E402
from pipeline.metrics import errors_over_reference, iou  # noqa: E402
from pipeline.parallel import Launcher  # noqa: E402
from pipeline.screen import ScreenSpace  # noqa: E402
from pipeline.surface import particle_ellipsoids  # noqa: E402
from stages import simulate  # noqa: E402
from stages.common import StageOptions, make_run  # noqa: E402

FIELDS = ["spheres:1:4", "ellipsoids:1:4", "ellipsoids:1.2:4", "ellipsoids:1.4:4", "ellipsoids:1.6:4",
          "ellipsoids:1.4:3"]
"""kind:ball radius (particle radii):cut-off (ball radii)."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "generalize.yaml"))
    ap.add_argument("--scene", default="validation_drop")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--frames", type=int, default=4, help="frames a camera, spread over the sequence")
    ap.add_argument("--fields", nargs="+", default=FIELDS)
    args = ap.parse_args()
    wp.config.quiet = True
    run = make_run(StageOptions(config=args.config), {"dataset": {"width": args.size, "height": args.size}})
    scene = run.loaded.scene(args.scene)
    sim = simulate.ensure(run, scene)
    info = read_sequence_info(sim.dir)
    r, p = info.particle_radius, run.config.dataset
    launch, ss = Launcher("cpu"), ScreenSpace("cpu")
    rows = ["bilateral", "nrf", *args.fields]
    scores: dict[str, dict] = {k: {"errors": [], "iou": []} for k in rows}
    for cam_name in ("static", "orbit"):
        for index in np.linspace(5, info.frames - 1, args.frames).astype(int):
            x, _ = load_frame(sim.dir / frame_name(int(index)))
            cam = camera_for_frame(scene.cameras, cam_name, int(index), info.frames, args.size, args.size)
            cache: dict = {}
            mesh = methods.normal_source("mesh", x, r, cam, p, ss, launch, frame_cache=cache)
            t_mask = mesh["mask"] > 0
            ell = particle_ellipsoids(x, r, p, launch, "cpu", cache["kernels"])
            for row in rows:
                if row in ("bilateral", "nrf"):
                    got = methods.normal_source(row, x, r, cam, p, ss, launch, frame_cache=cache)
                else:
                    kind, ball, cutoff = row.split(":")
                    b = float(ball)
                    params = MetaballParams(kernel_radius_radii=float(cutoff), depth_near=0.05, depth_far=50.0,
                                            step=0.05 * r)
                    got = (metaball_targets(ell.centres, b * r, cam, params, launch, shapes=ell.shapes / b,
                                            bounds=b * ell.bounds) if kind == "ellipsoids"
                           else metaball_targets(x, b * r, cam, params, launch))
                e = errors_over_reference(got["normals"], mesh["normals"], got["mask"] > 0, t_mask)[0]
                scores[row]["errors"].append(e)
                scores[row]["iou"].append(iou(got["mask"] > 0, t_mask))
    ss.close()
    launch.close()
    print(f"# bench_metaball_field: {date.today()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores; {args.scene}, both cameras, {args.frames} frames each, {args.size} px; "
          "against the mesh over its pixels (missed: 90 degrees)\n")
    print("| normals | ball radius (particle radii) | cut-off (ball radii) | mean (deg) | median (deg) | IoU |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        e = np.concatenate(scores[row]["errors"])
        name, ball, cutoff = (row, "", "") if ":" not in row else row.split(":")
        label = {"bilateral": "bilateral filter", "nrf": "narrow-range filter",
                 "spheres": "metaballs on spheres (ray-marched)",
                 "ellipsoids": "metaballs on ellipsoids (ray-marched)"}[name]
        print(f"| {label} | {ball} | {cutoff} | {e.mean():.2f} | {np.median(e):.2f} | "
              f"{np.mean(scores[row]['iou']):.3f} |")


if __name__ == "__main__":
    main()
