"""Screen-space fluid inputs: sphere splatting, depth filters and normals (host side).

Each filter is a function ``(depth, ...) -> depth`` over NumPy H x W float32 maps in the
convention of ``pipeline.camera`` (positive view depth, 0 = empty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from pipeline.camera import Camera
from pipeline.config import DatasetConfig
from pipeline.parallel import Launcher
from pipeline.screen import kernels as K

_EMPTY = 1.0e30


@dataclass
class SplatResult:
    """Raw sphere depth, mask and thickness of one view."""

    depth: np.ndarray
    mask: np.ndarray
    thickness: np.ndarray


class ScreenSpace:
    """Runs the screen-space kernels for one device (holds the thread pool)."""

    def __init__(self, device: str = "cpu", threads: int = 0):
        self.device = device
        self.launch = Launcher(device, threads, min_chunk=4096)

    def _arr(self, a: np.ndarray) -> wp.array:
        return wp.array(np.ascontiguousarray(a, np.float32).ravel(), dtype=float, device=self.device)

    def splat(self, positions_world: np.ndarray, radius: float, camera: Camera) -> SplatResult:
        """Nearest sphere-surface depth, fluid mask and summed chord thickness per pixel."""
        w, h = camera.width, camera.height
        depth = wp.full(w * h, _EMPTY, dtype=float, device=self.device)
        thickness = wp.zeros(w * h, dtype=float, device=self.device)
        if len(positions_world):
            centers = wp.array(camera.to_view(np.asarray(positions_world, np.float64)).astype(np.float32),
                               dtype=wp.vec3, device=self.device)
            # one launch: atomics from several CPU threads would race
            wp.launch(K.splat_spheres, dim=len(positions_world),
                      inputs=[centers, radius, camera.focal_px, w, h, depth, thickness], device=self.device)
        d = depth.numpy().reshape(h, w)
        mask = d < _EMPTY * 0.5
        d = np.where(mask, d, 0.0).astype(np.float32)
        return SplatResult(d, mask.astype(np.float32), thickness.numpy().reshape(h, w))

    def gaussian(self, depth: np.ndarray, sigma_px: float) -> np.ndarray:
        """Naive separable Gaussian blur restricted to fluid pixels (fixed screen-space size)."""
        h, w = depth.shape
        radius = max(1, int(np.ceil(3.0 * sigma_px)))
        a, b = self._arr(depth), wp.zeros(w * h, dtype=float, device=self.device)
        self.launch(K.gaussian_pass, w * h, [a, w, h, 0, sigma_px, radius, b])
        self.launch(K.gaussian_pass, w * h, [b, w, h, 1, sigma_px, radius, a])
        return a.numpy().reshape(h, w)

    def bilateral(self, depth: np.ndarray, camera: Camera, particle_radius: float, p: DatasetConfig) -> np.ndarray:
        """Bilateral Gaussian; spatial sigma from the projected particle radius at each pixel."""
        h, w = depth.shape
        a, b = self._arr(depth), wp.zeros(w * h, dtype=float, device=self.device)
        self.launch(K.bilateral_filter, w * h, [a, w, h, camera.focal_px, particle_radius,
                                                p.bilateral_sigma_px_scale,
                                                p.bilateral_range_radii * particle_radius,
                                                p.bilateral_max_radius_px, b])
        return b.numpy().reshape(h, w)

    def narrow_range(self, depth: np.ndarray, camera: Camera, particle_radius: float,
                     p: DatasetConfig) -> np.ndarray:
        """Narrow-Range Filter: alternating separable passes, then the 2D clean-up pass."""
        h, w = depth.shape
        a, b = self._arr(depth), wp.zeros(w * h, dtype=float, device=self.device)
        delta, mu = p.nrf_delta_radii * particle_radius, p.nrf_mu_radii * particle_radius
        common = [w, h]
        for _ in range(p.nrf_iterations):
            for axis in (0, 1):
                self.launch(K.narrow_range_pass, w * h, [a, *common, axis, camera.focal_px, particle_radius,
                                                         p.nrf_radius_scale, p.nrf_max_radius_px, delta, mu, b])
                a, b = b, a
        if p.nrf_cleanup_radius_px > 0:
            self.launch(K.narrow_range_cleanup, w * h, [a, *common, p.nrf_cleanup_radius_px, delta, mu, b])
            a = b
        return a.numpy().reshape(h, w)

    def normals(self, depth: np.ndarray, camera: Camera) -> np.ndarray:
        """View-space unit normals (H x W x 3) of a depth map; zero vectors where empty."""
        h, w = depth.shape
        out = wp.zeros(w * h, dtype=wp.vec3, device=self.device)
        self.launch(K.normals_from_depth, w * h, [self._arr(depth), w, h, camera.focal_px, out])
        return out.numpy().reshape(h, w, 3)

    def close(self) -> None:
        """Stop the thread pool."""
        self.launch.close()
