"""``make dataset``: generator inputs and mesh targets for every frame and camera, as EXR.

Writes ``data/dataset/<scene>-<key>/<camera>/frame_0001.exr`` (channels in ``pipeline.views``),
optional ``meshes/frame_0001.ply`` and a manifest listing each file with its split and fluid
share. The target mesh of a frame is built once and ray-cast from both cameras.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

from tqdm import tqdm

from pipeline import cache
from pipeline.camera import camera_for_frame
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.exr import read_exr, write_exr
from pipeline.frames import frame_name, load_frame, read_sequence_info
from pipeline.parallel import Launcher, init_warp
from pipeline.screen import ScreenSpace
from pipeline.screen import kernels as screen_kernels
from pipeline.surface import anisotropic_kernels, particle_ellipsoids, reconstruct
from pipeline.surface import kernels as surface_kernels
from pipeline.timing import Timings
from pipeline.views import raytraced_target_channels, screen_space_inputs, target_channels
from stages import simulate
from stages.common import Run, make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")
CAMERAS = ("static", "orbit")


def dataset_frames(run: Run, n_frames: int) -> list[int]:
    """The simulated frame numbers the dataset uses (stride, then cap)."""
    p = run.config.dataset
    frames = list(range(1, n_frames + 1, p.frame_stride))
    return frames[: p.max_frames] if p.max_frames else frames


def split_of(run: Run, camera: str) -> str:
    """'val' for the validation camera path, else 'train'. Whole held-out scenes
    (``dataset.holdout_scenes``) are applied by the consumers, so changing them does not
    invalidate the dataset."""
    return "val" if camera == run.config.dataset.validation_camera else "train"


def dataset_entry(run: Run, scene: SceneConfig, sim_key: str) -> cache.CacheEntry:
    """Cache entry keyed on the dataset config, the scene's cameras and the simulation."""
    params = to_dict(run.config.dataset)
    for key in ("holdout_scenes", "workers"):  # these change no file of the entry
        params.pop(key)
    config = {"dataset": params, "cameras": to_dict(scene.cameras)}
    return cache.entry(run.data_dir, "dataset", scene.name, config, {"simulate": sim_key}, run.device)


class _Worker(threading.local):
    """Per-thread kernels runners (frames are processed in parallel)."""

    def __init__(self, device: str, threads: int):
        self.ss = ScreenSpace(device, threads)
        self.launch = Launcher(device, threads)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """The complete dataset entry of a scene, building what is missing."""
    sim = simulate.ensure(run, scene)
    entry = dataset_entry(run, scene, sim.key)
    if entry.is_complete() and not force:
        log.info("dataset %s: cached (%s)", scene.name, entry.dir)
        return entry
    entry.begin(force=force)
    p = run.config.dataset
    info = read_sequence_info(sim.dir)
    frames = dataset_frames(run, info.frames)
    device = warp_device(run.device)
    workers = p.workers or os.cpu_count() or 1
    workers = 1 if device != "cpu" else workers
    # Warp initialised and the kernels loaded here, not by the workers at once
    init_warp((screen_kernels, surface_kernels), device)
    local = _Worker(device, 1 if workers > 1 else 0)
    timings = Timings()
    lock = threading.Lock()

    def build(index: int, frame: int) -> None:
        targets = {c: entry.path(f"{c}/{frame_name(frame, 'exr')}") for c in CAMERAS}
        if all(t.exists() for t in targets.values()):
            return
        t = Timings()
        x, _ = load_frame(sim.path(frame_name(frame)))
        r = info.particle_radius
        with t("anisotropy"):
            kernels = anisotropic_kernels(x, r, p, local.launch, device)
            ellipsoids = particle_ellipsoids(x, r, p, local.launch, device, kernels)
        mesh = None
        if p.target == "mesh" or p.keep_meshes:
            mesh = reconstruct(x, r, p, local.launch, device, kernels)
            for name, sec in mesh.timings.total.items():
                if name != "anisotropy":
                    t.total[name] += sec
                    t.count[name] += 1
        if p.keep_meshes:
            with cache.atomic_path(entry.path(f"meshes/{frame_name(frame, 'ply')}")) as tmp:
                mesh.to_trimesh().export(str(tmp), file_type="ply")
        for cam_path, target in targets.items():
            cam = camera_for_frame(scene.cameras, cam_path, index, len(frames), p.width, p.height)
            channels = screen_space_inputs(x, r, cam, p, local.ss, t, ellipsoids=ellipsoids)
            if p.target == "raytrace":
                channels.update(raytraced_target_channels(kernels, r, p, cam, local.ss, local.launch, device, t))
            else:
                channels.update(target_channels(mesh, cam, local.launch, device, t))
            with t("write"):
                write_exr(target, channels)
        with lock:
            for k, v in t.total.items():
                timings.total[k] += v
                timings.count[k] += t.count[k]

    log.info("dataset %s: %d frames x %d cameras at %dx%d, %d workers", scene.name, len(frames), len(CAMERAS),
             p.width, p.height, workers)
    start = time.perf_counter()
    with ThreadPoolExecutor(workers) as pool, tqdm(total=len(frames), desc=f"dataset {scene.name}",
                                                   unit="frame") as bar:
        futures = [pool.submit(build, i, f) for i, f in enumerate(frames)]
        for fut in futures:
            fut.result()
            bar.update()
    records = []
    for cam_path in CAMERAS:
        for i, frame in enumerate(frames):
            name = f"{cam_path}/{frame_name(frame, 'exr')}"
            mask = read_exr(entry.path(name), ["A"])["A"]
            records.append({"file": name, "camera": cam_path, "frame": frame, "index": i,
                            "split": split_of(run, cam_path),
                            "fluid_share": round(float(mask.mean()), 5)})
    entry.finish([r["file"] for r in records], timings.as_dict(), frames=records,
                 particle_radius=info.particle_radius, width=p.width, height=p.height,
                 wall_seconds=round(time.perf_counter() - start, 2))
    log.info("dataset %s: %d EXR files in %.1f s (%s) -> %s", scene.name, len(records),
             time.perf_counter() - start,
             ", ".join(f"{k} {1000 * v / max(timings.count[k], 1):.0f} ms" for k, v in timings.total.items()),
             entry.dir)
    empty = [r["file"] for r in records if r["fluid_share"] == 0]
    if empty:
        log.warning("dataset %s: %d views show no fluid (e.g. %s)", scene.name, len(empty), empty[0])
    return entry


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make dataset``."""
    run = make_run(parse_args("dataset", argv))
    for scene in run.loaded.scenes.values():
        ensure(run, scene, force=run.force)


if __name__ == "__main__":
    sys.exit(stage_main("dataset", main))
