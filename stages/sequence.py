"""``deep-ssfr render PATTERN --radius R --out DIR``: a user's own particle sequence, end to end.

Imports the frames (in frame-number order), frames them with a camera (``auto``, ``orbit`` or a
camera JSON), renders the screen-space inputs, refined normals and shading, and publishes
``DIR/frame_NNNN.exr`` (the files' own frame numbers), ``DIR/<name>_<method>.mp4``, the comparison
video and sheet, and ``DIR/camera.json`` (the cameras used, to match a 3D scene). Intermediates are
cached in ``DIR/.cache`` like every stage's, so a re-run resumes and a changed option redoes only
what it touches.
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
from pipeline.camera import framing_cameras, read_camera_file, write_camera_file
from pipeline.config import Config, ConfigError, Loaded, load
from pipeline.device import choose_device
from pipeline.frames import frame_name, load_frame
from pipeline.methods import METHODS
from pipeline.particles.sequence import ParticleSequence, find_sequence, parse_frame_range
from pipeline.renderer import SequenceRenderer
from pipeline.shading.background import Surroundings
from pipeline.sim.runner import import_sequence
from pipeline.sph import IMPORT_PADDING_RADII
from stages.common import Run, StageOptions
from stages.render import load_refiner, render_entry

log = logging.getLogger("deep_ssfr")
MODULE = "stages.sequence"
WHERE = "command line"


@dataclass(frozen=True)
class Request:
    """The options of ``deep-ssfr render PATTERN``."""

    pattern: str
    radius: float | None = None
    out: Path | None = None
    size: str = "512x512"
    frames: str = ":"
    camera: str = "auto"
    up: str = "y"
    fps: float = 30.0
    method: str = "refined"


def image_size(text: str) -> tuple[int, int]:
    """``"640x360"`` -> (640, 360)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or min(int(m[1]), int(m[2])) < 8:
        raise ConfigError(WHERE, "--size", f"must be WIDTHxHEIGHT with both at least 8, got {text!r}")
    return int(m[1]), int(m[2])


def _config(opts: StageOptions, req: Request) -> Loaded:
    """The config file's filter and shading settings (or the defaults, when the default config file
    is absent), with the command's size, method and frame rate; the cache in ``OUT/.cache``."""
    if req.out is None:
        raise ConfigError(WHERE, "--out", "is required with a PATTERN: the folder for the frames and videos")
    if req.up not in ("y", "z"):
        raise ConfigError(WHERE, "--up", f"must be y or z, got {req.up!r}")
    if req.method not in METHODS:
        raise ConfigError(WHERE, "--method", f"must be one of {', '.join(METHODS)}, got {req.method!r}")
    if not req.fps > 0:
        raise ConfigError(WHERE, "--fps", f"must be > 0, got {req.fps}")
    if req.camera not in ("auto", "orbit") and not Path(req.camera).is_file():
        raise ConfigError(WHERE, "--camera", f"is auto, orbit or a camera JSON file; {req.camera} does not exist")
    width, height = image_size(req.size)
    if Path(opts.config).exists() or opts.config != StageOptions.config:
        config = load(opts.config).config
    else:
        config = Config(scenes=())
    render = dataclasses.replace(config.render, width=width, height=height, method=req.method, video_fps=req.fps,
                                 frame_stride=1, max_frames=0, comparison=True)
    root = Path(req.out) / ".cache"
    return Loaded(dataclasses.replace(config, render=render, data_dir=str(root)), {}, Path(opts.config), root)


def sequence_name(seq: ParticleSequence) -> str:
    """A folder-safe name from the first file's name without its frame number (``fluid_0007.vtk`` -> ``fluid``)."""
    stem = seq.paths[0].name.split(".")[0]
    name = re.sub(r"[^A-Za-z0-9]+", "_", re.sub(r"\d+", "", stem)).strip("_")
    return name or "sequence"


def particle_radius(seq: ParticleSequence, req: Request) -> float:
    """``--radius``, else the median per-particle radius the first file carries (Houdini's pscale)."""
    if req.radius is not None:
        if not req.radius > 0:
            raise ConfigError(WHERE, "--radius", f"must be > 0, got {req.radius}")
        return float(req.radius)
    radii = seq.read(seq.numbers[0], up=req.up).radii
    if radii is None:
        raise ConfigError(WHERE, "--radius", f"is required: {seq.paths[0].name} has no pscale or radius attribute")
    radius = float(np.median(radii))
    log.info("render %s: particle radius %.4g from the files' per-particle radii (median)", seq.pattern, radius)
    return radius


