"""Everything a frame contributes per camera: screen-space inputs and mesh targets as EXR channels.

Channel names (Blender/Nuke style): ``Z`` raw sphere depth, ``A`` fluid mask, ``thickness``;
per filter ``<f>.Z`` and ``<f>.N.X/Y/Z`` for ``gaussian``, ``bilateral`` and ``nrf``; the same
of the ellipsoid splat with an ``aniso`` prefix (``aniso.Z``, ``aniso.A``, ``aniso.thickness``,
``aniso.N.*`` unfiltered, ``aniso_nrf.*``, ``aniso_bilateral.*``); the mesh target
``target.N.X/Y/Z``, ``target.Z``, ``target.A``. Depths are positive view depths (m).
"""

from __future__ import annotations

import numpy as np

from pipeline.camera import Camera
from pipeline.config import DatasetConfig
from pipeline.ellipsoids import Ellipsoids
from pipeline.parallel import Launcher
from pipeline.screen import FILTERS, ScreenSpace
from pipeline.surface import SurfaceMesh, raytrace_maps, render_maps
from pipeline.timing import Timings

AXES = ("X", "Y", "Z")
ANISO_FILTERS = ("nrf", "bilateral")


def normal_channels(prefix: str, normals: np.ndarray) -> dict[str, np.ndarray]:
    """``{prefix}N.X``... channels of an H x W x 3 normal map."""
    return {f"{prefix}N.{a}": normals[..., k] for k, a in enumerate(AXES)}


def screen_space_inputs(positions: np.ndarray, radius: float, camera: Camera, p: DatasetConfig,
                        ss: ScreenSpace, timings: Timings | None = None,
                        filters: tuple[str, ...] | None = FILTERS, ellipsoids: Ellipsoids | None = None,
                        aniso_filters: tuple[str, ...] = ANISO_FILTERS,
                        on_device: bool = False, raw_normals: bool = True) -> dict[str, np.ndarray]:
    """Splat, filter and differentiate: the screen-space channels of one view (``filters=None``:
    no sphere splat).

    With ``ellipsoids`` the view is splatted a second time with the particles drawn as those,
    adding ``aniso.Z``, ``aniso.A``, ``aniso.thickness``, ``aniso.N.*`` (unfiltered; not without
    ``raw_normals``) and ``aniso_<f>.Z``, ``aniso_<f>.N.*`` for each of ``aniso_filters``, and
    ``aniso.density`` where the ellipsoids carry their density. ``on_device``: torch tensors left on
    the screen space's device (``ScreenSpace.inputs``)."""
    out = ss.inputs(positions, radius, camera, p, filters, timings, on_device=on_device) if filters is not None else {}
    if ellipsoids is not None:
        out.update(ss.inputs(positions, radius, camera, p, aniso_filters, timings, ellipsoids, on_device,
                             raw_normals))
    for key in [k for k in out if k.endswith(".N")]:
        out.update(normal_channels(key[:-1], out.pop(key)))
    return out


def target_channels(mesh: SurfaceMesh, camera: Camera, launch: Launcher, device: str | None = None,
                    timings: Timings | None = None) -> dict[str, np.ndarray]:
    """Ray-cast mesh normal, depth and mask of one view."""
    device = device or launch.device
    t = timings or Timings()
    with t("raycast"):
        n, d, m = render_maps(mesh, camera, launch, device)
    return {**normal_channels("target.", n), "target.Z": d, "target.A": m}


def raytraced_target_channels(kernels, radius: float, p: DatasetConfig, camera: Camera, ss: ScreenSpace,
                              launch: Launcher, device: str | None = None,
                              timings: Timings | None = None) -> dict[str, np.ndarray]:
    """The same target channels, ray-marched through the anisotropic density (no mesh)."""
    device = device or launch.device
    t = timings or Timings()
    with t("raytrace"):
        n, d, m, _ = raytrace_maps(kernels, radius, p, camera, ss, launch, device)
    return {**normal_channels("target.", n), "target.Z": d, "target.A": m}
