"""Everything a frame contributes per camera: screen-space inputs and mesh targets as EXR channels.

Channel names (Blender/Nuke style): ``Z`` raw sphere depth, ``A`` fluid mask, ``thickness``;
per filter ``<f>.Z`` and ``<f>.N.X/Y/Z`` for ``gaussian``, ``bilateral`` and ``nrf``; the mesh
target ``target.N.X/Y/Z``, ``target.Z``, ``target.A``. Depths are positive view depths (m).
"""

from __future__ import annotations

import numpy as np

from pipeline.camera import Camera
from pipeline.config import DatasetConfig
from pipeline.parallel import Launcher
from pipeline.screen import FILTERS, ScreenSpace
from pipeline.surface import SurfaceMesh, render_maps
from pipeline.timing import Timings

AXES = ("X", "Y", "Z")


def normal_channels(prefix: str, normals: np.ndarray) -> dict[str, np.ndarray]:
    """``{prefix}N.X``... channels of an H x W x 3 normal map."""
    return {f"{prefix}N.{a}": normals[..., k] for k, a in enumerate(AXES)}


def screen_space_inputs(positions: np.ndarray, radius: float, camera: Camera, p: DatasetConfig,
                        ss: ScreenSpace, timings: Timings | None = None,
                        filters: tuple[str, ...] = FILTERS) -> dict[str, np.ndarray]:
    """Splat, filter and differentiate: the screen-space channels of one view."""
    out = ss.inputs(positions, radius, camera, p, filters, timings)
    for name in filters:
        out.update(normal_channels(f"{name}.", out.pop(f"{name}.N")))
    return out


def target_channels(mesh: SurfaceMesh, camera: Camera, launch: Launcher, device: str = "cpu",
                    timings: Timings | None = None) -> dict[str, np.ndarray]:
    """Ray-cast mesh normal, depth and mask of one view."""
    t = timings or Timings()
    with t("raycast"):
        n, d, m = render_maps(mesh, camera, launch, device)
    return {**normal_channels("target.", n), "target.Z": d, "target.A": m}
