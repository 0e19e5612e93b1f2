"""The refiner's dataset: screen-space inputs and reference targets of every frame and camera path.

Into one folder: ``<camera>/frame_0001.exr`` per camera path (channels in ``pipeline.views``) and,
with ``dataset.keep_meshes``, ``meshes/frame_0001.ply``. A frame's anisotropic kernels and mesh are
built once and seen from both cameras; frames run in parallel threads on the CPU. The manifest
records say each file's camera, frame, split and share of fluid pixels.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline.cache import atomic_path
from pipeline.camera import camera_for_frame
from pipeline.config import DatasetConfig, SceneConfig
from pipeline.executor import cluster_cpus, run_tasks, shards
from pipeline.exr import read_exr, write_exr
from pipeline.frames import frame_name
from pipeline.parallel import Launcher, init_warp
from pipeline.screen import ScreenSpace
from pipeline.screen import kernels as screen_kernels
from pipeline.surface import anisotropic_kernels, particle_ellipsoids, reconstruct
from pipeline.surface import kernels as surface_kernels
from pipeline.timing import Timings
from pipeline.views import raytraced_target_channels, screen_space_inputs, target_channels

log = logging.getLogger("deep_ssfr")
CAMERAS = ("static", "orbit")


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
    the frames are cut into one shard per CPU of the cluster, each built by a Ray task; ``subset``
    (positions in ``frames``) is what one shard builds."""
    folder = Path(folder)
    if executor != "local":
        shard_of = functools.partial(build_dataset, folder, scene, p, frames, load, radius, device)
        done = run_tasks(lambda sub: shard_of(subset=sub), shards(range(len(frames)), cluster_cpus(executor)),
                         executor, address)
        timings = Timings()
        for t in done:
            timings.merge(t)
        return timings
    workers = 1 if device != "cpu" else (p.workers or os.cpu_count() or 1)
    init_warp((screen_kernels, surface_kernels), device)  # loaded once here, not by the workers at once
    local = _Worker(device, 1 if workers > 1 else 0)
    timings, lock = Timings(), threading.Lock()

    def build(index: int, frame: int) -> None:
        targets = {c: folder / c / frame_name(frame, "exr") for c in CAMERAS}
        if all(t.exists() for t in targets.values()):
            return
        t = Timings()
        x = load(frame)
        with t("anisotropy"):
            kernels = anisotropic_kernels(x, radius, p, local.launch, device)
            ellipsoids = particle_ellipsoids(x, radius, p, local.launch, device, kernels)
        mesh = None
        if p.target == "mesh" or p.keep_meshes:
            mesh = reconstruct(x, radius, p, local.launch, device, kernels)
            t.merge(mesh.timings, skip=("anisotropy",))
        if p.keep_meshes:
            with atomic_path(folder / "meshes" / frame_name(frame, "ply")) as tmp:
                mesh.to_trimesh().export(str(tmp), file_type="ply")
        for cam_path, target in targets.items():
            cam = camera_for_frame(scene.cameras, cam_path, index, len(frames), p.width, p.height)
            channels = screen_space_inputs(x, radius, cam, p, local.ss, t, ellipsoids=ellipsoids)
            if p.target == "raytrace":
                channels.update(raytraced_target_channels(kernels, radius, p, cam, local.ss, local.launch, device, t))
            else:
                channels.update(target_channels(mesh, cam, local.launch, device, t))
            with t("write"):
                write_exr(target, channels)
        with lock:
            timings.merge(t)

    log.info("dataset %s: %d frames x %d cameras at %dx%d, %d workers", scene.name, len(frames), len(CAMERAS),
             p.width, p.height, workers)
    todo = [(i, frames[i]) for i in (range(len(frames)) if subset is None else subset)]
    with ThreadPoolExecutor(workers) as pool, tqdm(total=len(todo), desc=f"dataset {scene.name}",
                                                   unit="frame") as bar:
        for fut in [pool.submit(build, i, f) for i, f in todo]:
            fut.result()
            bar.update()
    return timings


def manifest_records(folder: Path, frames: list[int], validation_camera: str) -> list[dict]:
    """One record per written view: file, camera path, frame, index on the path, split ('val' for
    the validation camera path) and share of fluid pixels. Whole held-out scenes are applied by
    the consumers, so changing them does not invalidate a dataset."""
    records = []
    for cam_path in CAMERAS:
        for i, frame in enumerate(frames):
            name = f"{cam_path}/{frame_name(frame, 'exr')}"
            mask = read_exr(Path(folder) / name, ["A"])["A"]
            records.append({"file": name, "camera": cam_path, "frame": frame, "index": i,
                            "split": "val" if cam_path == validation_camera else "train",
                            "fluid_share": round(float(mask.mean()), 5)})
    return records
