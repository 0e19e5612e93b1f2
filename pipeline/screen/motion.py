"""Screen-space motion vectors in Blender's ``Vector`` pass layout.

Four values per pixel, in pixels with +Y up the image (Blender and Nuke count rows from the
bottom): (X, Y) = where the point was one frame earlier minus where it is now, (Z, W) = where it is
now minus where it will be one frame later (Cycles' convention). A point moving right at 5 pixels
per frame has X = Z = -5. A particle's world motion over one frame is its velocity (m/s) divided
by the frame rate; the camera's motion counts too when the neighbouring frames' cameras are given
(``gap`` frames away: motion is divided by the gap, the particle assumed at constant velocity).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from pipeline.camera import Camera
from pipeline.device import torch_waits_for_warp, warp_waits_for_torch
from pipeline.parallel import Launcher
from pipeline.screen import kernels as K
from pipeline.vectors import as_float32, is_tensor, xp


def _pixels(points_world, camera: Camera):
    """(column, row) pixel coordinates (N x 2, rows down) and whether each point is in front; numpy
    arrays or torch tensors."""
    col, row, d = camera.project(camera.to_view(points_world))
    front = d > 1e-6
    where = xp(col).where
    return xp(col).stack([where(front, col, 0.0), where(front, row, 0.0)], -1), front


def _up(delta_px):
    """Pixel displacements (rows down) with +Y up."""
    return delta_px * xp(delta_px).asarray([1.0, -1.0], dtype=delta_px.dtype, **_on(delta_px))


def _on(a) -> dict:
    """The keyword that puts a new torch tensor on ``a``'s device (none for numpy)."""
    return {"device": a.device} if is_tensor(a) else {}


def particle_motion(positions, velocities, camera: Camera, fps: float, prev: tuple[Camera, int] | None = None,
                    nxt: tuple[Camera, int] | None = None):
    """N x 4 motion of each particle (``Vector`` layout, pixels per frame) from its velocity (m/s,
    None: at rest) at ``fps`` frames per second, with the cameras (and frame gaps) of the previous
    and next rendered frames (None: this frame's camera, gap 1). Points behind a camera get 0.
    Torch tensors (a GPU's frame) give a float32 tensor on their device, from the same float64
    arithmetic as numpy's (equal to rounding: the matrix products may sum in another order)."""
    m = xp(positions)
    x = m.asarray(positions, dtype=m.float64, **_on(positions))
    step = m.zeros_like(x) if velocities is None else m.asarray(velocities, dtype=m.float64, **_on(x)) / fps
    cam_prev, gap_prev = prev or (camera, 1)
    cam_next, gap_next = nxt or (camera, 1)
    now, front = _pixels(x, camera)
    before, front_prev = _pixels(x - step * gap_prev, cam_prev)
    after, front_next = _pixels(x + step * gap_next, cam_next)
    back = _up(before - now) / gap_prev
    ahead = _up(now - after) / gap_next
    out = m.concatenate([m.where((front & front_prev)[:, None], back, 0.0),
                         m.where((front & front_next)[:, None], ahead, 0.0)], axis=1)
    return as_float32(out)


def camera_motion(depth, camera: Camera, prev: tuple[Camera, int] | None, nxt: tuple[Camera, int] | None,
                  launch: Launcher, on_device: bool = False):
    """H x W x 4 motion (``Vector`` layout) of static surfaces at view ``depth`` (m; 0 or inf:
    none, motion 0) caused by the camera moving between frames; None when it does not move.

    One Warp pass a neighbouring camera on ``launch``'s device (``kernels.static_motion``), in
    float64 as numpy did it (to rounding; 352 ms of numpy at 1024 x 1024 on a 2-core CPU, 38 ms of kernel).
    ``depth`` may be a torch tensor there; ``on_device`` gives a tensor there too."""
    moving = [c for c in (prev, nxt) if c is not None and not np.array_equal(c[0].view, camera.view)]
    if not moving:
        return None
    h, w = depth.shape
    device = launch.device
    if is_tensor(depth):
        import torch

        depth = depth.to(torch.float32).contiguous().reshape(-1)
        warp_waits_for_torch(str(device))
        depth_d = wp.from_torch(depth)
    else:
        depth_d = wp.array(np.ascontiguousarray(depth, np.float32).ravel(), dtype=float, device=device)
    out = wp.zeros(h * w, dtype=wp.vec4, device=device)
    rotation, shift = _pose(camera)
    for slot, (other, sign) in enumerate(((prev, 1.0), (nxt, -1.0))):
        if other is None:
            continue
        cam, gap = other
        launch(K.static_motion, h * w, [depth_d, w, h, camera.focal_px, rotation, shift, *_pose(cam), cam.focal_px,
                                        cam.width, cam.height, sign, float(gap), slot, out])
    if on_device:
        motion = wp.to_torch(out).reshape(h, w, 4)
        torch_waits_for_warp(str(device))
        return motion
    return out.numpy().reshape(h, w, 4)


def _pose(camera: Camera) -> tuple[wp.mat33d, wp.vec3d]:
    """The camera's world-to-view rotation and translation, in float64 for ``kernels.static_motion``."""
    return wp.mat33d(*camera.view[:3, :3].ravel()), wp.vec3d(*camera.view[:3, 3])