def _cameras(req: Request, frames: list[int], lo, hi, width: int, height: int):
    """The camera of every frame, and what keys them in the cache."""
    if req.camera in ("auto", "orbit"):
        cams = framing_cameras(lo, hi, width, height, len(frames), orbit=req.camera == "orbit")
        return cams, {"kind": req.camera, "lo": list(map(float, lo)), "hi": list(map(float, hi))}
    cams = read_camera_file(Path(req.camera), frames, width, height)
    return cams, {"kind": "file", "views": [c.view.round(9).tolist() for c in cams], "fov": [c.fov_y_deg for c in cams]}


def main(opts: StageOptions, req: Request) -> None:
    """Render a user's particle sequence into ``req.out``."""
    loaded = _config(opts, req)
    run = Run(loaded, choose_device(loaded.config.device), opts.force)
    cache.VERIFY_HASHES = opts.verify
    start_frame, end_frame = parse_frame_range(req.frames)
    seq = find_sequence(req.pattern, start_frame, end_frame)
    name, radius, p = sequence_name(seq), particle_radius(seq, req), loaded.config.render
    start = time.perf_counter()
    files = [(str(f), os.path.getsize(f), os.path.getmtime(f)) for f in seq.paths]
    sim = cache.entry(run.data_dir, "simulate", name, {"files": files, "radius": radius, "fps": req.fps,
                                                       "up": req.up}, {}, run.device, MODULE)
    if run.force or not sim.is_complete():
        sim.begin(force=run.force)
        extra = import_sequence(sim.dir, name, list(seq.paths), radius, req.fps, req.up, req.pattern)
        sim.finish(extra.pop("files"), extra.pop("timings"), **extra)
    indices = list(range(1, len(seq) + 1))
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for i in indices:
        x, _ = load_frame(sim.path(frame_name(i)))
        lo, hi = np.minimum(lo, x.min(0)), np.maximum(hi, x.max(0))
    _check_units(radius, lo, hi)
    cams, camera_key = _cameras(req, list(seq.numbers), lo - radius, hi + radius, p.width, p.height)
    refiner, weights = load_refiner(run)
    entry = render_entry(run, name, camera_key, sim.key, weights, MODULE)
    if run.force or not entry.is_complete():
        entry.begin(force=run.force)
        log.info("render %s: %d frames (%d to %d) of %s, %dx%d, %s camera, method %s", name, len(seq),
                 seq.numbers[0], seq.numbers[-1], req.pattern, p.width, p.height, req.camera, p.method)
        pad = IMPORT_PADDING_RADII * radius
        around = Surroundings(tuple(lo - pad), tuple(hi + pad), walls=False)
        with SequenceRenderer(entry.dir, name, around, loaded.config, run.device, refiner) as renderer:
            outputs = renderer.render(indices, lambda i: load_frame(sim.path(frame_name(i))), radius,
                                      lambda i: cams[i])
        entry.finish(outputs, renderer.timings.as_dict(), ms_per_frame=renderer.timings.per_call_ms(),
                     frames=len(indices), weights=weights)
    out = Path(req.out)
    for i, number in zip(indices, seq.numbers, strict=True):
        cache.publish(entry.path(f"frames/{frame_name(i, 'exr')}"), out / frame_name(number, "exr"))
    videos = [f"{name}_{p.method}.mp4", f"{name}_comparison.mp4", f"{name}_comparison_sheet.png"]
    for video in videos:
        cache.publish(entry.path(video), out / video)
    write_camera_file(out / "camera.json", cams, list(seq.numbers), up=req.up)
    log.info("render %s: %d frames in %.1f s -> %s (%s ... %s, %s, camera.json)", name, len(seq),
             time.perf_counter() - start, out, frame_name(seq.numbers[0], "exr"), frame_name(seq.numbers[-1], "exr"),
             ", ".join(videos[:2]))


def _check_units(radius: float, lo: np.ndarray, hi: np.ndarray) -> None:
    """Warn when the radius cannot match the data's scale (a radius in mm for data in m, say)."""
    extent = float(np.max(hi - lo))
    if extent > 0 and not 1e-4 < radius / extent < 0.2:
        log.warning("the particle radius %.4g is %.2g of the sequence's extent %.4g: check --radius and the units",
                    radius, radius / extent, extent)
