"""Particle files: one module per format, dispatched by extension.

Readers return ``ParticleFrame`` (positions float32 N x 3, velocities or None); a corrupt or
truncated file raises ``ParticleFormatError`` naming the file and what is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


class ParticleFormatError(ValueError):
    """A particle file could not be read; the message names the file."""


@dataclass
class ParticleFrame:
    """One frame of particles."""

    positions: np.ndarray
    velocities: np.ndarray | None = None


def read_particles(path: str | Path) -> ParticleFrame:
    """Read a frame from legacy VTK, BGEO (gzip v5), PLY or XYZ (raw float32)."""
    from pipeline.particles import bgeo, ply, vtk, xyz

    path = Path(path)
    readers = {".vtk": vtk.read, ".bgeo": bgeo.read, ".ply": ply.read, ".xyz": xyz.read}
    reader = readers.get(path.suffix.lower())
    if reader is None:
        raise ParticleFormatError(f"{path}: unsupported particle format {path.suffix!r} "
                                  f"(supported: {', '.join(readers)})")
    if not path.exists():
        raise ParticleFormatError(f"{path}: file not found")
    try:
        frame = reader(path)
    except ParticleFormatError:
        raise
    except Exception as exc:  # any parse failure becomes a located, readable error
        raise ParticleFormatError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from exc
    if frame.positions.ndim != 2 or frame.positions.shape[1] != 3:
        raise ParticleFormatError(f"{path}: positions have shape {frame.positions.shape}, expected N x 3")
    if len(frame.positions) == 0:
        raise ParticleFormatError(f"{path}: the file holds no particles")
    if not np.isfinite(frame.positions).all():
        raise ParticleFormatError(f"{path}: positions contain NaN or infinity")
    return frame


def write_particles(path: str | Path, frame: ParticleFrame, fmt: str = "") -> None:
    """Write a frame as PLY, legacy VTK (binary) or XYZ, by ``fmt`` or else the extension."""
    from pipeline.particles import ply, vtk, xyz

    path = Path(path)
    writers = {"vtk": vtk.write, "ply": ply.write, "xyz": xyz.write}
    fmt = fmt or path.suffix.lower().lstrip(".")
    writer = writers.get(fmt)
    if writer is None:
        raise ValueError(f"{path}: cannot write {fmt!r} (supported: {', '.join(writers)})")
    writer(path, frame)
