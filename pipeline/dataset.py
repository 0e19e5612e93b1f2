"""The refiner's dataset: screen-space inputs and reference targets of every frame and camera path.

Into one folder: ``<camera>/frame_0001.exr`` per camera path (channels in ``pipeline.views``) and,
with ``dataset.keep_meshes``, ``meshes/frame_0001.ply``. With ``dataset.random_views`` each frame is
also seen from that many random cameras (``random/frame_0001_v0.exr``...: training views of the
ellipsoid splat at random sizes, distances and particle sizes on screen). A frame's anisotropic
kernels and mesh are built once and seen from every camera; frames run in parallel threads on the
CPU. Every view's header holds its camera and ``particleRadius``. The manifest records say each
file's camera, frame, split and share of fluid pixels.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import warp as wp
from tqdm import tqdm

from pipeline.cache import atomic_path
from pipeline.camera import Camera, camera_for_frame, random_view
from pipeline.config import DatasetConfig, SceneConfig
from pipeline.executor import run_sharded
from pipeline.exr import camera_attributes, read_exr, read_exr_header, write_exr
from pipeline.frames import frame_name
from pipeline.parallel import Launcher, init_warp
from pipeline.screen import ScreenSpace
from pipeline.screen import kernels as screen_kernels
from pipeline.surface import anisotropic_kernels, particle_ellipsoids, reconstruct
from pipeline.surface import kernels as surface_kernels
from pipeline.timing import Timings
from pipeline.views import raytraced_target_channels, screen_space_inputs, target_channels
from pipeline.writer import BackgroundWriter

log = logging.getLogger("deep_ssfr")
CAMERAS = ("static", "orbit")
RANDOM = "random"
"""Folder of the random training views."""


def random_view_name(frame: int, view: int) -> str:
    """``random/frame_0001_v0.exr``: random view ``view`` of ``frame``."""
    return f"{RANDOM}/{frame_name(frame, 'exr')[:-4]}_v{view}.exr"


def view_attributes(camera: Camera, radius: float, mask: np.ndarray) -> dict:
    """Header of a dataset view: the camera (standard attributes) and the particle radius, from which
    the refiner's inputs express depths in radii and sizes in projected radii, and the share of its
    pixels that are fluid (``mask``), which the manifest reads without decompressing the view."""
    return {**camera_attributes(camera), "particleRadius": float(radius), "fluidShare": fluid_share(mask)}


def fluid_share(mask: np.ndarray) -> float:
    """The share of fluid pixels of a view's mask, as the manifest records it."""
    return round(float(mask.mean()), 5)


def random_cameras(scene: str, frame: int, x: np.ndarray, radius: float, p: DatasetConfig) -> list[Camera]:
    """The random cameras of one frame, seeded by ``view_seed``, the scene name, frame and view."""
    return [random_view(x, radius, np.random.default_rng([p.view_seed, zlib.crc32(scene.encode()), frame, k]),
                        p.random_radius_px, p.random_size, p.random_fov_deg, p.random_elevation_deg)
            for k in range(p.random_views)]


class _Abandoned(Exception):
    """A frame left at a step boundary because the build is ending (Ctrl-C or another frame's error)."""


class _Worker(threading.local):
    """Per-thread kernel runners (frames are processed in parallel)."""

    def __init__(self, device: str, threads: int):
        self.ss = ScreenSpace(device, threads)
        self.launch = Launcher(device, threads)


