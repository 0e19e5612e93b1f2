"""SPH facts every part of the pipeline shares: the poly6 kernel, particle spacing and volume.

Particles of radius r start on a cubic lattice of spacing 2r, so each stands for a volume (2r)^3;
the poly6 kernel W(d, h) = 315 / (64 pi h^9) (h^2 - d^2)^3 (Mueller et al. 2003) weighs
neighbours in the simulator, in the seeding tables and in the reconstructed surface's density.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.vectors import bounds

POLY6_NORM = 315.0 / (64.0 * math.pi)
"""Normalisation of the poly6 profile (1 - q^2)^3 over the unit ball (q = d / h)."""

WATER_DENSITY = 1000.0
"""Rest density of water (kg/m^3), assumed for imported sequences."""

IMPORT_PADDING_RADII = 4.0
"""Margin around an imported sequence's first frame, in particle radii, that forms its domain."""


def poly6_coefficient(h: float) -> float:
    """The factor 315 / (64 pi h^9) of the poly6 kernel with support ``h``."""
    return POLY6_NORM / h**9


def poly6(r2: np.ndarray, h: float) -> np.ndarray:
    """Poly6 kernel values at squared distances ``r2`` (0 beyond the support ``h``)."""
    h2 = h * h
    return poly6_coefficient(h) * np.where(r2 < h2, (h2 - r2) ** 3, 0.0)


def spacing(radius: float) -> float:
    """Distance between neighbouring particles at rest: the lattice spacing 2r."""
    return 2.0 * radius


def particle_volume(radius: float) -> float:
    """Volume one particle stands for at rest: (2r)^3."""
    return spacing(radius) ** 3


def lattice_offsets(spacing_: float, reach: float) -> np.ndarray:
    """Offsets (K x 3) of a cubic lattice's points within a cube of half side ``reach`` (rounded up)."""
    k = int(math.ceil(reach / spacing_))
    ax = np.arange(-k, k + 1) * spacing_
    return np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)


def anisotropy_support(radius: float, kernel_radius: float) -> float:
    """The anisotropy's neighbour radius: twice its kernel radius (``aniso_kernel_radius``, in
    particle radii)."""
    return 2.0 * kernel_radius * radius


NEIGHBOUR_PAIRS_LIMIT = 2e10
"""Most neighbour pairs (particles times neighbours within the anisotropy's support) a frame may
need: about 3 minutes of neighbour search on 2 CPU cores if every particle is seen. A fluid at rest
has about 520 neighbours a particle there, so 38 million particles fit; a cloud packed far denser
than a fluid (or a radius far too large for its units) does not."""


def neighbour_count(positions: np.ndarray, support: float) -> float:
    """Mean number of particles within ``support`` of a particle, estimated from cubic cells of that
    side: 4/3 pi times the mean occupancy of a particle's own cell (exact for a uniform fluid), at
    most every particle. Cells are counted densely where the grid is small, else by hash."""
    if len(positions) == 0:
        return 0.0
    cells = ((positions - bounds(positions)[0]) * np.float32(1.0 / support)).astype(np.int64)
    dims = bounds(cells)[1] + 1
    if float(np.prod(dims.astype(np.float64))) <= 8 * len(positions) + 4096:
        counts = np.bincount((cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2])
    else:  # a few stray particles far out make the dense grid too large
        keys = (cells[:, 0] * 73856093) ^ (cells[:, 1] * 19349663) ^ (cells[:, 2] * 83492791)
        counts = np.unique(keys, return_counts=True)[1]
    estimate = 4.0 / 3.0 * math.pi * float((counts.astype(np.float64) ** 2).sum()) / len(positions)
    return min(estimate, float(len(positions)))
