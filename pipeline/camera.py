"""Pinhole cameras and the one view-space convention every stage uses.

View space is right-handed: +X right, +Y up, the camera looks down -Z. Depth maps store the
positive distance along -Z (``d = -z_view``, metres) and 0 where there is no fluid. Normals are
unit view-space vectors; a surface facing the camera has n_z > 0. Pixel (col i, row j) has its
centre at (i + 0.5, j + 0.5), row 0 at the top.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.config import Cameras


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """World-to-view 4x4 matrix of a camera at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:
        right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    view = np.eye(4)
    view[0, :3], view[1, :3], view[2, :3] = right, true_up, -forward
    view[:3, 3] = -view[:3, :3] @ eye
    return view


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: world-to-view matrix, vertical field of view and image size."""

    view: np.ndarray
    fov_y_deg: float
    width: int
    height: int

    @property
    def focal_px(self) -> float:
        """Focal length in pixels (same horizontally and vertically: square pixels)."""
        return 0.5 * self.height / math.tan(math.radians(self.fov_y_deg) / 2.0)

    @property
    def eye(self) -> np.ndarray:
        """Camera position in world space."""
        return -self.view[:3, :3].T @ self.view[:3, 3]

    @property
    def cam_to_world(self) -> np.ndarray:
        """View-to-world 4x4 matrix (the pose pyrender wants)."""
        return np.linalg.inv(self.view)

    def to_view(self, points: np.ndarray) -> np.ndarray:
        """World points (N x 3) to view space."""
        return points @ self.view[:3, :3].T + self.view[:3, 3]

    def project(self, points_view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View points to (column, row, depth) in pixels and metres."""
        d = -points_view[:, 2]
        f = self.focal_px
        col = self.width / 2.0 + f * points_view[:, 0] / d
        row = self.height / 2.0 - f * points_view[:, 1] / d
        return col, row, d

    def pixel_rays(self) -> np.ndarray:
        """Per-pixel view-space ray directions scaled so that z = -1 (H x W x 3)."""
        f = self.focal_px
        cols = (np.arange(self.width) + 0.5 - self.width / 2.0) / f
        rows = -(np.arange(self.height) + 0.5 - self.height / 2.0) / f
        x, y = np.meshgrid(cols, rows)
        return np.stack([x, y, -np.ones_like(x)], axis=-1).astype(np.float32)

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """View-space positions (H x W x 3) of a depth map (positive depth along -Z)."""
        return self.pixel_rays() * depth[..., None]


def camera_for_frame(cameras: Cameras, path: str, index: int, count: int, width: int, height: int) -> Camera:
    """The camera of ``path`` ('static' or 'orbit') at frame ``index`` of ``count`` (0-based)."""
    if path == "static":
        c = cameras.static
        return Camera(look_at(c.eye, c.target), c.fov_deg, width, height)
    if path == "orbit":
        c = cameras.orbit
        t = index / max(count - 1, 1)
        azimuth = math.radians(c.start_deg + c.sweep_deg * t)
        target = np.asarray(c.target, float)
        eye = target + np.array([c.distance * math.sin(azimuth), c.height, c.distance * math.cos(azimuth)])
        return Camera(look_at(eye, target), c.fov_deg, width, height)
    raise ValueError(f"unknown camera path {path!r} (static or orbit)")
