"""Particles drawn as ellipsoids: what the anisotropy (``pipeline.surface``) makes and the
ellipsoid splat (``pipeline.screen``) draws."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp


@dataclass
class Ellipsoids:
    """Particles as ellipsoids |shapes[i] (x - centres[i])| <= 1 (world space), with the radii of
    their bounding spheres: what ellipsoid splatting draws instead of spheres. Host arrays, or on a
    GPU Warp arrays where the anisotropy made them (``particle_ellipsoids(on_device=True)``), which
    the splat reads in place."""

    centres: np.ndarray | wp.array   # N x 3
    shapes: np.ndarray | wp.array    # N x 3 x 3, symmetric: the inverse of the semi-axis matrix (1/m)
    bounds: np.ndarray | wp.array    # N (m)
