"""``deep-ssfr render PATTERN --radius R --out DIR``: a user's own particle sequence, end to end.

Imports the frames in frame-number order, frames them with a camera (``auto``, ``orbit`` or a
camera JSON), renders and publishes ``DIR/frame_NNNN.exr`` (the files' own frame numbers), the
preview and comparison videos, the sheet and ``DIR/camera.json``. Intermediates are cached in
``DIR/.cache`` like every stage's: a re-run resumes, a changed option redoes only what it touches.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import cache
from pipeline.camera import camera_file_size, sequence_cameras, write_camera_file
from pipeline.config import Config, ConfigError
from pipeline.config_files import Loaded, load
from pipeline.device import choose_device
from pipeline.frames import frame_name, load_frame, sequence_bounds
from pipeline.particles.sequence import find_sequence, parse_frame_range
from pipeline.renderer import COMPARED, render_sequence
from pipeline.resources import check_render
from pipeline.shading.background import Surroundings
from pipeline.sim.runner import import_sequence
from pipeline.sph import IMPORT_PADDING_RADII, anisotropy_support
from stages.common import Run, StageOptions
from stages.render import networks, render_entry

log = logging.getLogger("deep_ssfr")
MODULE, WHERE = "stages.sequence", "command line"
STRAY_SHARE = 0.002
"""The automatic and orbit cameras frame the bulk of each frame: up to this share of its particles
beyond each side of an axis (a few droplets flung far away) may fall outside the picture."""
MAX_SIDE = 16384
"""Largest image side a render accepts (px): OpenGL's usual texture limit, 16K."""


@dataclass(frozen=True)
class Request:
    """The options of ``deep-ssfr render PATTERN`` (``deep-ssfr render --help``)."""

    pattern: str
    radius: float | None = None
    out: Path | None = None
    size: str = ""  # WIDTHxHEIGHT; '': the camera file's, else 512x512
    frames: str = ":"
    camera: str = "auto"
    up: str = "y"
    fps: float = 30.0
    method: str = "refined"
    background: str = "scene"
    compare: bool = False


def _loaded(opts: StageOptions, req: Request) -> Loaded:
    """The config file's filter and shading settings (the built-in defaults when the default file is
    absent) with the request's size, method and frame rate, and the cache in ``OUT/.cache``."""
    if req.out is None:
        raise ConfigError(WHERE, "--out", "is required with a PATTERN: the folder for the frames and videos")
    if req.camera not in ("auto", "orbit") and not Path(req.camera).is_file():
        raise ConfigError(WHERE, "--camera", f"is auto, orbit or a camera JSON file; {req.camera} does not exist")
    own = camera_file_size(Path(req.camera)) if req.camera not in ("auto", "orbit") else None
    text = req.size or (f"{own[0]}x{own[1]}" if own else "512x512")  # --size, else the camera file's
    size = re.fullmatch(r"(\d+)[xX](\d+)", text.strip())
    if not size or min(int(size[1]), int(size[2])) < 8:
        raise ConfigError(WHERE, "--size", f"must be WIDTHxHEIGHT, both at least 8, got {text!r}")
    if max(int(size[1]), int(size[2])) > MAX_SIDE:
        raise ConfigError(WHERE, "--size", f"{text} is larger than {MAX_SIDE} pixels a side")
    if not req.fps > 0:
        raise ConfigError(WHERE, "--fps", f"must be > 0, got {req.fps}")
    config = load(opts.config).config if Path(opts.config).exists() or opts.config != StageOptions.config \
        else Config(scenes=())
    render = dataclasses.replace(config.render, width=int(size[1]), height=int(size[2]), method=req.method,
                                 video_fps=req.fps, frame_stride=1, max_frames=0, comparison=req.compare,
                                 background=req.background)
    # absolute: a Ray task on another node starts in a folder of its own
    root = Path(req.out).resolve() / ".cache"
    executor = {"executor": opts.executor} if opts.executor else {}
    return Loaded(dataclasses.replace(config, render=render, data_dir=str(root), **executor), {}, Path(opts.config),
                  root)


