"""``make render``: particles to shaded EXR sequences, previews, a video and a comparison.

Writes ``data/render/<scene>-<key>/`` (files: ``pipeline.renderer``), keyed on the render and
filter settings, the cameras, the particles and the generator's weights.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

from pipeline import cache
from pipeline.camera import camera_for_frame
from pipeline.config import SceneConfig, to_dict
from pipeline.frames import frame_name, load_frame, read_sequence_info, select_frames
from pipeline.model import SHIPPED_WEIGHTS
from pipeline.model.inference import checked_digest, load_weights
from pipeline.renderer import COMPARED, render_sequence
from pipeline.resources import check_render
from pipeline.shading.background import Surroundings
from stages import simulate
from stages.common import Run, StageOptions, make_run

log = logging.getLogger("deep_ssfr")


def load_refiner(run: Run):
    """(refiner, a content hash of its checkpoint) for ``render.weights``: 'shipped', 'trained'
    (this config's best checkpoint, training it if needed) or a path."""
    choice = run.config.render.weights
    if choice == "trained":
        from stages import train

        path = train.ensure(run).path("best.pt")
    else:
        path = SHIPPED_WEIGHTS if choice == "shipped" else Path(choice)
    return load_weights(path, run.device, run.config.render.refiner_precision)


def load_metaball(run: Run):
    """(metaball generator, a content hash of its checkpoint) for ``metaball.weights``: 'shipped',
    'trained' (this config's best checkpoint, training it if needed) or a path."""
    from pipeline.metaball.inference import MetaballNet
    from pipeline.metaball.train import SHIPPED_WEIGHTS as SHIPPED_METABALL

    choice = run.config.metaball.weights
    if choice == "trained":
        from stages import metaball_train

        path = metaball_train.ensure(run).path("best.pt")
    else:
        path = SHIPPED_METABALL if choice == "shipped" else Path(choice)
    checked_digest(path)  # the card's record of these weights
    return MetaballNet(path, run.device), cache.file_hash(path)[:12]


def networks(run: Run, methods) -> tuple[object, object, str]:
    """(refiner, metaball generator, a key of both checkpoints) for the methods that need them
    (None and '' for those not used)."""
    refiner, weights = load_refiner(run) if "refined" in methods else (None, "")
    metaball, metaball_weights = load_metaball(run) if "metaball" in methods else (None, "")
    return refiner, metaball, "+".join(w for w in (weights, metaball_weights) if w)


def render_entry(run: Run, name: str, cameras, sim_key: str, weights: str, module: str = "") -> cache.CacheEntry:
    """Keyed on the render and filter settings, the cameras, the particles and the weights."""
    filters = to_dict(run.config.dataset)
    for key in ("frame_stride", "max_frames", "width", "height", "holdout_scenes", "validation_camera", "workers",
                "keep_meshes"):
        filters.pop(key)
    config = {"render": to_dict(run.config.render), "filters": filters, "cameras": cameras}
    return cache.entry(run.data_dir, "render", name, config, {"simulate": sim_key, "weights": weights}, run.device,
                       module)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """Render a scene's sequence (resuming per frame); returns the entry."""
    p = run.config.render
    sim = simulate.ensure(run, scene)
    info = read_sequence_info(sim.dir)
    methods = set(COMPARED if p.comparison else ()) | {p.method}
    refiner, metaball, weights = networks(run, methods)
    entry = render_entry(run, scene.name, to_dict(scene.cameras), sim.key, weights)
    frames = select_frames(info.frames, p.frame_stride, p.max_frames)
    if not entry.path(cache.MANIFEST).exists():  # work to do: estimate it (begin checks the outputs)
        manifest = sim.manifest()
        check_render(run.data_dir, p.width, p.height, len(frames),
                     manifest.get("particles") or manifest.get("particles_max", 0), "render.width, render.height",
                     copies=1)
    if not entry.begin(force=force):
        log.info("render %s: cached (%s)", scene.name, entry.dir)
        return entry
    log.info("render %s: %d frames, %s camera, method %s%s, %dx%d", scene.name, len(frames), p.camera, p.method,
             " + comparison" if p.comparison else "", p.width, p.height)
    sim_dir = sim.dir  # shards carry a path, not the entry
    files, timings = render_sequence(entry.dir, scene.name, Surroundings.of_scene(scene), run.config, run.device,
                                     refiner, frames, lambda f: load_frame(sim_dir / frame_name(f)),
                                     info.particle_radius, lambda i: camera_for_frame(scene.cameras, p.camera, i,
                                                                                      len(frames), p.width, p.height),
                                     fps=info.fps / p.frame_stride, metaball=metaball)
    per_frame = timings.per_call_ms()
    entry.finish(files, timings.as_dict(), ms_per_frame=per_frame, frames=len(frames), weights=weights)
    log.info("render %s: %d frames -> %s (%s)", scene.name, len(frames), entry.dir,
             ", ".join(f"{k} {v:.0f} ms" for k, v in per_frame.items()))
    return entry


def main(opts: StageOptions) -> None:
    """``deep-ssfr render`` of the configured scenes."""
    run = make_run(opts)
    start = time.perf_counter()
    simulate.ahead(run, list(run.loaded.scenes.values()))
    for scene in run.loaded.scenes.values():
        entry = ensure(run, scene, force=run.force)
        log.info("render %s: outputs in %s", scene.name, entry.dir)
    log.info("render: done in %.1f s", time.perf_counter() - start)
