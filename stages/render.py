"""``make render``: particles to shaded EXR sequences, previews, a video and a comparison.

Writes ``data/render/<scene>-<key>/``: ``frames/frame_0001.exr`` (R G B A linear beauty, N.X N.Y
N.Z, Z, thickness, mask), ``preview/frame_0001.png``, ``<scene>_<method>.mp4``, and with
``render.comparison`` also ``compare/frame_0001.png``, ``<scene>_comparison.mp4`` and
``<scene>_comparison_sheet.png`` (bilateral | narrow-range | refined | mesh).
"""

from __future__ import annotations

import hashlib
import logging
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline import cache
from pipeline.camera import camera_for_frame
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.exr import write_exr
from pipeline.frames import frame_name, load_frame, read_sequence_info
from pipeline.media import contact_sheet, label, write_png, write_video
from pipeline.parallel import Launcher
from pipeline.render import normal_source, shade_frame
from pipeline.screen import ScreenSpace
from pipeline.shading import Shader, load_environment, tonemap
from pipeline.shading.background import BackgroundRenderer
from pipeline.timing import Timings
from pipeline.writer import BackgroundWriter
from stages import simulate
from stages.common import Run, StageError, make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")
SHIPPED = Path(__file__).resolve().parents[1] / "pipeline" / "weights" / "refiner.pt"
COMPARED = ("bilateral", "nrf", "refined", "mesh")


def resolve_weights(run: Run) -> Path:
    """The generator checkpoint ``render.weights`` names, with a clear error when it is missing."""
    choice = run.config.render.weights
    if choice == "shipped":
        path = SHIPPED
    elif choice == "trained":
        from stages import train

        path = train.ensure(run).path("best.pt")
    else:
        path = Path(choice)
    if not path.exists():
        raise StageError(f"no generator checkpoint at {path}; run `make train` and set render.weights to "
                         f"'trained' or a checkpoint path, or restore the shipped weights")
    return path


def load_refiner(run: Run):
    """(refiner, a content hash of the checkpoint)."""
    from pipeline.model.inference import load_refiner as load

    path = resolve_weights(run)
    try:
        refiner = load(path)
    except Exception as exc:
        raise StageError(f"cannot load generator checkpoint {path} ({exc})") from None
    return refiner, hashlib.sha256(path.read_bytes()).hexdigest()[:12]


