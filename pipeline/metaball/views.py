"""Particles as metaballs in the network's working frame, and the thesis' random ball sets.

A convolutional network's reach is a fixed number of pixels, so a view must reach it at one scale,
in space and on screen. In space, each view is moved into its camera's frame (camera at the origin
looking down -Z) and scaled about the camera, which leaves the image unchanged, until its median ball
has radius ``metaball.working_ball_radius``; its depth code starts ``depth_margin`` in front of the
nearest ball centre and spans ``depth_span``, so a code step means the same depth in ball radii in
every view. On screen, the image is drawn at the size where the median ball's projected radius lies
within half an octave below ``metaball.working_radius_px`` (``pixel_scale``, in half-octave steps so a
sequence's scale does not change with every frame); the network's maps are resampled back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.config import MetaballConfig
from pipeline.ellipsoids import Ellipsoids
from pipeline.metaball import (
    PAPER_FOV_Y_DEG,
    MetaballParams,
    circle_input,
    ellipsoid_maps,
    metaball_targets,
    minimal_radius,
    sphere_input,
    sphere_layers,
)
from pipeline.model.scale import working_half_octaves
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
    camera: Camera         # at the working image size
    params: MetaballParams
    scale: float           # working units per scene unit
    size: tuple[int, int] = (0, 0)  # the view's own image (height, width)
    splat_radius: float = 1.0  # sphere inputs: the spheres' radius in minimal radii
    field_steps: int | None = None  # sphere inputs: Newton steps of the field normals (None: the spheres')
    shapes: np.ndarray | None = None  # N x 3 x 3 maps of ellipsoidal balls onto the unit ball (None: spheres)
    bounds: np.ndarray | None = None  # N largest semi-axes of those ellipsoids (working units)

    def circles(self, launch: Launcher, colours: np.ndarray | None = None) -> np.ndarray:
        """The 4 x H x W circle input (``pipeline.metaball.circle_input``)."""
        return circle_input(self.positions, self.radii, self.camera, self.params, launch, colours)

    def layers(self, launch: Launcher) -> dict:
        """The balls' sphere splat (``pipeline.metaball.sphere_layers``; depths in working units)."""
        return sphere_layers(self.positions, self.radii, self.camera, self.params, launch, self.splat_radius,
                             self.field_steps, self.shapes, self.bounds)

    def inputs(self, kind: str, launch: Launcher, colours: np.ndarray | None = None) -> np.ndarray:
        """The network input of ``kind``: 'circles' (the thesis') or a sphere input ('field',
        'spheres': ``sphere_input`` of ``layers``)."""
        if kind == "circles":
            return self.circles(launch, colours)
        return sphere_input(self.layers(launch))

    def targets(self, launch: Launcher, colours: np.ndarray | None = None, own_size: bool = False) -> dict:
        """The ray-marched G-buffers (``metaball_targets``) with depth back in scene units, at the
        working scale (what the network learns) or at the view's ``own_size`` (what a viewer sees)."""
        camera = self.camera
        if own_size:
            camera = Camera(camera.view, camera.fov_y_deg, self.size[1], self.size[0])
        out = metaball_targets(self.positions, self.radii, camera, self.params, launch, colours, self.shapes,
                               self.bounds)
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


def network_input(inputs: np.ndarray, m: MetaballConfig) -> np.ndarray:
    """A view's input as the generator of ``m`` sees it: the sphere input without the layers behind
    when ``m.layers`` is off (the ablation), else unchanged."""
    if m.input == "circles" or m.layers:
        return inputs
    out = inputs.copy()
    out[5:] = 0.0
    return out


def working_view(positions: np.ndarray, ball_radii, camera: Camera, m: MetaballConfig,
                 shapes: np.ndarray | None = None, bounds: np.ndarray | None = None) -> WorkingView:
    """The working frame of balls at world ``positions`` with radii ``ball_radii`` (scene units; one
    value or N) seen by ``camera``, ellipsoids where world ``shapes`` (N x 3 x 3) are given (with
    their largest semi-axes ``bounds``, computed when not given). Balls behind the camera are
    dropped."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    radii = np.broadcast_to(np.asarray(ball_radii, np.float64), (len(pos),))
    view = camera.to_view(pos) if len(pos) else pos
    front = -view[:, 2] > 0
    view, radii = view[front], radii[front]
    scale = m.working_ball_radius / float(np.median(radii)) if len(radii) else 1.0
    if shapes is not None:  # A (x - P) = A R^T (u - U) / scale for working-frame u = scale (R x + t)
        shapes, bounds = ellipsoid_maps(shapes, radii, front, camera.view[:3, :3], bounds)
        shapes, bounds = shapes / scale, bounds * scale
    view = view * scale
    near = float((-view[:, 2]).min()) - m.depth_margin if len(view) else 7.0
    h, w = camera.height, camera.width
    s = pixel_scale(view, radii * scale, camera, m.iso_level, m.working_radius_px)
    origin = Camera(np.eye(4), camera.fov_y_deg, max(1, round(w * s)), max(1, round(h * s)))
    return WorkingView(view, radii * scale, origin, params_of(m, max(near, 1e-3)), scale, (h, w), m.splat_radius,
                       m.field_steps if m.input == "field" else None, shapes, bounds)


def pixel_scale(view: np.ndarray, radii: np.ndarray, camera: Camera, iso_level: float,
                working_radius_px: float) -> float:
    """The image scale (..., 2^-1/2, 1, 2^1/2, ..., at most ``MAX_UPSCALE``: the refiner's rule,
    ``pipeline.model.scale.working_half_octaves``) that brings the median projected minimal radius
    of the balls on screen into (``working_radius_px`` / sqrt 2, ``working_radius_px``]; 1 without
    balls on screen or with a working radius of 0."""
    if working_radius_px <= 0 or not len(view):
        return 1.0
    depth = -view[:, 2]
    f = camera.focal_px
    x, y = camera.width / 2.0 + f * view[:, 0] / depth, camera.height / 2.0 - f * view[:, 1] / depth
    seen = (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
    if not seen.any():
        return 1.0
    r_px = float(np.median(f * minimal_radius(radii[seen], iso_level) / depth[seen]))
    return 2.0 ** (working_half_octaves(r_px, working_radius_px) / 2.0)


def fluid_view(positions: np.ndarray, particle_radius: float, camera: Camera, m: MetaballConfig,
               ellipsoids: Ellipsoids | None = None) -> WorkingView:
    """Fluid particles as metaballs of radius ``ball_radius_radii`` particle radii: spheres at the
    particles, or with ``metaball.anisotropic`` their ``ellipsoids`` (``particle_ellipsoids``; their
    smoothed centres and shapes) as large."""
    b = m.ball_radius_radii
    if not m.anisotropic:
        return working_view(positions, b * particle_radius, camera, m)
    if ellipsoids is None:
        raise ValueError("anisotropic metaballs (metaball.anisotropic) need the particles' ellipsoids")
    centres, shapes, bounds = (a.numpy() if hasattr(a, "numpy") else np.asarray(a)
                               for a in (ellipsoids.centres, ellipsoids.shapes, ellipsoids.bounds))
    return working_view(centres, b * particle_radius, camera, m, shapes / b, b * bounds.astype(np.float64))


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

