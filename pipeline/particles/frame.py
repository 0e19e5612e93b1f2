"""One frame of particles as every reader returns it, and the attribute names they pick by."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

VELOCITY_NAMES = ("velocity", "v", "vel", "velocities")
RADIUS_NAMES = ("pscale", "radius", "radii")

class ParticleFormatError(ValueError):
    """A particle file could not be read; the message names the file."""


@dataclass
class ParticleFrame:
    """One frame of particles."""

    positions: np.ndarray
    """Particle centres, float32 N x 3, in the file's length unit."""
    velocities: np.ndarray | None = None
    """Particle velocities, float32 N x 3, in the file's length unit per second; None when absent."""
    radii: np.ndarray | None = None
    """Per-particle radii, float32 N, in the file's length unit; None when absent."""


def frame_from_point_data(positions: np.ndarray, point_data: Mapping[str, np.ndarray]) -> ParticleFrame:
    """A frame from positions and named point attributes, picking velocities and radii by name."""
    by_name = {name.lower(): np.asarray(values) for name, values in point_data.items()}
    velocities = radii = None
    for name in VELOCITY_NAMES:
        values = by_name.get(name)
        if values is not None and values.ndim == 2 and values.shape[1] == 3:
            velocities = values.astype(np.float32)
            break
    for name in RADIUS_NAMES:
        values = by_name.get(name)
        if values is not None and (values.ndim == 1 or (values.ndim == 2 and values.shape[1] == 1)):
            radii = values.reshape(-1).astype(np.float32)
            break
    return ParticleFrame(np.array(positions, dtype=np.float32), velocities, radii)
