"""Dataset-stage costs: screen-space inputs per frame at 512^2 and 1024^2, and the anisotropic mesh
target (kernels, density grid, marching cubes, normals, ray casting) against pysplashsurf's
isotropic reconstruction of the same particles at the same cube size.

Frames: the SPlisHSPlasH dam break (6,859 particles, BGEO) and a 50k-particle PBF dam break.

    .venv/bin/pip install -e '.[bench]'   # pysplashsurf
    .venv/bin/python benchmarks/bench_dataset.py
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import warp as wp

from pipeline.camera import Camera, look_at
from pipeline.config import Cameras, DatasetConfig, FluidShape, SceneConfig, SimulateConfig, from_dict
from pipeline.device import choose_device, warp_device
from pipeline.parallel import Launcher
from pipeline.particles import read_particles
from pipeline.screen import ScreenSpace
from pipeline.sim.pbf import PBFSolver
from pipeline.surface import particle_ellipsoids, reconstruct, render_maps

ROOT = Path(__file__).resolve().parents[1]


def _ms(fn, repeat=3):
    fn()
    start = time.perf_counter()
    for _ in range(repeat):
        out = fn()
    return 1000 * (time.perf_counter() - start) / repeat, out


def _camera_for(x: np.ndarray, size: int) -> Camera:
    lo, hi = x.min(0), x.max(0)
    centre = (lo + hi) / 2
    extent = float(np.linalg.norm(hi - lo))
    return Camera(look_at(centre + np.array([0.0, 0.35, 1.0]) * 1.3 * extent, centre), 40.0, size, size)


def _pbf_frame(n: int) -> tuple[np.ndarray, float]:
    """Positions and radius of a PBF dam break of about ``n`` particles, half a second in."""
    x, _, radius = _pbf_state(n)
    return x, radius


def _pbf_state(n: int) -> tuple[np.ndarray, np.ndarray, float]:
    """``_pbf_frame`` with the particles' velocities (m/s)."""
    block = (0.5, 0.7, 0.8)
    radius = 0.5 * (np.prod(block) / n) ** (1 / 3)
    cams = from_dict(Cameras, {"static": {"eye": [0, 0, 3], "target": [0, 0, 0]}, "orbit": {"target": [0, 0, 0]}})
    scene = SceneConfig(name="bench", cameras=cams, domain_hi=(1.6, 1.2, 0.8),
                        fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=block),))
    solver = PBFSolver(scene, SimulateConfig(particle_radius=float(radius)), "cpu", seed=0)
    for f in range(1, 16):  # half a second: the column is collapsing
        solver.advance_frame(f)
    x, v = solver.state()
    solver.close()
    return x, v, float(radius)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50_000)
    parser.add_argument("--exact", action="store_true", help="the exact (pre-2026-11) filters instead of the fast")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="where Warp runs (auto: CUDA when Warp and torch see a GPU; run cpu and cuda for both)")
    args = parser.parse_args()
    wp.config.quiet = True
    device = warp_device(choose_device(args.device))
    p = DatasetConfig(filter_mode="exact" if args.exact else "fast")
    ss, launch = ScreenSpace(device), Launcher(device)
    bgeo = ROOT / "tests" / "data" / "dam_break_frame_9_6859_particles.bgeo"
    frames = {"splishsplash dam break (6,859)": (read_particles(bgeo).positions, 0.025)}
    x50, r50 = _pbf_frame(args.particles)
    frames[f"PBF dam break ({len(x50):,})"] = (x50, r50)

    where = "CUDA" if device != "cpu" else f"CPU, {launch.threads} threads"
    print(f"screen-space inputs on {where}, ms per frame ({p.filter_mode} filters)")
    print(f"{'frame':34s} {'size':>6s} {'splat':>7s} {'bilat':>7s} {'nrf':>7s} {'normals':>8s} {'ellipsoids':>10s} "
          f"{'ell. splat':>10s}")
    for name, (x, r) in frames.items():
        t_ell, ell = _ms(lambda x=x, r=r: particle_ellipsoids(x, r, p, launch))
        for size in (512, 1024):
            cam = _camera_for(x, size)
            t_splat, sp = _ms(lambda x=x, r=r, cam=cam: ss.splat(x, r, cam))
            t_bil, d = _ms(lambda sp=sp, cam=cam, r=r: ss.bilateral(sp.depth, cam, r, p))
            t_nrf, _ = _ms(lambda sp=sp, cam=cam, r=r: ss.narrow_range(sp.depth, cam, r, p))
            t_n, _ = _ms(lambda d=d, cam=cam: ss.normals(d, cam))
            t_esplat, _ = _ms(lambda ell=ell, cam=cam: ss.splat_ellipsoids(ell, cam))
            print(f"{name:34s} {size:6d} {t_splat:7.1f} {t_bil:7.1f} {t_nrf:7.1f} {t_n:8.1f} {t_ell:10.1f} "
                  f"{t_esplat:10.1f}")
    print("(ellipsoids: the anisotropy per frame, shared by every view; ell. splat: depth, thickness and the "
          "analytic normals of the ellipsoids)")

    try:
        import pysplashsurf
    except ImportError:
        pysplashsurf = None
        print("\npysplashsurf not installed (pip install -e '.[bench]'): no comparison")
    print("\nmesh target, seconds per frame")
    print(f"{'frame':34s} {'aniso':>6s} {'grid':>6s} {'mc':>6s} {'normal':>6s} {'ray512':>7s} {'total':>6s} "
          f"{'splash':>7s} {'ratio':>6s}")
    for name, (x, r) in frames.items():
        reconstruct(x, r, p, launch)  # warm-up (compilation)
        start = time.perf_counter()
        mesh = reconstruct(x, r, p, launch)
        total = time.perf_counter() - start
        cam = _camera_for(x, 512)
        t_ray, _ = _ms(lambda mesh=mesh, cam=cam: render_maps(mesh, cam, launch), repeat=2)
        t = mesh.timings.total
        splash = float("nan")
        if pysplashsurf is not None:
            cube = r / p.grid_cells_per_radius
            kw = dict(particle_radius=r, smoothing_length=2.0 * r, cube_size=cube, iso_surface_threshold=0.6)
            pysplashsurf.reconstruct_surface(x.astype(np.float64), **kw)
            start = time.perf_counter()
            pysplashsurf.reconstruct_surface(x.astype(np.float64), **kw)
            splash = time.perf_counter() - start
        print(f"{name:34s} {t['anisotropy']:6.2f} {t['density']:6.2f} {t['marching_cubes']:6.2f} "
              f"{t['normals']:6.2f} {t_ray / 1000:7.3f} {total:6.2f} {splash:7.2f} {total / splash:6.2f}x")
    print(f"(ours: anisotropic kernels, {p.grid_cells_per_radius} cells per radius, analytic normals; "
          "splashsurf: isotropic, same cube size, both on 2 threads)")

    # marching cubes: scikit-image against Warp's IsoSurfaceMarchingCubes on the same density grid
    from skimage import measure
    from warp.geometry import IsoSurfaceMarchingCubes

    from pipeline.surface import anisotropic_kernels, density_grid

    print("\nmarching cubes on the anisotropic density grid, seconds")
    for name, (x, r) in frames.items():
        centres, g, ext = anisotropic_kernels(x, r, p, launch, device)
        field, _ = density_grid(centres, g, ext, (2 * r) ** 3, r / p.grid_cells_per_radius, launch, device)
        grid = field.numpy()  # scikit-image's copy on the host (on the CPU a view)
        t_sk, (v, f, _, _) = _ms(lambda grid=grid: measure.marching_cubes(grid, p.iso_level), repeat=2)
        t_wp, (wv, wf) = _ms(lambda field=field: IsoSurfaceMarchingCubes.extract(field, p.iso_level), repeat=2)
        print(f"{name:34s} grid {'x'.join(map(str, grid.shape)):>12s}  scikit-image {t_sk / 1000:5.2f} "
              f"({len(f):,} tris)  warp {t_wp / 1000:5.2f} ({len(wf) // 3:,} tris)")
    ss.close()
    launch.close()


if __name__ == "__main__":
    main()
