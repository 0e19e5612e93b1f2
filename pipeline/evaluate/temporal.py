"""Temporal error per pixel: how much a method's normals change from one frame to the next beyond
the reference surface's own change.

Each pixel of frame t's reference surface is followed to frame t+1 with the exact particle motion
between the two frames (the front particles' displacement, splatted as the motion pass is), through
both frames' cameras. Where the point stays on the reference surface (it is not hidden or uncovered
at t+1), a method's change there, N(t+1, p') - N(t, p) in world space, is compared with the
reference's: the temporal error is the angle that the difference of the two changes spans on the
unit sphere, 2 asin(|dN_method - dN_reference| / 2). A method that holds still where the mesh moves
scores the mesh's change; one that flickers where the mesh holds still scores its flicker.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from pipeline.camera import Camera
from pipeline.screen import ScreenSpace

DEPTH_TOLERANCE_RADII = 3.0
"""A followed point stays on the reference surface at t+1 where the surface's depth there is within
this many particle radii of the point's own depth (else it was hidden or newly seen: left out)."""


@dataclass(frozen=True)
class Flow:
    """Where frame t's reference pixels land in frame t+1."""

    rows: np.ndarray   # H x W target row of each pixel (pixel centres at integers; valid where ``valid``)
    cols: np.ndarray   # H x W target column
    valid: np.ndarray  # pixels on the reference surface at both frames

    @cached_property
    def nearest(self) -> tuple[np.ndarray, np.ndarray]:
        """The target pixels' (rows, columns), rounded."""
        return np.rint(self.rows).astype(np.int64), np.rint(self.cols).astype(np.int64)

    def sample(self, image: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``image`` (H x W x k) at the target points, bilinear over the neighbours inside ``mask``
        (a normal 3 degrees a pixel apart would otherwise be off by up to half that)."""
        h, w = mask.shape
        r0 = np.clip(np.floor(self.rows).astype(np.int64), 0, h - 1)
        c0 = np.clip(np.floor(self.cols).astype(np.int64), 0, w - 1)
        fr, fc = np.clip(self.rows - r0, 0, 1), np.clip(self.cols - c0, 0, 1)
        total = np.zeros((h, w, image.shape[-1]))
        weight = np.zeros((h, w))
        for dr, dc, wt in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
            r, c = np.minimum(r0 + dr, h - 1), np.minimum(c0 + dc, w - 1)
            wt = wt * mask[r, c]
            total += wt[..., None] * image[r, c]
            weight += wt
        return total / np.maximum(weight, 1e-12)[..., None]


def surface_flow(ss: ScreenSpace, x0: np.ndarray, x1: np.ndarray, radius: float, cam0: Camera, cam1: Camera,
                 depth0: np.ndarray, mask0: np.ndarray, depth1: np.ndarray, mask1: np.ndarray) -> Flow:
    """Follow frame t's reference surface (``depth0``/``mask0`` under ``cam0``) to frame t+1 with
    the displacement of the particles common to both frames (the first min(N0, N1): simulators
    append new particles) and keep the pixels that land on the t+1 reference surface at their depth."""
    n = min(len(x0), len(x1))
    a, b = np.asarray(x0[:n], np.float64), np.asarray(x1[:n], np.float64)
    col0, row0, d0 = cam0.project(cam0.to_view(a))
    col1, row1, d1 = cam1.project(cam1.to_view(b))
    # per particle: (columns, rows, depth change) to t+1; splatted from the front particles of t
    shift = np.stack([col1 - col0, row1 - row0, d1 - d0, np.zeros(n)], 1).astype(np.float32)
    motion, covered = ss.motion(a, shift, radius, cam0, np.where(mask0, depth0, 0.0).astype(np.float32))
    h, w = depth0.shape
    rr, cc = np.mgrid[0:h, 0:w]
    rows, cols = rr + motion[..., 1].astype(np.float64), cc + motion[..., 0].astype(np.float64)
    inside = (rows > -0.5) & (rows < h - 0.5) & (cols > -0.5) & (cols < w - 0.5)
    flow = Flow(np.where(inside, rows, 0.0), np.where(inside, cols, 0.0), inside)
    r, c = flow.nearest
    expected = depth0 + motion[..., 2]
    lands = mask1[r, c] & (np.abs(depth1[r, c] - expected) < DEPTH_TOLERANCE_RADII * radius)
    return Flow(flow.rows, flow.cols, mask0 & covered & inside & lands)


def _unit(n: np.ndarray) -> np.ndarray:
    """Vectors scaled to unit length (0 stays 0)."""
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def _world(normals: np.ndarray, cam: Camera) -> np.ndarray:
    """View-space normals (H x W x 3) in world space, unit length (0 stays 0)."""
    return _unit(normals.astype(np.float64) @ cam.view[:3, :3])


def normal_change(flow: Flow, normals: np.ndarray, next_normals: np.ndarray, next_mask: np.ndarray, cam0: Camera,
                  cam1: Camera) -> np.ndarray:
    """H x W x 3: each pixel's change of world normal from t (view ``normals`` under ``cam0``) to
    where it lands at t+1 (``next_normals`` under ``cam1``, sampled within ``next_mask``)."""
    return _unit(flow.sample(_world(next_normals, cam1), next_mask)) - _world(normals, cam0)


def temporal_errors(flow: Flow, method: tuple[np.ndarray, np.ndarray], next_method: tuple[np.ndarray, np.ndarray],
                    reference_change: np.ndarray, cam0: Camera, cam1: Camera) -> tuple[np.ndarray, int]:
    """Temporal errors (degrees) of a method, given as (view normals, mask) at t and t+1, against the
    reference's ``normal_change``, over the followed pixels where the method shows fluid at both
    ends, and the number of followed pixels where it does not (reported apart: a change cannot be
    scored where there is no normal)."""
    (n0, m0), (n1, m1) = method, next_method
    r, c = flow.nearest
    shown = flow.valid & m0 & m1[r, c]
    gap = np.linalg.norm(normal_change(flow, n0, n1, m1, cam0, cam1)[shown] - reference_change[shown], axis=-1)
    return np.degrees(2 * np.arcsin(np.clip(gap / 2, 0.0, 1.0))), int((flow.valid & ~shown).sum())
