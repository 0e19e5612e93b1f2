"""``make dataset``: generator inputs and reference targets for every frame and camera, as EXR.

Writes ``data/dataset/<scene>-<key>/<camera>/frame_0001.exr`` (``pipeline.dataset``) and a manifest
listing each file with its split and fluid share.
"""

from __future__ import annotations

import dataclasses
import logging
import time

from pipeline import cache
from pipeline.config import DatasetConfig, SceneConfig, to_dict
from pipeline.dataset import build_dataset, manifest_records
from pipeline.device import warp_device
from pipeline.frames import frame_name, load_frame, read_sequence_info, select_frames
from stages import simulate
from stages.common import Run, StageOptions, make_run

log = logging.getLogger("deep_ssfr")


def scene_params(run: Run, scene: SceneConfig) -> DatasetConfig:
    """The dataset parameters of a scene: random training views only for simulated scenes that train
    or validate; a held-out scene that is only evaluated, and an imported sequence, get their two
    camera paths (the recipe the shipped weights were trained with)."""
    p, t = run.config.dataset, run.config.train
    evaluated_only = scene.name in p.holdout_scenes and scene.name not in t.validation_scenes
    # without random views their splats change no file: such entries are shared by configs that differ there
    return dataclasses.replace(p, random_views=0, random_view_spheres=False) if evaluated_only or scene.source else p


def dataset_entry(run: Run, scene: SceneConfig, sim_key: str) -> cache.CacheEntry:
    """Cache entry keyed on the dataset config, the scene's cameras and the simulation."""
    params = to_dict(scene_params(run, scene))
    for key in ("holdout_scenes", "workers"):  # these change no file of the entry
        params.pop(key)
    config = {"dataset": params, "cameras": to_dict(scene.cameras)}
    return cache.entry(run.data_dir, "dataset", scene.name, config, {"simulate": sim_key}, run.device)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """The complete dataset entry of a scene, building what is missing."""
    sim = simulate.ensure(run, scene)
    entry = dataset_entry(run, scene, sim.key)
    if not entry.begin(force=force):
        log.info("dataset %s: cached (%s)", scene.name, entry.dir)
        return entry
    p = scene_params(run, scene)
    info = read_sequence_info(sim.dir)
    frames = select_frames(info.frames, p.frame_stride, p.max_frames)
    start = time.perf_counter()
    sim_dir = sim.dir  # the tasks carry a path, not the entry
    timings = build_dataset(entry.dir, scene, p, frames, lambda f: load_frame(sim_dir / frame_name(f))[0],
                            info.particle_radius, warp_device(run.device), run.config.executor, run.config.ray_address)
    records = manifest_records(entry.dir, frames, p.validation_camera, p.random_views)
    wall = time.perf_counter() - start
    entry.finish([r["file"] for r in records], timings.as_dict(), frames=records,
                 particle_radius=info.particle_radius, width=p.width, height=p.height, wall_seconds=round(wall, 2))
    log.info("dataset %s: %d EXR files in %.1f s (%s) -> %s", scene.name, len(records), wall,
             ", ".join(f"{k} {v:.0f} ms" for k, v in timings.per_call_ms().items()), entry.dir)
    empty = [r["file"] for r in records if r["fluid_share"] == 0]
    if empty:
        log.warning("dataset %s: %d views show no fluid (e.g. %s)", scene.name, len(empty), empty[0])
    return entry


def main(opts: StageOptions) -> None:
    """``deep-ssfr dataset``: every configured scene."""
    run = make_run(opts)
    scenes = list(run.loaded.scenes.values())
    simulate.ahead(run, scenes)
    for scene in scenes:
        ensure(run, scene, force=run.force)
