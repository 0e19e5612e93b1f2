"""The scene behind the fluid (floor, container walls, obstacles) rasterised with pyrender.

Headless through EGL (``PYOPENGL_PLATFORM=egl``, set here when unset). pyrender returns 8-bit
colour, read as sRGB and converted to linear, and linear view depth (0 where nothing is hit).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.config import Obstacle, RenderConfig, SceneConfig
from pipeline.shading import srgb_to_linear

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _checker_floor(lo, hi, tile: float, y: float):
    import trimesh

    xs = np.arange(lo[0], hi[0] + 1e-9, tile)
    zs = np.arange(lo[2], hi[2] + 1e-9, tile)
    verts, faces, colours = [], [], []
    for i in range(len(xs) - 1):
        for k in range(len(zs) - 1):
            base = len(verts)
            verts += [(xs[i], y, zs[k]), (xs[i + 1], y, zs[k]), (xs[i + 1], y, zs[k + 1]), (xs[i], y, zs[k + 1])]
            faces += [(base, base + 2, base + 1), (base, base + 3, base + 2)]
            c = (200, 200, 195, 255) if (i + k) % 2 == 0 else (70, 75, 85, 255)
            colours += [c, c]
    return trimesh.Trimesh(np.array(verts), np.array(faces), face_colors=np.array(colours, np.uint8), process=False)


def _box(lo, hi, colour):
    import trimesh

    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    box = trimesh.creation.box(extents=hi - lo)
    box.apply_translation((lo + hi) / 2)
    box.visual.face_colors = colour
    return box


def _light_pose(direction) -> np.ndarray:
    """Pose whose -Z axis points along the light's travel (from the sun into the scene)."""
    from pipeline.camera import look_at

    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    return np.linalg.inv(look_at(d, (0.0, 0.0, 0.0)))


@dataclass(frozen=True)
class Surroundings:
    """What stands around the fluid: a floor under the box ``lo``..``hi`` (Y up), the container's
    back and side walls when ``walls``, and the obstacles."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    obstacles: tuple[Obstacle, ...] = ()
    walls: bool = True

    @classmethod
    def of_scene(cls, scene: SceneConfig) -> Surroundings:
        """A configured scene's container and obstacles."""
        return cls(scene.domain_lo, scene.domain_hi, scene.obstacles)


class BackgroundRenderer:
    """Renders the floor, walls and obstacles from any camera (cached per camera)."""

    def __init__(self, around: Surroundings, p: RenderConfig, width: int, height: int):
        import pyrender

        self._pyrender = pyrender
        lo, hi = np.asarray(around.lo, float), np.asarray(around.hi, float)
        span = float((hi - lo).max())
        self.scene = pyrender.Scene(ambient_light=np.full(3, 0.35), bg_color=np.array([0.0, 0.0, 0.0, 0.0]))
        floor_lo = lo - np.array([1.5, 0, 1.5]) * span
        floor_hi = hi + np.array([1.5, 0, 1.5]) * span
        tile = span / 8.0
        # one pyrender mesh of every surface, drawn in this order: the scene keeps its meshes in a
        # set, whose order differs from process to process, and a seam's pixels where two meshes
        # meet at one depth go to whichever is drawn first
        primitives = list(pyrender.Mesh.from_trimesh(_checker_floor(floor_lo, floor_hi, tile, lo[1] - 1e-3),
                                                     smooth=False).primitives)
        wall = 0.02 * span
        walls = [  # back wall and the two side walls of the container (the front stays open)
            ((lo[0] - wall, lo[1], lo[2] - wall), (hi[0] + wall, hi[1], lo[2]), (170, 180, 190, 255)),
            ((lo[0] - wall, lo[1], lo[2]), (lo[0], hi[1] * 0.5, hi[2]), (150, 160, 175, 255)),
            ((hi[0], lo[1], lo[2]), (hi[0] + wall, hi[1] * 0.5, hi[2]), (150, 160, 175, 255)),
        ]
        for a, b, c in walls if around.walls else ():
            primitives += pyrender.Mesh.from_trimesh(_box(a, b, c), smooth=False).primitives
        import trimesh

        for ob in around.obstacles:
            if ob.shape == "sphere":
                m = trimesh.creation.icosphere(subdivisions=3, radius=ob.radius)
                m.apply_translation(ob.center)
                m.visual.vertex_colors = (210, 120, 60, 255)
            else:
                m = _box(ob.lo, ob.hi, (210, 120, 60, 255))
            primitives += pyrender.Mesh.from_trimesh(m, smooth=ob.shape == "sphere").primitives
        self.scene.add(pyrender.Mesh(primitives=primitives))
        self.scene.add(pyrender.DirectionalLight(color=np.ones(3), intensity=p.light_intensity),
                       pose=_light_pose(p.light_dir))
        self.renderer = pyrender.OffscreenRenderer(width, height)
        self.width, self.height = width, height
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def render(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Linear RGB (H x W x 3) and view depth (H x W, 0 = nothing) from ``camera``."""
        key = camera.view.tobytes()
        if key not in self._cache:
            pr = self._pyrender
            cam = pr.PerspectiveCamera(yfov=math.radians(camera.fov_y_deg), aspectRatio=camera.width / camera.height,
                                       znear=0.01, zfar=1000.0)
            node = self.scene.add(cam, pose=camera.cam_to_world)
            colour, depth = self.renderer.render(self.scene)
            self.scene.remove_node(node)
            if len(self._cache) > 4:
                self._cache.clear()
            self._cache[key] = (srgb_to_linear(colour[..., :3]), depth.astype(np.float32))
        return self._cache[key]

    def close(self) -> None:
        """Release the GL context."""
        self.renderer.delete()
