"""Raw little-endian float32 x y z triplets (splashsurf's ``.xyz``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.particles.frame import ParticleFormatError, ParticleFrame


def read(path: Path) -> ParticleFrame:
    """Read positions; the size must be a whole number of 12-byte points."""
    raw = Path(path).read_bytes()
    if len(raw) % 12:
        raise ParticleFormatError(f"{path}: size {len(raw)} bytes is not a multiple of 12 (3 x float32)")
    return ParticleFrame(np.frombuffer(raw, dtype="<f4").reshape(-1, 3).astype(np.float32))


def write(path: Path, frame: ParticleFrame) -> None:
    """Write positions only."""
    Path(path).write_bytes(np.ascontiguousarray(frame.positions, dtype="<f4").tobytes())