def build_dataset(folder: Path, scene: SceneConfig, p: DatasetConfig, frames: list[int],
                  load: Callable[[int], np.ndarray], radius: float, device: str, executor: str = "local",
                  address: str = "", subset: list[int] | None = None) -> Timings:
    """Write the views of every frame not yet written (a killed run resumes); returns the timings.

    ``load(frame)`` gives a frame's positions; ``device`` is a Warp device. With ``executor='ray'``
    the frames are cut into one shard per CPU (or GPU) of the cluster, each built by a Ray task; ``subset``
    (positions in ``frames``) is what one shard builds."""
    folder = Path(folder)
    if executor != "local":
        shard_of = functools.partial(build_dataset, folder, scene, p, frames, load, radius, device)
        done = run_sharded(lambda sub: shard_of(subset=sub), len(frames), executor, address, device)
        timings = Timings()
        for t in done:
            timings.merge(t)
        return timings
    workers = 1 if device != "cpu" else (p.workers or os.cpu_count() or 1)
    init_warp((screen_kernels, surface_kernels), device)  # loaded once here, not by the workers at once
    local = _Worker(device, 1 if workers > 1 else 0)
    timings, lock = Timings(), threading.Lock()
    stop = threading.Event()  # set on Ctrl-C or a failed frame: the frames in flight end at their next step
    # One worker (a GPU): the views' EXRs are compressed on a background thread while the device makes
    # the next views. Several CPU workers write their own: they keep the cores busy already.
    writer = BackgroundWriter() if workers == 1 else None
    writer_timings = Timings()

    def write_view(t: Timings, target: Path, channels: dict[str, np.ndarray], attributes: dict) -> None:
        with t("write"):
            write_exr(target, channels, attributes=attributes)

    def check() -> None:
        if stop.is_set():
            raise _Abandoned  # this frame's views written so far stay; a resume builds the rest

    def build(index: int, frame: int) -> None:
        targets = {c: folder / c / frame_name(frame, "exr") for c in CAMERAS}
        randoms = [folder / random_view_name(frame, k) for k in range(p.random_views)]
        if all(t.exists() for t in [*targets.values(), *randoms]):
            return
        t = Timings()
        x = load(frame)
        check()
        with t("anisotropy"):
            kernels = anisotropic_kernels(x, radius, p, local.launch, device)
            ellipsoids = particle_ellipsoids(x, radius, p, local.launch, device, kernels, density=True)
        check()
        mesh = None
        if p.target == "mesh" or p.keep_meshes:
            mesh = reconstruct(x, radius, p, local.launch, device, kernels)
            t.merge(mesh.timings, skip=("anisotropy",))
            check()
        if p.keep_meshes:
            with atomic_path(folder / "meshes" / frame_name(frame, "ply")) as tmp:
                mesh.to_trimesh().export(str(tmp), file_type="ply")
        views = [(camera_for_frame(scene.cameras, c, index, len(frames), p.width, p.height), path, True)
                 for c, path in targets.items()]
        views += [(cam, path, False) for cam, path in zip(random_cameras(scene.name, frame, x, radius, p), randoms,
                                                          strict=True)]
        # on a GPU the positions go up once for every view's sphere splat, which moves them into view
        # space there (on the host: 4 ms a view for 49k particles, and an upload each)
        x_views = wp.array(np.asarray(x, np.float32), dtype=wp.vec3, device=device) if device != "cpu" else x
        for cam, target, every_filter in views:
            check()
            if target.exists():
                continue
            # random views are for training: the ellipsoid splat and its bilateral filter (and the
            # sphere splat's, for a refiner on spheres)
            spheres = ("bilateral",) if p.random_view_spheres else None
            channels = screen_space_inputs(x_views, radius, cam, p, local.ss, t, ellipsoids=ellipsoids,
                                           **({} if every_filter else {"filters": spheres,
                                                                       "aniso_filters": ("bilateral",)}))
            if p.target == "raytrace":
                channels.update(raytraced_target_channels(kernels, radius, p, cam, local.ss, local.launch, device, t))
            else:
                channels.update(target_channels(mesh, cam, local.launch, device, t))
            attributes = view_attributes(cam, radius, channels["A" if every_filter else "aniso.A"])
            if writer is None:
                write_view(t, target, channels, attributes)
            else:
                writer.submit(write_view, writer_timings, target, channels, attributes)
        with lock:
            timings.merge(t)

    log.info("dataset %s: %d frames x %d cameras at %dx%d, %d workers", scene.name, len(frames), len(CAMERAS),
             p.width, p.height, workers)
    todo = [(i, frames[i]) for i in (range(len(frames)) if subset is None else subset)]
    pool = ThreadPoolExecutor(workers)
    try:
        with tqdm(total=len(todo), desc=f"dataset {scene.name}", unit="frame") as bar:
            for fut in [pool.submit(build, i, f) for i, f in todo]:
                fut.result()
                bar.update()
    except BaseException:  # a failed frame or Ctrl-C: frames not begun are dropped, those in flight stop
        stop.set()
        pool.shutdown(wait=True, cancel_futures=True)
        if writer is not None:
            writer.cancel()
        raise
    pool.shutdown()
    if writer is not None:
        writer.close()  # every queued view written (or its error raised) before the manifest
    timings.merge(writer_timings)
    return timings


def manifest_records(folder: Path, frames: list[int], validation_camera: str, random_views: int = 0) -> list[dict]:
    """One record per written view: file, camera path ('random' for the random views), frame, index on
    the path, split ('val' for the validation camera path, 'train' for random views) and share of
    fluid pixels. Whole held-out scenes are applied by
    the consumers, so changing them does not invalidate a dataset."""

    def share(name: str, mask: str) -> float:
        """The view's fluid share from its header (the mask itself for a view written without it)."""
        header = read_exr_header(Path(folder) / name)
        if "fluidShare" in header:
            return float(header["fluidShare"])
        return fluid_share(read_exr(Path(folder) / name, [mask])[mask])

    records = []
    for cam_path in CAMERAS:
        for i, frame in enumerate(frames):
            name = f"{cam_path}/{frame_name(frame, 'exr')}"
            records.append({"file": name, "camera": cam_path, "frame": frame, "index": i,
                            "split": "val" if cam_path == validation_camera else "train",
                            "fluid_share": share(name, "A")})
    for k in range(random_views):
        for i, frame in enumerate(frames):
            name = random_view_name(frame, k)
            records.append({"file": name, "camera": RANDOM, "frame": frame, "index": i, "view": k, "split": "train",
                            "fluid_share": share(name, "aniso.A")})
    return records
