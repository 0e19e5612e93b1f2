"""The ``metaball`` method: fluid particles drawn as circles, turned by the trained pix2pix generator
into the G-buffers of their metaball surface (Horvath 2019), and that surface's own ray-marched maps.

Both run in the working frame of ``pipeline.metaball.views`` with the metaball settings the
generator was trained with (its checkpoint's ``config``), so a view's scale, distance and size on
screen do not change what the network sees beyond the particles' size in pixels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.camera import Camera
from pipeline.config import MetaballConfig, from_dict
from pipeline.metaball import decode_gbuffers
from pipeline.metaball.train import SHIPPED_WEIGHTS, load_generator, predict
from pipeline.metaball.views import WorkingView, fluid_view
from pipeline.parallel import Launcher

SIDE_MULTIPLE = 256
"""The U-Net's input sides must be multiples of this (8 halvings)."""


class MetaballNet:
    """A trained metaball generator and the metaball settings it was trained with."""

    def __init__(self, path: Path | str = SHIPPED_WEIGHTS, device: str = "cpu"):
        self.device = torch.device(device)
        self.generator, state = load_generator(Path(path), str(self.device))
        self.config: MetaballConfig = from_dict(MetaballConfig, state["config"], path, "config")
        self.path = Path(path)

    def view(self, positions: np.ndarray, particle_radius: float, camera: Camera) -> WorkingView:
        """The particles' working view for ``camera``."""
        return fluid_view(positions, particle_radius, camera, self.config)

    def gbuffers(self, positions: np.ndarray, particle_radius: float, camera: Camera,
                 launch: Launcher) -> dict[str, np.ndarray]:
        """Predicted ``normals`` (view space, unit), ``depth`` (scene units, 0 empty), ``mask`` and
        ``colour`` of one view (H x W [x 3]). Images whose sides are not multiples of 256 are padded
        with empty pixels for the network and cropped back."""
        view = self.view(positions, particle_radius, camera)
        h, w = camera.height, camera.width
        circles = view.circles(launch)
        side_h, side_w = (-(-s // SIDE_MULTIPLE) * SIDE_MULTIPLE for s in (h, w))
        padded = np.zeros((4, side_h, side_w), np.float32)
        padded[:, :h, :w] = circles
        out = decode_gbuffers(predict(self.generator, padded, self.device)[:, :h, :w], view.params)
        mask = out["mask"] > 0
        # decode_gbuffers' depth is in working units: back to the scene's
        out["depth"] = np.where(mask, out["depth"] / view.scale, 0.0).astype(np.float32)
        return out

    def targets(self, positions: np.ndarray, particle_radius: float, camera: Camera,
                launch: Launcher) -> dict[str, np.ndarray]:
        """The ray-marched metaball surface of the same particles (``metaball_targets``; depth in scene
        units): what the network was trained to predict."""
        return self.view(positions, particle_radius, camera).targets(launch)
