"""Particles as metaballs in the network's working frame, and the thesis' random ball sets.

The network sees circles in pixels and depth codes, so a view must reach it at one scale: each view
is moved into its camera's frame (camera at the origin looking down -Z) and scaled about the camera,
which leaves the image unchanged, until its median ball has radius ``metaball.working_ball_radius``.
Its depth code starts ``depth_margin`` in front of the nearest ball centre and spans ``depth_span``,
so a code step means the same depth in ball radii in every view, near or far, large or small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.config import MetaballConfig
from pipeline.metaball import PAPER_FOV_Y_DEG, MetaballParams, circle_input, metaball_targets
from pipeline.parallel import Launcher

PAPER_RADII = (0.5, 1.2)
"""Radius range of the thesis' random balls (its scene units)."""

PAPER_DEPTHS = (10.0, 20.0)
"""View-depth range of the thesis' random ball centres."""


def params_of(m: MetaballConfig, depth_near: float = 7.0) -> MetaballParams:
    """The field, march and drawing parameters of ``m`` with depth code 0 at ``depth_near``."""
    return MetaballParams(iso_level=m.iso_level, kernel_radius_radii=m.kernel_radius_radii, depth_near=depth_near,
                          depth_far=depth_near + m.depth_span, step=m.step, bisections=m.bisections,
                          outline_width=m.outline_width, outline_min_px=m.outline_min_px)


@dataclass(frozen=True)
class WorkingView:
    """One view in the working frame: ball centres and radii in working units seen by ``camera`` (the
    view's intrinsics at the origin), with the view's depth code in ``params``."""

    positions: np.ndarray  # N x 3 view-space centres times ``scale``
    radii: np.ndarray      # N ball radii in working units
    camera: Camera
    params: MetaballParams
    scale: float           # working units per scene unit

    def circles(self, launch: Launcher, colours: np.ndarray | None = None) -> np.ndarray:
        """The 4 x H x W circle input (``pipeline.metaball.circle_input``)."""
        return circle_input(self.positions, self.radii, self.camera, self.params, launch, colours)

    def targets(self, launch: Launcher, colours: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The ray-marched G-buffers (``metaball_targets``) with depth back in scene units."""
        out = metaball_targets(self.positions, self.radii, self.camera, self.params, launch, colours)
        out["depth"] = (out["depth"] / self.scale).astype(np.float32)
        return out

    def depth_code(self, depth: np.ndarray) -> np.ndarray:
        """Scene-unit view depths (0 = empty) as this view's depth code in [0, 1]."""
        p = self.params
        return np.clip((depth * self.scale - p.depth_near) / (p.depth_far - p.depth_near), 0.0, 1.0)

    def depth_of(self, code: np.ndarray) -> np.ndarray:
        """``depth_code``'s inverse: scene-unit view depths of codes."""
        p = self.params
        return ((p.depth_near + code * (p.depth_far - p.depth_near)) / self.scale).astype(np.float32)


def working_view(positions: np.ndarray, ball_radii, camera: Camera, m: MetaballConfig) -> WorkingView:
    """The working frame of balls at world ``positions`` with radii ``ball_radii`` (scene units; one
    value or N) seen by ``camera``. Balls behind the camera are dropped."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    radii = np.broadcast_to(np.asarray(ball_radii, np.float64), (len(pos),))
    view = camera.to_view(pos) if len(pos) else pos
    front = -view[:, 2] > 0
    view, radii = view[front], radii[front]
    scale = m.working_ball_radius / float(np.median(radii)) if len(radii) else 1.0
    view = view * scale
    near = float((-view[:, 2]).min()) - m.depth_margin if len(view) else 7.0
    origin = Camera(np.eye(4), camera.fov_y_deg, camera.width, camera.height)
    return WorkingView(view, radii * scale, origin, params_of(m, max(near, 1e-3)), scale)


def fluid_view(positions: np.ndarray, particle_radius: float, camera: Camera, m: MetaballConfig) -> WorkingView:
    """Fluid particles as metaballs of radius ``ball_radius_radii`` particle radii."""
    return working_view(positions, m.ball_radius_radii * particle_radius, camera, m)


def random_ball_set(rng: np.random.Generator, max_balls: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random set as the thesis draws them: 1 to ``max_balls`` balls of radius 0.5 to 1.2 with
    random colours, centred at view depths 10 to 20 inside the 60 degree view of the paper camera.
    Returns (positions, radii, colours) in the paper camera's frame (its world is its view)."""
    n = int(rng.integers(1, max_balls + 1))
    depth = rng.uniform(*PAPER_DEPTHS, n)
    half = math.tan(math.radians(PAPER_FOV_Y_DEG) / 2.0)
    x = rng.uniform(-1.0, 1.0, n) * half * depth
    y = rng.uniform(-1.0, 1.0, n) * half * depth
    positions = np.stack([x, y, -depth], axis=1)
    return positions, rng.uniform(*PAPER_RADII, n), rng.uniform(0.0, 1.0, (n, 3)).astype(np.float32)


def jittered(positions: np.ndarray, radii: np.ndarray, rng: np.random.Generator, share: float = 0.25) -> np.ndarray:
    """One of a set's repeated renderings: every ball moved by a random offset of up to ``share`` of its
    radius per axis (the thesis renders each set three times with small offsets)."""
    return positions + rng.uniform(-share, share, positions.shape) * np.asarray(radii)[:, None]

