"""Sweep of the bilateral filter's two parameters against the mesh on training scenes.

The bilateral filter is both a baseline and the refiner's input. Its spatial sigma is a multiple of
the projected particle radius (``dataset.bilateral_sigma_px_scale``) and its range sigma a number of
particle radii (``dataset.bilateral_range_radii``): both scale-free, so one setting should serve
every resolution. This prints, for each pair, the mean and median angular error against the
ray-cast mesh of the sphere and the ellipsoid splat at each size, pooled over a few frames of the
scenes' two cameras, with the fixed-size Gaussian beside it. Training scenes only: the held-out
scenes do not choose the parameters. ``--taps`` also sweeps ``dataset.bilateral_max_taps`` (0:
every pixel of the radius), which only matters where the radius is wider than it: large sizes.

    .venv/bin/python benchmarks/tune_bilateral.py [--scenes dam_break pouring] [--sizes 256 1024]
                                                  [--sigmas 1.5] [--ranges 10] [--taps 0 16 8]
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import warp as wp

from pipeline.camera import camera_for_frame
from pipeline.exr import stack
from pipeline.frames import frame_name, load_frame, read_sequence_info, spread
from pipeline.metrics import angular_errors
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.surface import anisotropic_kernels, particle_ellipsoids, reconstruct
from pipeline.views import screen_space_inputs, target_channels
from stages import simulate
from stages.common import StageOptions, make_run

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    parser.add_argument("--scenes", nargs="+", default=["dam_break", "double_pouring", "sphere_crown"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    parser.add_argument("--frames", type=int, default=3, help="frames per scene")
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.75, 1.0, 1.5, 2.0])
    parser.add_argument("--ranges", type=float, nargs="+", default=[1.0, 2.0, 3.0, 6.0])
    parser.add_argument("--taps", type=int, nargs="+", help="max taps a side (default: the config's)")
    args = parser.parse_args()
    wp.config.quiet = True
    run = make_run(StageOptions(config=args.config))
    base = run.config.dataset
    ss, launch = ScreenSpace("cpu"), Launcher("cpu")
    taps = args.taps or [base.bilateral_max_taps]
    settings = [(s, g, t) for s in args.sigmas for g in args.ranges for t in taps]
    errors: dict = {}
    for name in args.scenes:
        scene = run.loaded.scene(name)
        sim = simulate.ensure(run, scene)
        info = read_sequence_info(sim.dir)
        r = info.particle_radius
        picks = spread(list(range(1, info.frames + 1)), args.frames + 2)[1:-1]
        for frame in picks:
            x, _ = load_frame(sim.dir / frame_name(frame))
            kernels = anisotropic_kernels(x, r, base, launch, "cpu")
            ellipsoids = particle_ellipsoids(x, r, base, launch, "cpu", kernels)
            mesh = reconstruct(x, r, base, launch, "cpu", kernels)
            for path in ("static", "orbit"):
                for size in args.sizes:
                    cam = camera_for_frame(scene.cameras, path, frame - 1, info.frames, size, size)
                    tc = target_channels(mesh, cam, launch)
                    target, t_mask = stack(tc, "target.N."), tc["target.A"] > 0
                    for splat, ell in (("sphere", None), ("ellipsoid", ellipsoids)):
                        ch = screen_space_inputs(x, r, cam, base, ss, filters=("gaussian",) if ell is None else None,
                                                 ellipsoids=ell, aniso_filters=())
                        raw = ch["aniso.Z" if ell is not None else "Z"]
                        fluid = raw > 0
                        if ell is None:
                            errors.setdefault((size, splat, "gaussian"), []).append(
                                angular_errors(stack(ch, "gaussian.N."), target, fluid & t_mask))
                        for s, g, t in settings:
                            p = dataclasses.replace(base, bilateral_sigma_px_scale=s, bilateral_range_radii=g,
                                                    bilateral_max_taps=t, width=size, height=size)
                            n = ss.normals(ss.bilateral(raw, cam, r, p), cam)
                            errors.setdefault((size, splat, (s, g, t)), []).append(angular_errors(n, target,
                                                                                                 fluid & t_mask))
        print(f"  {name}: {len(picks)} frames x 2 cameras", flush=True)
    print(f"\nbilateral sigma (x projected radius) / range (radii) / max taps: mean / median angular error (deg) "
          f"vs the mesh; current {base.bilateral_sigma_px_scale} / {base.bilateral_range_radii} / "
          f"{base.bilateral_max_taps}")
    head = "".join(f" {f'{z} {sp[:4]}':>15s}" for z in args.sizes for sp in ("sphere", "ellipsoid"))
    print(f"{'setting':>14s}{head} {'avg mean':>9s}")
    rows = [("gaussian", "gaussian")] + [(f"{s:g} / {g:g} / {t}", (s, g, t)) for s, g, t in settings]
    for label, key in rows:
        cells, means = "", []
        for z in args.sizes:
            for sp in ("sphere", "ellipsoid"):
                got = errors.get((z, sp, key))
                if not got:
                    cells += f" {'':>15s}"
                    continue
                e = np.concatenate(got)
                means.append(float(e.mean()))
                cells += f" {e.mean():7.2f} / {np.median(e):5.2f}"
        print(f"{label:>14s}{cells} {np.mean(means):9.2f}")
    ss.close()
    launch.close()


if __name__ == "__main__":
    main()
