"""The refined method's mask rule: which pixels of a normal map show fluid. One rule for rendering,
evaluation and the trainer's choice of its best checkpoint."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.vectors import is_tensor, length


def normal_mask(normals: np.ndarray, threshold: float = 0.5, lengths: np.ndarray | None = None) -> np.ndarray:
    """Fluid pixels of a normal map: vectors at least ``threshold`` long (``lengths``: theirs, when
    the caller has them already)."""
    return (length(normals) if lengths is None else lengths) >= threshold


REFINED_REACH_PX = 3
"""How far (pixels at the refiner's working scale) outside the splat's fluid a refined normal may
still count as fluid. The reference surface is wider than the particles' splat: on the held-out
views only 87-90% of the mesh's pixels are splat pixels, so a refined mask held to the splat could
not reach an IoU of 0.9, and the refiner learns the rest of the silhouette from the target. Chosen on
the validation scene alone (``benchmarks/tune_inference.py``): 6.91 / 6.62 / 6.61 degrees mean at
256 px for reaches of 2 / 3 / 4 pixels, and 3 and 4 the same at 512 and 1024."""


def bounding_window(mask: np.ndarray, margin: int) -> tuple[slice, slice]:
    """Rows and columns of ``mask``'s bounding box grown by ``margin`` pixels, clipped to the image
    (``mask`` must have a pixel set)."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    h, w = mask.shape
    return (slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)),
            slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)))


@dataclass(frozen=True)
class NearestFluid:
    """Every pixel's distance to its nearest ``fluid`` pixel and where that pixel is, from one
    distance transform on the fluid's bounding box grown past ``reach_px``: every pixel outside the
    box is further away, and inside it the nearest fluid pixel is the one of the whole image
    (tested). ``near`` and the renderer's depth spread (``spread``) share it.

    Of a torch tensor (a GPU's maps) the transform is made where the tensor lies, on the whole
    image (``pipeline.screen.nearest_fluid_pixels``: scipy's numbers, no trip to the host), and its
    fields, ``near`` and ``spread`` are tensors there; an image without fluid is allowed then."""

    shape: tuple[int, int]
    window: tuple[slice, slice]
    distance: np.ndarray  # on the window
    rows: np.ndarray      # the nearest fluid pixel's row and column, in window coordinates
    cols: np.ndarray

    @classmethod
    def of(cls, fluid: np.ndarray, reach_px: float) -> NearestFluid:
        """The transform of ``fluid`` (which must have a pixel) for reaches up to ``reach_px``."""
        if is_tensor(fluid):
            from pipeline.screen import nearest_fluid_pixels

            return cls(tuple(fluid.shape), (slice(None), slice(None)), *nearest_fluid_pixels(fluid))
        from scipy.ndimage import distance_transform_edt

        window = bounding_window(fluid, int(np.ceil(reach_px)) + 1)
        distance, (rows, cols) = distance_transform_edt(~fluid[window], return_indices=True)
        return cls(fluid.shape, window, distance, rows, cols)

    def near(self, reach_px: float) -> np.ndarray:
        """Pixels at most ``reach_px`` (no more than the reach it was made for) from a fluid pixel."""
        if is_tensor(self.distance):
            return self.distance <= reach_px
        out = np.zeros(self.shape, bool)
        out[self.window] = self.distance <= reach_px
        return out

    def spread(self, values: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """``values`` at each ``mask`` pixel taken from its nearest fluid pixel (0 off the mask; the
        mask must lie within the reach)."""
        if is_tensor(self.distance):
            import torch

            found = self.rows >= 0
            picked = values[self.rows.clamp_min(0).long(), self.cols.clamp_min(0).long()]
            return torch.where(mask & found, picked, 0.0).to(torch.float32)
        w = self.window
        out = np.zeros(values.shape, np.float32)
        out[w] = np.where(mask[w], values[w][self.rows, self.cols], 0.0)
        return out


def near(fluid: np.ndarray, reach_px: float) -> np.ndarray:
    """Pixels at most ``reach_px`` (Euclidean, pixel centres) from a ``fluid`` pixel."""
    if reach_px <= 0 or not fluid.any():
        return fluid
    return NearestFluid.of(fluid, reach_px).near(reach_px)


def refined_mask(normals: np.ndarray, fluid: np.ndarray, threshold: float = 0.5, reach_px: float = 0.0,
                 lengths: np.ndarray | None = None, nearest: NearestFluid | None = None) -> np.ndarray:
    """The pixels a refined normal map shows as fluid: where the predicted normal is at least
    ``threshold`` long (Choi et al. 3.3 drop shorter ones as noise) within ``reach_px`` of the
    splat's fluid (``REFINED_REACH_PX`` at the working scale, scaled to the image by the renderer).
    The one rule for rendering, evaluation and the trainer's choice of its best checkpoint.
    ``lengths`` and ``nearest`` (of ``fluid``) save recomputing what the caller has. ``normals`` (and
    ``lengths``) may be a torch tensor on the refiner's device (``lengths`` H x W): the mask is then
    one there too."""
    within = nearest.near(reach_px) if nearest is not None and reach_px > 0 else near(fluid, reach_px)
    long_enough = normal_mask(normals, threshold, lengths)
    if not isinstance(long_enough, np.ndarray) and not is_tensor(within):
        import torch

        within = torch.from_numpy(within).to(long_enough.device)
    return long_enough & within
