"""``deep-ssfr refine PATTERN --out DIR``: refine screen-space EXRs of your own into refined normals.

Each input EXR carries the generator's input channels (``pipeline.model.data``): for the shipped,
ellipsoid-trained weights ``aniso_bilateral.N.X/Y/Z`` (filtered view-space normals), ``aniso.Z``
(raw splat depth), ``aniso_bilateral.Z`` (filtered depth) and ``aniso.A`` (fluid mask); for
sphere-trained weights the same without the ``aniso`` prefixes. ``deep-ssfr dataset`` writes such
files. Each output ``DIR/<input name>`` holds ``N.X N.Y N.Z`` (refined unit normals, view space)
and ``mask``; outputs that exist are kept unless ``--force``. The scale-free inputs of the shipped
weights also need each image's focal length in pixels and the particle radius: read from the
header (the standard ``pinholeFocalLength`` and ``sensorOverallDimensions``, and ``particleRadius``,
as ``deep-ssfr dataset`` writes them), else from ``--fov`` and ``--radius``.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

from tqdm import tqdm

from pipeline.config import ConfigError
from pipeline.device import choose_device
from pipeline.exr import read_exr, read_exr_header, write_exr
from pipeline.methods import refine
from pipeline.model import SHIPPED_WEIGHTS
from pipeline.model.data import input_channels, view_geometry
from pipeline.model.inference import load_weights
from pipeline.particles.sequence import numbered_files
from stages.common import StageOptions

log = logging.getLogger("deep_ssfr")


def geometry(path: Path, height: int, radius: float, fov_deg: float) -> tuple[float | None, float | None]:
    """(focal length in px, particle radius) of an input EXR: its header, else the command line's."""
    focal_px, r = view_geometry(read_exr_header(path))
    if fov_deg > 0:
        focal_px = 0.5 * height / math.tan(math.radians(fov_deg) / 2)
    return focal_px, radius if radius > 0 else r


def main(opts: StageOptions, pattern: str, out: Path, weights: str = "shipped", threshold: float = 0.5,
         radius: float = 0.0, fov_deg: float = 0.0) -> None:
    """Refine every EXR ``pattern`` matches (in frame-number order) into ``out``."""
    if not 0.0 <= threshold <= 1.0:
        raise ConfigError("command line", "--threshold", f"must be between 0 and 1, got {threshold}")
    if radius < 0 or not 0 <= fov_deg < 180:
        raise ConfigError("command line", "--radius" if radius < 0 else "--fov", "out of range")
    files = [path for _, path in numbered_files(pattern) if path.suffix.lower() == ".exr"]
    if not files:
        raise FileNotFoundError(f"{pattern}: no EXR file matches the pattern")
    refiner, digest = load_weights(SHIPPED_WEIGHTS if weights == "shipped" else Path(weights), choose_device())
    names = input_channels(refiner.splat)
    start, done = time.perf_counter(), 0
    for path in tqdm(files, desc="refine", unit="frame"):
        target = Path(out) / path.name
        if target.exists() and not opts.force:
            continue
        channels = read_exr(path, list(refiner.spec.view_channels))
        focal_px, r = geometry(path, channels[names.raw].shape[0], radius, fov_deg)
        if refiner.spec.features == "radius" and (focal_px is None or r is None):
            raise ValueError(f"{path}: the header gives no {'particleRadius' if r is None else 'camera'}; pass "
                             f"{'--radius' if r is None else '--fov'}")
        normals, mask, _ = refine(refiner, channels, threshold, focal_px, r)
        channels = {f"N.{a}": normals[..., k] for k, a in enumerate("XYZ")}
        write_exr(target, {**channels, "mask": mask.astype("float32")})
        done += 1
    log.info("refine: %d of %d frames refined with weights %s (%s, %s input) in %.1f s -> %s", done, len(files),
             weights, digest, refiner.splat, time.perf_counter() - start, out)
