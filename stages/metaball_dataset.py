"""``make metaball-dataset``: circle inputs and ray-marched metaball G-buffers for the pix2pix network.

Writes ``data/metaball_dataset/<scene>-<key>/frame_0001_v0.exr`` for every training and validation
scene (held-out scenes are never rendered here) and, with ``metaball.random_sets``,
``data/metaball_dataset/random_sets-<key>/set_0001_r0.exr`` (``pipeline.metaball.dataset``), each
with a manifest of its views and their surface shares.
"""

from __future__ import annotations

import logging
import os
import time

from pipeline import cache
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.frames import frame_name, load_frame, read_sequence_info, select_frames
from pipeline.metaball.dataset import build_fluid_views, build_random_sets
from stages import simulate
from stages.common import Run, StageError, StageOptions, make_run, train_scenes

log = logging.getLogger("deep_ssfr")
RANDOM_SETS = "random_sets"
"""Entry name of the thesis' random ball sets."""

_VIEW_KEYS = ("random_radius_px", "random_fov_deg", "random_elevation_deg", "aniso_smoothing", "aniso_kr",
              "aniso_ks", "aniso_kn", "aniso_neps", "aniso_kernel_radius")
"""The dataset's random-camera ranges and anisotropy (the ellipsoids), which the fluid views share."""


def roles(run: Run) -> tuple[list[SceneConfig], list[SceneConfig]]:
    """(training scenes, validation scenes): the configured scenes outside ``dataset.holdout_scenes``
    (or ``train.train_scenes``) train; ``train.validation_scenes`` validate. Other held-out scenes are
    never rendered for the network."""
    cfg = run.config
    scenes = run.loaded.scenes
    train = [scenes[s] for s in train_scenes(run)]
    val = [scenes[s] for s in cfg.train.validation_scenes if s in scenes]
    if not train and not cfg.metaball.random_sets:
        raise StageError("no metaball training views: no training scene and metaball.random_sets is 0")
    return train, val


VIEW_FIELDS = ("ball_radius_radii", "iso_level", "kernel_radius_radii", "working_ball_radius", "depth_margin",
               "depth_span", "step", "bisections", "outline_width", "outline_min_px", "input", "splat_radius",
               "field_steps", "working_radius_px", "size", "frame_stride", "max_frames", "views_per_frame",
               "random_sets", "repeats", "max_balls", "seed", "anisotropic")
"""The ``metaball`` keys the views depend on (the network's and training's keys change none of them)."""


def _config(run: Run, **extra) -> dict:
    m = to_dict(run.config.metaball)
    return {"metaball": {k: m[k] for k in VIEW_FIELDS}, **extra}


def _workers(run: Run) -> int:
    return 1 if run.device != "cpu" else (run.config.dataset.workers or os.cpu_count() or 1)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """The metaball views of one simulated scene, building what is missing."""
    m, d = run.config.metaball, run.config.dataset
    sim = simulate.ensure(run, scene)
    views = {k: getattr(d, k) for k in _VIEW_KEYS}
    entry = cache.entry(run.data_dir, "metaball_dataset", scene.name, _config(run, views=views),
                        {"simulate": sim.key}, run.device)
    if not entry.begin(force=force):
        log.info("metaball dataset %s: cached (%s)", scene.name, entry.dir)
        return entry
    info = read_sequence_info(sim.dir)
    frames = select_frames(info.frames, m.frame_stride, m.max_frames)
    start = time.perf_counter()
    sim_dir = sim.dir
    records = build_fluid_views(entry.dir, scene.name, frames, lambda f: load_frame(sim_dir / frame_name(f))[0],
                                info.particle_radius, m, d, warp_device(run.device), _workers(run))
    wall = time.perf_counter() - start
    entry.finish([r["file"] for r in records], {}, views=records, size=m.size, particle_radius=info.particle_radius,
                 wall_seconds=round(wall, 1))
    log.info("metaball dataset %s: %d views in %.1f s -> %s", scene.name, len(records), wall, entry.dir)
    return entry


def ensure_random_sets(run: Run, force: bool = False) -> cache.CacheEntry | None:
    """The thesis' random ball sets (None when ``metaball.random_sets`` is 0)."""
    m = run.config.metaball
    if not m.random_sets:
        return None
    entry = cache.entry(run.data_dir, "metaball_dataset", RANDOM_SETS, _config(run), {}, run.device)
    if not entry.begin(force=force):
        log.info("metaball dataset %s: cached (%s)", RANDOM_SETS, entry.dir)
        return entry
    start = time.perf_counter()
    records = build_random_sets(entry.dir, m, warp_device(run.device), _workers(run))
    entry.finish([r["file"] for r in records], {}, views=records, size=m.size,
                 wall_seconds=round(time.perf_counter() - start, 1))
    log.info("metaball dataset %s: %d views -> %s", RANDOM_SETS, len(records), entry.dir)
    return entry


def main(opts: StageOptions) -> None:
    """``deep-ssfr metaball-dataset``: every training and validation scene, and the random sets."""
    run = make_run(opts)
    train, val = roles(run)
    simulate.ahead(run, [*train, *val])
    for scene in [*train, *val]:
        ensure(run, scene, force=run.force)
    ensure_random_sets(run, force=run.force)
