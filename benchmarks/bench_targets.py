"""Marching-cubes mesh target against the ray-traced density target, 256 to 2048 px.

Both come from the same anisotropic kernels. Per frame and size: the angle between the two
targets' normals (where both show fluid), their silhouette IoU, and each one's time per view (the
mesh: density grid + marching cubes + normals, then the ray cast; the ray-traced: the support
splat and the march; the kernels, shared, are timed apart).

    .venv/bin/python benchmarks/bench_targets.py [--sizes 256 512 1024 2048]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dataset import _camera_for, _pbf_frame  # noqa: E402

from pipeline.config import DatasetConfig  # noqa: E402
from pipeline.metrics import angular_errors, iou  # noqa: E402
from pipeline.parallel import Launcher  # noqa: E402
from pipeline.particles import read_particles  # noqa: E402
from pipeline.screen import ScreenSpace  # noqa: E402
from pipeline.surface import anisotropic_kernels, raytrace_maps, reconstruct, render_maps  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _timed(fn):
    start = time.perf_counter()
    out = fn()
    return 1000 * (time.perf_counter() - start), out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    parser.add_argument("--particles", type=int, default=50_000)
    args = parser.parse_args()
    wp.config.quiet = True
    p = DatasetConfig()
    ss, launch = ScreenSpace("cpu"), Launcher("cpu")
    bgeo = ROOT / "tests" / "data" / "dam_break_frame_9_6859_particles.bgeo"
    x_pbf, r_pbf = _pbf_frame(args.particles)
    frames = {"SPlisHSPlasH dam break (6,859)": (read_particles(bgeo).positions, 0.025),
              f"PBF dam break ({len(x_pbf):,})": (x_pbf, r_pbf)}
    print(f"{'frame':32s} {'size':>5s} {'kernels':>8s} {'mesh':>7s} {'cast':>6s} {'raytrace':>9s} "
          f"{'mean deg':>8s} {'median':>7s} {'p95':>6s} {'IoU':>6s}   (ms per view)")
    for name, (x, r) in frames.items():
        x = np.asarray(x, np.float32)
        anisotropic_kernels(x, r, p, launch, "cpu")  # compile
        t_kernels, kernels = _timed(lambda x=x, r=r: anisotropic_kernels(x, r, p, launch, "cpu"))
        t_mesh, mesh = _timed(lambda x=x, r=r, k=kernels: reconstruct(x, r, p, launch, kernels=k))
        for size in args.sizes:
            cam = _camera_for(x, size)
            t_cast, (n_mesh, _, m_mesh) = _timed(lambda mesh=mesh, cam=cam: render_maps(mesh, cam, launch))
            t_ray, (n_ray, _, m_ray, _) = _timed(lambda k=kernels, r=r, cam=cam: raytrace_maps(k, r, p, cam, ss,
                                                                                               launch))
            e = angular_errors(n_ray, n_mesh, (m_ray > 0) & (m_mesh > 0))
            print(f"{name:32s} {size:5d} {t_kernels:8.0f} {t_mesh:7.0f} {t_cast:6.0f} {t_ray:9.0f} "
                  f"{e.mean():8.2f} {np.median(e):7.2f} {np.percentile(e, 95):6.2f} "
                  f"{iou(m_ray > 0, m_mesh > 0):6.3f}", flush=True)
    print("mesh: density grid + marching cubes + gradient normals (once per frame); cast: its ray cast per "
          "view; raytrace: support splat + march per view; kernels: shared by both")
    ss.close()
    launch.close()


if __name__ == "__main__":
    main()
