"""The ``metaball`` method: fluid particles as metaballs drawn cheaply (spheres or the thesis' circles),
turned by the trained generator into the G-buffers of their metaball surface (Horvath 2019), and that
surface's own ray-marched maps.

Both run in the working frame of ``pipeline.metaball.views`` with the metaball settings the
generator was trained with (its checkpoint's ``config``): a view's scale, distance and size on screen
do not change what the network sees. The network runs on the working-scale image's part that can
show surface (the balls' box, grown by the field's reach), and its maps are resampled to the view.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import distance_transform_edt

from pipeline.camera import Camera
from pipeline.config import MetaballConfig, from_dict
from pipeline.ellipsoids import Ellipsoids
from pipeline.metaball import decode_gbuffers, sphere_input
from pipeline.metaball.train import SHIPPED_WEIGHTS, load_generator, predict
from pipeline.metaball.views import WorkingView, fluid_view, network_input
from pipeline.model.scale import resize_map
from pipeline.parallel import Launcher
from pipeline.vectors import length


class MetaballNet:
    """A trained metaball generator and the metaball settings it was trained with."""

    def __init__(self, path: Path | str = SHIPPED_WEIGHTS, device: str = "cpu"):
        self.device = torch.device(device)
        self.generator, state = load_generator(Path(path), str(self.device))
        self.generator.to(memory_format=torch.channels_last)
        # checkpoints from before the choice saw the thesis' circles at the view's own size
        config = {"input": "circles", "working_radius_px": 0.0, "architecture": "unet", "crop": 0, "splat_radius": 1.0,
                  "residual": False, "anisotropic": False, "ball_radius_radii": 1.0, **state["config"]}
        self.config: MetaballConfig = from_dict(MetaballConfig, config, path, "config")
        self.path = Path(path)

    def view(self, positions: np.ndarray, particle_radius: float, camera: Camera,
             ellipsoids: Ellipsoids | None = None) -> WorkingView:
        """The particles' working view for ``camera`` (``ellipsoids``: what anisotropic metaballs
        are made of, ``fluid_view``)."""
        return fluid_view(positions, particle_radius, camera, self.config, ellipsoids)

    def gbuffers(self, positions: np.ndarray, particle_radius: float, camera: Camera,
                 launch: Launcher, ellipsoids: Ellipsoids | None = None) -> dict[str, np.ndarray]:
        """Predicted ``normals`` (view space, unit), ``depth`` (scene units, 0 empty), ``mask`` and
        ``colour`` of one view (H x W [x 3])."""
        m = self.config
        view = self.view(positions, particle_radius, camera, ellipsoids)
        layers = view.layers(launch) if m.input != "circles" else None
        inputs = network_input(sphere_input(layers) if layers is not None else view.inputs(m.input, launch), m)
        h, w = inputs.shape[1:]
        rows, cols = _reach(inputs, math.ceil(m.kernel_radius_radii * m.working_radius_px) + 2)
        out = {"colour": np.zeros((h, w, 3), np.float32), "depth": np.zeros((h, w), np.float32),
               "normals": np.zeros((h, w, 3), np.float32), "mask": np.zeros((h, w), np.float32)}
        if rows.stop > rows.start:
            part = decode_gbuffers(predict(self.generator, inputs[:, rows, cols], self.device), view.params)
            if layers is not None:  # depth from the splat (the sphere input has none to learn from)
                part["depth"] = nearest_depth(layers["front"][rows, cols])
            for key, a in part.items():
                out[key][rows, cols] = a
        mask = out["mask"] > 0
        # decode_gbuffers' depth is in working units: back to the scene's
        out["depth"] = np.where(mask, out["depth"] / view.scale, 0.0).astype(np.float32)
        return to_size(out, view.size)

    def targets(self, positions: np.ndarray, particle_radius: float, camera: Camera,
                launch: Launcher, ellipsoids: Ellipsoids | None = None) -> dict[str, np.ndarray]:
        """The ray-marched metaball surface of the same particles (``metaball_targets``; depth in scene
        units) at the view's own size: what the network's maps stand in for."""
        return self.view(positions, particle_radius, camera, ellipsoids).targets(launch, own_size=True)


def nearest_depth(front: np.ndarray) -> np.ndarray:
    """Each pixel's depth of the nearest pixel a sphere covers: the blended surface's depth on and
    just around the splat (it lies within a fraction of a ball radius of the spheres' front)."""
    covered = front > 0
    if covered.all() or not covered.any():
        return front
    _, (r, c) = distance_transform_edt(~covered, return_indices=True)
    return front[r, c]


def _reach(inputs: np.ndarray, margin: int) -> tuple[slice, slice]:
    """Rows and columns of the input's box of drawn pixels grown by ``margin`` (empty slices when
    nothing is drawn); the whole image when ``margin`` is not positive (a field without cut-off)."""
    h, w = inputs.shape[1:]
    if margin <= 2:
        return slice(0, h), slice(0, w)
    drawn = np.abs(inputs).max(axis=0) > 0
    r, c = np.flatnonzero(drawn.any(axis=1)), np.flatnonzero(drawn.any(axis=0))
    if r.size == 0:
        return slice(0, 0), slice(0, 0)
    return (slice(max(r[0] - margin, 0), min(r[-1] + 1 + margin, h)),
            slice(max(c[0] - margin, 0), min(c[-1] + 1 + margin, w)))


def to_size(maps: dict[str, np.ndarray], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """G-buffers (``normals``, ``depth``, ``colour``, ``mask``) resampled to ``size`` (h, w): averaged
    over the surface part of each new pixel when shrinking, interpolated over it when growing; a
    pixel is surface where at least half of it is."""
    mask = maps["mask"]
    if tuple(size) == mask.shape or 0 in size:
        return maps
    m = (mask > 0).astype(np.float32)
    stacked = np.concatenate([np.moveaxis(maps["normals"], -1, 0), maps["depth"][None],
                              np.moveaxis(maps["colour"], -1, 0)]) * m
    mode = "area" if size[0] < mask.shape[0] else "bilinear"
    both = resize_map(torch.from_numpy(np.concatenate([stacked, m[None]]).astype(np.float32)), size, mode).numpy()
    cover = both[-1]
    keep = cover >= 0.5
    values = both[:-1] / np.maximum(cover, 1e-6)
    n = np.moveaxis(values[:3], 0, -1)
    n = n / np.maximum(length(n), 1e-12)[..., None]
    return {"normals": np.where(keep[..., None], n, 0.0).astype(np.float32),
            "depth": np.where(keep, values[3], 0.0).astype(np.float32),
            "colour": np.where(keep[..., None], np.moveaxis(values[4:7], 0, -1), 0.0).astype(np.float32),
            "mask": keep.astype(np.float32)}
