"""One frame from particles to a shaded image, with any normal-map method.

Methods: ``refined`` (bilateral screen-space input through the generator, pixels whose predicted
normal is shorter than a threshold dropped), ``gaussian``, ``bilateral``, ``nrf`` (screen-space
filters of sphere splats), ``aniso`` and ``aniso_nrf`` (the particles splatted as their
anisotropic ellipsoids, normals of that depth unfiltered or after the narrow-range filter) and
``mesh`` (the anisotropic marching-cubes surface, the reference).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.camera import Camera
from pipeline.config import DatasetConfig, RenderConfig
from pipeline.evaluate.metrics import refined_mask
from pipeline.exr import stack
from pipeline.model.data import input_channels, make_input
from pipeline.model.inference import Refiner
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.shading import Shader
from pipeline.surface import anisotropic_kernels, particle_ellipsoids, reconstruct
from pipeline.timing import Timings
from pipeline.views import raytraced_target_channels, screen_space_inputs, target_channels

METHODS = ("gaussian", "bilateral", "nrf", "aniso", "aniso_nrf", "refined", "mesh")
ANISO_METHODS = ("aniso", "aniso_nrf")
NAMES = {"gaussian": "Gaussian", "bilateral": "bilateral", "nrf": "narrow-range", "aniso": "ellipsoids",
         "aniso_nrf": "ellipsoids + narrow-range", "refined": "refined (cGAN)", "mesh": "mesh (reference)"}
"""How each method is called in reports, comparison titles and figures."""


def method_maps(method: str, channels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Normals, depth, mask and thickness of a screen-space filter method (``gaussian``,
    ``bilateral``, ``nrf``, ``aniso``, ``aniso_nrf``) from a view's channels."""
    splat = "aniso." if method in ANISO_METHODS else ""
    return {"normals": stack(channels, f"{method}.N."), "depth": channels[f"{method}.Z"],
            "mask": channels[f"{splat}A"], "thickness": channels[f"{splat}thickness"]}


@dataclass
class RenderedFrame:
    """The passes of one rendered frame (H x W [x k], linear, view space)."""

    beauty: np.ndarray      # RGBA
    normals: np.ndarray     # the normal map that was shaded
    depth: np.ndarray       # fluid view depth, 0 where no fluid
    thickness: np.ndarray
    mask: np.ndarray        # pixels the method calls fluid

    def channels(self) -> dict[str, np.ndarray]:
        """EXR channels named the Blender/Nuke way."""
        out = {c: self.beauty[..., k] for k, c in enumerate("RGBA")}
        out.update({f"N.{a}": self.normals[..., k] for k, a in enumerate("XYZ")})
        out.update({"Z": self.depth, "thickness": self.thickness, "mask": self.mask})
        return out


def refine(refiner: Refiner, channels: dict[str, np.ndarray], threshold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Refined unit normals and their fluid mask from a view's screen-space channels.

    Pixels whose predicted normal is shorter than ``threshold`` are dropped as noise (Choi et al.,
    section 3.3), and so are pixels without splatted fluid (there is no depth to shade there).
    """
    names = input_channels(refiner.splat)
    fluid = channels[names.fluid] > 0
    n = refiner(make_input(channels, refiner.auxiliary, refiner.splat), fluid)
    mask = refined_mask(n, fluid, threshold)
    length = np.linalg.norm(n, axis=-1)
    return np.where(mask[..., None], n / np.maximum(length, 1e-6)[..., None], 0.0).astype(np.float32), mask


def normal_source(method: str, positions: np.ndarray, radius: float, camera: Camera, filters: DatasetConfig,
                  ss: ScreenSpace, launch: Launcher, refiner: Refiner | None = None, threshold: float = 0.5,
                  timings: Timings | None = None, frame_cache: dict | None = None) -> dict[str, np.ndarray]:
    """Normals, depth, mask and thickness of a method for one view.

    ``frame_cache`` (a dict the caller keeps per frame) shares the particles' anisotropic kernels
    between the methods and views of one frame that need them (ellipsoids, refined on ellipsoids,
    the mesh)."""
    t = timings or Timings()
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if method == "refined" and refiner is None:
        raise ValueError("the refined method needs a generator")
    cache = frame_cache if frame_cache is not None else {}

    def kernels():
        if "kernels" not in cache:
            with t("anisotropy"):
                cache["kernels"] = anisotropic_kernels(np.asarray(positions, np.float32), radius, filters, launch,
                                                       ss.device)
        return cache["kernels"]

    if method in ANISO_METHODS or (method == "refined" and refiner.splat == "ellipsoid"):
        ellipsoids = particle_ellipsoids(positions, radius, filters, launch, ss.device, kernels())
        aniso_filter = {"aniso": (), "aniso_nrf": ("nrf",), "refined": ("bilateral",)}[method]
        with t("inputs"):
            ch = screen_space_inputs(positions, radius, camera, filters, ss, t, filters=None, ellipsoids=ellipsoids,
                                     aniso_filters=aniso_filter)
        if method != "refined":
            return method_maps(method, ch)
    else:
        screen_filter = "bilateral" if method in ("refined", "mesh") else method
        with t("inputs"):
            ch = screen_space_inputs(positions, radius, camera, filters, ss, t, filters=(screen_filter,))
    if method == "refined":
        names = input_channels(refiner.splat)
        with t("refiner"):
            n, mask = refine(refiner, ch, threshold)
        return {"normals": n, "depth": np.where(mask, ch[names.blurred], 0.0), "mask": mask.astype(np.float32),
                "thickness": ch[names.thickness]}
    thickness = ch["thickness"]
    if method == "mesh":
        with t("mesh"):
            if filters.target == "raytrace":
                tc = raytraced_target_channels(kernels(), radius, filters, camera, ss, launch, ss.device)
            else:
                if "mesh" not in cache:
                    cache["mesh"] = reconstruct(positions, radius, filters, launch, ss.device, kernels())
                tc = target_channels(cache["mesh"], camera, launch)
        n = np.stack([tc[f"target.N.{a}"] for a in "XYZ"], -1)
        return {"normals": n, "depth": tc["target.Z"], "mask": tc["target.A"], "thickness": thickness}
    return method_maps(method, ch)


def shade_frame(source: dict[str, np.ndarray], background: np.ndarray, background_depth: np.ndarray,
                camera: Camera, p: RenderConfig, shader: Shader, timings: Timings | None = None) -> RenderedFrame:
    """Deferred shading of a normal source over the background."""
    t = timings or Timings()
    with t("shading"):
        beauty = shader.shade(source["normals"], source["depth"], source["thickness"], source["mask"], background,
                              background_depth, camera, p)
    return RenderedFrame(beauty, source["normals"], source["depth"], source["thickness"], source["mask"])