def main(opts: StageOptions, req: Request) -> None:
    """Render a user's particle sequence into ``req.out``."""
    loaded = _loaded(opts, req)
    run, p, start = Run(loaded, choose_device(loaded.config.device), opts.force), loaded.config.render, time.time()
    cache.VERIFY_HASHES = opts.verify
    seq = find_sequence(req.pattern, *parse_frame_range(req.frames))
    radius = req.radius if req.radius is not None else seq.median_radius(req.up)
    if radius is None or not radius > 0:
        raise ConfigError(WHERE, "--radius", f"must be > 0, got {req.radius}" if req.radius is not None else
                          f"is required: {seq.paths[0].name} has no pscale or radius attribute" if radius is None
                          else f"is required: the median pscale or radius of {seq.paths[0].name} is {radius:g}, "
                               f"not a size")
    name, files = seq.name, [(str(f), os.path.getsize(f), os.path.getmtime(f)) for f in seq.paths]
    sim = cache.entry(run.data_dir, "simulate", name, {"files": files, "radius": radius, "fps": req.fps,
                                                       "up": req.up}, {}, run.device, MODULE)
    if sim.begin(force=run.force):
        extra = import_sequence(sim.dir, name, list(seq.paths), radius, req.fps, req.up, req.pattern,
                                support=anisotropy_support(radius, loaded.config.dataset.aniso_kernel_radius),
                                stray=STRAY_SHARE)
        sim.finish(extra.pop("files"), extra.pop("timings"), **extra)
    indices = list(range(1, len(seq) + 1))
    box = sim.manifest().get("bounds")  # taken as the files were imported
    lo, hi = np.asarray(box, float) if box else sequence_bounds(sim.dir, len(seq), stray=STRAY_SHARE)
    if not 1e-4 < radius / max(float((hi - lo).max()), 1e-12) < 0.2:
        log.warning("render %s: the radius %.4g does not fit the sequence's extent %.4g; check --radius and the "
                    "units", name, radius, float((hi - lo).max()))
    cams, camera_key = sequence_cameras(req.camera, list(seq.numbers), lo - radius, hi + radius, p.width, p.height)
    refiner, metaball, weights = networks(run, {p.method, *(COMPARED if p.comparison else ())})
    entry = render_entry(run, name, camera_key, sim.key, weights, MODULE)
    if not entry.path(cache.MANIFEST).exists():  # work to do: estimate it (begin checks the outputs)
        size = "--size" if req.size or req.camera in ("auto", "orbit") else f"--size (here {req.camera}'s)"
        check_render(Path(req.out), p.width, p.height, len(seq), sim.manifest().get("particles_max", 0), size)
    if entry.begin(force=run.force):
        log.info("render %s: frames %d to %d (%d) of %s, %dx%d, %s camera, method %s", name, seq.numbers[0],
                 seq.numbers[-1], len(seq), req.pattern, p.width, p.height, req.camera, p.method)
        around = Surroundings(tuple(lo - IMPORT_PADDING_RADII * radius), tuple(hi + IMPORT_PADDING_RADII * radius),
                              walls=False)
        sim_dir = sim.dir  # shards carry a path, not the entry
        outputs, timings = render_sequence(entry.dir, name, around, loaded.config, run.device, refiner, indices,
                                           lambda i: load_frame(sim_dir / frame_name(i)), radius, lambda i: cams[i],
                                           metaball=metaball)
        entry.finish(outputs, timings.as_dict(), ms_per_frame=timings.per_call_ms(), frames=len(indices),
                     weights=weights)
    out = Path(req.out)
    for i, number in zip(indices, seq.numbers, strict=True):
        cache.publish(entry.path(f"frames/{frame_name(i, 'exr')}"), out / frame_name(number, "exr"))
    compared = (f"{name}_comparison.mp4", f"{name}_comparison_sheet.png") if p.comparison else ()
    for video in (f"{name}_{p.method}.mp4", *compared):
        cache.publish(entry.path(video), out / video)
    write_camera_file(out / "camera.json", cams, list(seq.numbers), up=req.up)
    log.info("render %s: %d frames in %.1f s -> %s (frame_NNNN.exr, %s_%s.mp4, %scamera.json)", name, len(seq),
             time.time() - start, out, name, p.method, f"{name}_comparison.mp4, " if p.comparison else "")
