"""Particles drawn as ellipsoids: what the anisotropy (``pipeline.surface``) makes and the
ellipsoid splat (``pipeline.screen``) draws."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import warp as wp

DENSITY_CHANNEL = "aniso.density"
"""The ellipsoid splat's map of ``Ellipsoids.density``: its largest value along each pixel's ray
(``ScreenSpace.inputs``; the refiner's density feature, ``pipeline.model.data.density_feature``)."""


@dataclass
class Ellipsoids:
    """Particles as ellipsoids |shapes[i] (x - centres[i])| <= 1 (world space), with the radii of
    their bounding spheres: what ellipsoid splatting draws instead of spheres. Host arrays, or on a
    GPU Warp arrays where the anisotropy made them (``particle_ellipsoids(on_device=True)``), which
    the splat reads in place. Where known, the mesh's density at each kernel centre in iso-levels
    (``surface.KernelMaker.densities``; below 1 the mesh leaves the centre outside)."""

    centres: np.ndarray | wp.array   # N x 3
    shapes: np.ndarray | wp.array    # N x 3 x 3, symmetric: the inverse of the semi-axis matrix (1/m)
    bounds: np.ndarray | wp.array    # N (m)
    density: np.ndarray | wp.array | None = None  # N (iso-levels)
