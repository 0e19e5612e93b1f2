"""The metaball dataset: network inputs and ray-marched G-buffers, one EXR per view.

Fluid views: each chosen frame of a scene seen from ``metaball.views_per_frame`` random cameras
(``pipeline.camera.random_view`` at ``metaball.size``, the dataset's field of view and elevation
ranges, particles within half an octave of ``metaball.working_radius_px`` on screen, or the dataset's
range without a working radius), its particles as metaballs in the working frame
(``pipeline.metaball.views``; with ``metaball.anisotropic`` the particles' ellipsoids), drawn at the
working scale. Random sets: the thesis' random balls,
each rendered ``metaball.repeats`` times with small offsets. Every EXR holds ``view_channels`` (the
target depth in scene units) and, in its header, the camera, ``metaballScale`` and the depth code's
``metaballNear`` / ``metaballFar`` (working units), from which ``training_pair`` encodes the target.
"""

from __future__ import annotations

import dataclasses
import threading
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.camera import Camera, random_view
from pipeline.config import DatasetConfig, MetaballConfig
from pipeline.exr import camera_attributes, read_exr, read_exr_header, write_exr
from pipeline.metaball import MetaballParams, encode_targets, input_names, paper_camera, view_channels
from pipeline.metaball import kernels as metaball_kernels
from pipeline.metaball.views import (
    WorkingView,
    fluid_view,
    jittered,
    network_input,
    params_of,
    random_ball_set,
    working_view,
)
from pipeline.parallel import Launcher, init_warp
from pipeline.surface import particle_ellipsoids


def fluid_view_name(frame: int, view: int) -> str:
    """``frame_0001_v0.exr``: random view ``view`` of ``frame``."""
    return f"frame_{frame:04d}_v{view}.exr"


def set_view_name(index: int, repeat: int) -> str:
    """``set_0001_r0.exr``: rendering ``repeat`` of random set ``index``."""
    return f"set_{index:04d}_r{repeat}.exr"


def fluid_cameras(scene: str, frame: int, x: np.ndarray, radius: float, m: MetaballConfig,
                  d: DatasetConfig) -> list[Camera]:
    """The random cameras of one frame (seeded by ``metaball.seed``, the scene, frame and view)."""
    w = m.working_radius_px
    radius_px = (w / 2.0**0.5, w * 2.0**0.5) if w else d.random_radius_px
    return [random_view(x, radius, np.random.default_rng([m.seed, zlib.crc32(scene.encode()), frame, k]),
                        radius_px, (m.size, m.size), d.random_fov_deg, d.random_elevation_deg)
            for k in range(m.views_per_frame)]


def write_view(path: Path, view: WorkingView, world_camera: Camera, launch: Launcher, radius: float, kind: str,
               colours: np.ndarray | None = None) -> float:
    """Render one view's input of ``kind`` and its targets into ``path`` (atomically), at the working
    scale; returns its surface share."""
    targets = view.targets(launch, colours)
    inputs = view.inputs(kind, launch, colours)
    p = view.params
    attributes = {**camera_attributes(world_camera), "particleRadius": float(radius),
                  "metaballScale": float(view.scale), "metaballNear": float(p.depth_near),
                  "metaballFar": float(p.depth_far)}
    write_exr(path, view_channels(targets, inputs, kind), attributes=attributes)
    return float(targets["mask"].mean())


def _pool(workers: int, device: str, jobs: list[Callable[[Launcher], None]], desc: str) -> None:
    """Run ``jobs`` over ``workers`` threads, each with its own launcher, with a progress bar."""
    init_warp((metaball_kernels,), device)
    local, made = threading.local(), []

    def run(job):
        if not hasattr(local, "launch"):
            local.launch = Launcher(device, 1 if workers > 1 else 0)
            made.append(local.launch)
        job(local.launch)

    try:
        with ThreadPoolExecutor(workers) as pool, tqdm(total=len(jobs), desc=desc, unit="view") as bar:
            for fut in [pool.submit(run, j) for j in jobs]:
                fut.result()
                bar.update()
    finally:
        for launch in made:
            launch.close()


def build_fluid_views(folder: Path, scene: str, frames: list[int], load: Callable[[int], np.ndarray], radius: float,
                      m: MetaballConfig, d: DatasetConfig, device: str, workers: int) -> list[dict]:
    """Write every fluid view not yet written (a killed run resumes); returns the manifest records."""
    records, jobs = [], []
    launch = Launcher(device) if m.anisotropic else None
    try:
        for frame in frames:
            x = load(frame)
            cams = fluid_cameras(scene, frame, x, radius, m, d)
            paths = [folder / fluid_view_name(frame, k) for k in range(len(cams))]
            records += [{"file": path.name, "frame": frame, "view": k} for k, path in enumerate(paths)]
            if all(path.exists() for path in paths):
                continue
            # the mesh's ellipsoids, shared by the frame's views (made on the host for the worker threads)
            ell = particle_ellipsoids(x, radius, d, launch, on_device=False) if launch is not None else None
            for cam, path in zip(cams, paths, strict=True):
                if not path.exists():
                    jobs.append(lambda launch, x=x, cam=cam, path=path, ell=ell: write_view(
                        path, fluid_view(x, radius, cam, m, ell), cam, launch, radius, m.input))
    finally:
        if launch is not None:
            launch.close()
    _pool(workers, device, jobs, f"metaball {scene}")
    return records


def build_random_sets(folder: Path, m: MetaballConfig, device: str, workers: int) -> list[dict]:
    """Write the thesis' random ball sets (``metaball.random_sets`` x ``repeats``); returns the records."""
    records, jobs = [], []
    cam = paper_camera(m.size, m.size)
    for index in range(m.random_sets):
        rng = np.random.default_rng([m.seed, 1, index])
        positions, radii, colours = random_ball_set(rng, m.max_balls)
        for r in range(m.repeats):
            path = folder / set_view_name(index, r)
            moved = jittered(positions, radii, rng) if r else positions
            records.append({"file": path.name, "set": index, "repeat": r})
            if not path.exists():
                jobs.append(lambda launch, moved=moved, radii=radii, colours=colours, path=path: write_view(
                    path, working_view(moved, radii, cam, m), cam, launch, float(np.median(radii)), m.input,
                    colours))
    _pool(workers, device, jobs, "metaball random sets")
    return records


def view_params(header: dict, m: MetaballConfig) -> MetaballParams:
    """The parameters of one dataset view: ``m``'s, with the depth code its header records."""
    return dataclasses.replace(params_of(m, float(header["metaballNear"])), depth_far=float(header["metaballFar"]))


def training_pair(path: Path, m: MetaballConfig) -> tuple[np.ndarray, np.ndarray]:
    """(4 x H x W input of ``metaball.input``, 7 x H x W encoded target), both in [0, 1], of one
    dataset view."""
    ch = read_exr(path)
    header = read_exr_header(path)
    circles = network_input(np.stack([ch[name] for name in input_names(m.input)]), m)
    targets = {"colour": np.stack([ch[f"metaball.{c}"] for c in "RGB"], -1),
               "depth": ch["metaball.Z"] * float(header["metaballScale"]),
               "normals": np.stack([ch[f"metaball.N.{c}"] for c in "XYZ"], -1), "mask": ch["metaball.A"]}
    return circles, encode_targets(targets, view_params(header, m))