def render_entry(run: Run, scene: SceneConfig, sim_key: str, weights: str) -> cache.CacheEntry:
    """Keyed on the render and filter settings, the cameras, the particles and the weights."""
    filters = to_dict(run.config.dataset)
    for key in ("frame_stride", "max_frames", "width", "height", "holdout_scenes", "validation_camera", "workers",
                "keep_meshes"):
        filters.pop(key)
    config = {"render": to_dict(run.config.render), "filters": filters, "cameras": to_dict(scene.cameras)}
    return cache.entry(run.data_dir, "render", scene.name, config, {"simulate": sim_key, "weights": weights},
                       run.device)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """Render a scene's sequence (resuming per frame); returns the entry."""
    p = run.config.render
    sim = simulate.ensure(run, scene)
    info = read_sequence_info(sim.dir)
    methods = set(COMPARED if p.comparison else ()) | {p.method}
    refiner, weights = load_refiner(run) if "refined" in methods else (None, "")
    entry = render_entry(run, scene, sim.key, weights)
    if entry.is_complete() and not force:
        log.info("render %s: cached (%s)", scene.name, entry.dir)
        return entry
    entry.begin(force=force)
    frames = list(range(1, info.frames + 1, p.frame_stride))
    frames = frames[: p.max_frames] if p.max_frames else frames
    device = warp_device(run.device)
    ss, launch = ScreenSpace(device), Launcher(device)
    env = load_environment(p.environment) if p.environment else None
    shader = Shader(device, environment=env)
    background = BackgroundRenderer(scene, p, p.width, p.height)
    timings = Timings()
    no_fluid: list[int] = []
    log.info("render %s: %d frames, %s camera, method %s%s, %dx%d", scene.name, len(frames), p.camera, p.method,
             " + comparison" if p.comparison else "", p.width, p.height)
    write_timings = Timings()

    def write_outputs(frame: int, shaded: dict) -> None:
        main = shaded[p.method]
        with write_timings("exr_write"):
            write_exr(entry.path(f"frames/{frame_name(frame, 'exr')}"), main.channels())
        write_png(entry.path(f"preview/{frame_name(frame, 'png')}"), tonemap(main.beauty, p.exposure))
        if p.comparison:
            tiles = [label(tonemap(shaded[m].beauty, p.exposure), _TITLES[m]) for m in COMPARED]
            write_png(entry.path(f"compare/{frame_name(frame, 'png')}"), np.concatenate(tiles, axis=1))

    def done(frame: int) -> bool:
        outputs = [f"frames/{frame_name(frame, 'exr')}", f"preview/{frame_name(frame, 'png')}"]
        outputs += [f"compare/{frame_name(frame, 'png')}"] if p.comparison else []
        return all(entry.path(o).exists() for o in outputs)

    try:
        with BackgroundWriter() as writer:
            for i, frame in enumerate(tqdm(frames, desc=f"render {scene.name}", unit="frame")):
                if done(frame):
                    continue
                x, _ = load_frame(sim.path(frame_name(frame)))
                cam = camera_for_frame(scene.cameras, p.camera, i, len(frames), p.width, p.height)
                with timings("background"):
                    bg, bg_depth = background.render(cam)
                    bg = shader.fill_sky(bg, bg_depth, cam, p)
                shaded, frame_cache = {}, {}
                for method in [p.method] + [m for m in COMPARED if p.comparison and m != p.method]:
                    t = timings if method == p.method else Timings()
                    src = normal_source(method, x, info.particle_radius, cam, run.config.dataset, ss, launch,
                                        refiner, p.normal_threshold, t, frame_cache)
                    shaded[method] = shade_frame(src, bg, bg_depth, cam, p, shader, t)
                if not shaded[p.method].mask.any():
                    no_fluid.append(frame)
                writer.submit(write_outputs, frame, shaded)
    finally:
        background.close()
        ss.close()
        launch.close()
        shader.close()
    if no_fluid:
        log.warning("render %s: the camera sees no fluid in %d frames (first: %d); they show the background only",
                    scene.name, len(no_fluid), no_fluid[0])
    files = [f"frames/{frame_name(f, 'exr')}" for f in frames]
    video = entry.path(f"{scene.name}_{p.method}.mp4")
    write_video(video, [entry.path(f"preview/{frame_name(f, 'png')}") for f in frames], p.video_fps)
    files.append(video.name)
    if p.comparison:
        compares = [entry.path(f"compare/{frame_name(f, 'png')}") for f in frames]
        write_video(entry.path(f"{scene.name}_comparison.mp4"), compares, p.video_fps)
        picks = [compares[int(k)] for k in np.linspace(0, len(compares) - 1, min(4, len(compares))).round()]
        contact_sheet(entry.path(f"{scene.name}_comparison_sheet.png"), picks)
        files += [f"{scene.name}_comparison.mp4", f"{scene.name}_comparison_sheet.png"]
    for k, v in write_timings.total.items():
        timings.total[k] += v
        timings.count[k] += write_timings.count[k]
    per_frame = {k: round(1000 * v / max(timings.count[k], 1), 2) for k, v in timings.total.items()}
    entry.finish(files, timings.as_dict(), ms_per_frame=per_frame, frames=len(frames), weights=weights)
    log.info("render %s: %d frames -> %s (%s)", scene.name, len(frames), entry.dir,
             ", ".join(f"{k} {v:.0f} ms" for k, v in per_frame.items()))
    return entry


_TITLES = {"bilateral": "bilateral", "nrf": "narrow-range", "refined": "refined (cGAN)", "mesh": "mesh (reference)",
           "gaussian": "gaussian"}


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make render``."""
    run = make_run(parse_args("render", argv))
    start = time.perf_counter()
    for scene in run.loaded.scenes.values():
        entry = ensure(run, scene, force=run.force)
        log.info("render %s: outputs in %s", scene.name, entry.dir)
    log.info("render: done in %.1f s", time.perf_counter() - start)


if __name__ == "__main__":
    sys.exit(stage_main("render", main))
