"""One frame from particles to a shaded image, with any normal-map method.

Methods: ``refined`` (bilateral screen-space input through the generator, pixels whose predicted
normal is shorter than a threshold dropped), ``metaball`` (the particles as circles through the
pix2pix generator of ``pipeline.metaball``, Horvath 2019), ``gaussian``, ``bilateral``, ``nrf`` (screen-space
filters of sphere splats), ``aniso`` and ``aniso_nrf`` (the particles splatted as their
anisotropic ellipsoids, normals of that depth unfiltered or after the narrow-range filter) and
``mesh`` (the anisotropic marching-cubes surface, the reference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import warp as wp

from pipeline.camera import Camera
from pipeline.config import METHODS, DatasetConfig, RenderConfig
from pipeline.device import on_torch_stream
from pipeline.ellipsoids import Ellipsoids
from pipeline.exr import camera_attributes, stack, write_exr
from pipeline.masks import REFINED_REACH_PX, NearestFluid, bounding_window, refined_mask
from pipeline.model.data import RELIEF_WINDOW_RADII, input_channels, prepare
from pipeline.model.inference import Refiner, fluid_window
from pipeline.model.scale import (
    MAX_WORKING_PIXELS,
    UPSCALE_BELOW_PX,
    median_radius_px,
    resize_normal_map,
    working_scale,
)
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.screen import kernels as K
from pipeline.shading import Shader
from pipeline.surface import anisotropic_kernels, kernel_densities, particle_ellipsoids, reconstruct, seen_kernels
from pipeline.timing import Timings
from pipeline.vectors import as_float32, host, is_tensor, length, xp
from pipeline.views import raytraced_target_channels, screen_space_inputs, target_channels

if TYPE_CHECKING:  # the metaball network's module (and its scipy) loads only where that method runs
    from pipeline.metaball.inference import MetaballNet

ANISO_METHODS = ("aniso", "aniso_nrf")
NAMES = {"gaussian": "Gaussian", "bilateral": "bilateral", "nrf": "narrow-range", "aniso": "ellipsoids",
         "aniso_nrf": "ellipsoids + narrow-range", "refined": "refined (cGAN)", "metaball": "metaballs (network)",
         "mesh": "mesh (reference)"}
"""How each method is called in reports, comparison titles and figures."""


def method_maps(method: str, channels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Normals, depth, mask and thickness of a screen-space filter method (``gaussian``,
    ``bilateral``, ``nrf``, ``aniso``, ``aniso_nrf``) from a view's channels."""
    splat = "aniso." if method in ANISO_METHODS else ""
    return {"normals": stack(channels, f"{method}.N."), "depth": channels[f"{method}.Z"],
            "mask": channels[f"{splat}A"], "thickness": channels[f"{splat}thickness"]}


LAYER = "ViewLayer"
"""The one render layer every pass of a frame belongs to (channel ``ViewLayer.<Pass>.<Channel>``)."""

PASSES = {"Combined": "RGBA", "Depth": "Z", "Fluid": "RGBA", "Thickness": "X", "Mask": "X", "Normal": "XYZ",
          "ViewNormal": "XYZ", "Vector": "XYZW"}
"""The passes of a rendered frame and their channels, in file order (docs/compositing.md)."""

HALF_PASSES = ("Combined", "Fluid", "Mask")
"""Passes stored as half floats under ``render.exr_half: colour``: colour, and the 0/1 mask (exact in
half)."""


def channel_names(passes: dict[str, str] = PASSES) -> list[str]:
    """``ViewLayer.<Pass>.<Channel>`` names of the passes."""
    return [f"{LAYER}.{name}.{c}" for name, chans in passes.items() for c in chans]


@dataclass
class RenderedFrame:
    """The passes of one rendered frame (H x W [x k], linear; colour premultiplied by alpha)."""

    beauty: np.ndarray         # RGBA: the fluid over the background (alpha 1) or over nothing
    fluid: np.ndarray          # RGBA: the fluid alone (0 where it is hidden or absent)
    depth: np.ndarray          # view depth of the nearest surface (m), +inf where there is none
    normals: np.ndarray        # the shaded unit normals in view space, 0 outside the fluid
    normals_world: np.ndarray  # the same in world space
    thickness: np.ndarray      # fluid thickness along the view ray (m)
    mask: np.ndarray           # pixels the method calls fluid (before the depth test)
    motion: np.ndarray | None = None  # H x W x 4 screen motion (pipeline.screen.motion), None: 0

    def passes(self) -> dict[str, np.ndarray]:
        """Each pass of ``PASSES`` as an H x W x k array."""
        h, w = self.depth.shape
        motion = self.motion if self.motion is not None else np.zeros((h, w, 4), np.float32)
        return {"Combined": self.beauty, "Depth": self.depth[..., None], "Fluid": self.fluid,
                "Thickness": self.thickness[..., None], "Mask": self.mask[..., None], "Normal": self.normals_world,
                "ViewNormal": self.normals, "Vector": motion}

    def channels(self, half: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
        """EXR channels named ``ViewLayer.<Pass>.<Channel>``, which Blender reads as one render
        layer with every pass and Nuke as one layer per pass (docs/compositing.md); those named in
        ``half`` already as contiguous float16 planes (torch's vectorised conversion: a 1080p
        frame's 18 half channels in 16 ms of the writer thread against numpy's 52)."""
        out = {}
        for name, data in self.passes().items():
            names = [f"{LAYER}.{name}.{c}" for c in PASSES[name]]
            if half and all(n in half for n in names):
                planes = torch.from_numpy(np.ascontiguousarray(data, np.float32)).permute(2, 0, 1)
                out.update(zip(names, planes.to(torch.float16).contiguous().numpy(), strict=True))
            else:
                out.update((n, data[..., k]) for k, n in enumerate(names))
        return out

    @staticmethod
    def half_channels(which: str) -> tuple[str, ...]:
        """Channel names stored as half floats for ``render.exr_half`` ('none', 'colour',
        'all_but_depth', 'all')."""
        if which == "all":
            return tuple(channel_names())
        if which == "all_but_depth":
            return tuple(channel_names({k: v for k, v in PASSES.items() if k != "Depth"}))
        if which == "colour":
            return tuple(channel_names({k: PASSES[k] for k in HALF_PASSES}))
        return ()

    def write(self, path, p: RenderConfig, camera: Camera, fps: float, frame: int) -> None:
        """The frame's EXR as the renderer writes it: every pass, ``render.exr_half`` and
        ``render.exr_compression``, the camera in the header."""
        half = self.half_channels(p.exr_half)
        write_exr(path, self.channels(half), half=half, compression=p.exr_compression,
                  attributes=camera_attributes(camera, fps, p.sensor_width_mm, frame))


def refine(refiner: Refiner, channels: dict[str, np.ndarray], threshold: float = 0.5, focal_px: float | None = None,
           radius: float | None = None, timings: Timings | None = None,
           on_device: bool | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``refine_view`` of the fluid's part of the view (``refine_window``): the same numbers (tested),
    without preparing, resampling and masking the empty rest of a wide frame."""
    names = input_channels(refiner.splat)
    window = refine_window(refiner, channels[names.raw], channels[names.fluid] > 0, focal_px, radius)
    if window is None:
        return refine_view(refiner, channels, threshold, focal_px, radius, timings, on_device)
    ys, xs = window
    part = {c: channels[c][ys, xs] for c in refiner.spec.view_channels}
    n, mask, depth = refine_view(refiner, part, threshold, focal_px, radius, timings, on_device)
    x = xp(n)
    h, w = channels[names.raw].shape
    full = [x.zeros((h, w, 3), dtype=n.dtype), x.zeros((h, w), dtype=mask.dtype), x.zeros((h, w), dtype=depth.dtype)]
    if is_tensor(n):
        full = [a.to(n.device) for a in full]
    for whole, cut in zip(full, (n, mask, depth), strict=True):
        whole[ys, xs] = cut
    return tuple(full)


def refine_window(refiner: Refiner, raw, fluid, focal_px: float | None,
                  radius: float | None) -> tuple[slice, slice] | None:
    """The part of a view ``refine_view`` gives the same numbers on as on the whole: the fluid's box
    grown by what reaches a fluid pixel at the working scale (the generator's receptive radius, the
    relief feature's window, the mask's reach), starting on a multiple of the generator's stride
    there, and for an area-averaged frame on whole blocks of it. None where no part would do: no
    fluid, a working scale that is no power of two (its resampling grid depends on the image's size),
    or a box that is most of the image anyway."""
    spec = refiner.spec
    scale = 1.0
    if spec.features == "radius" and focal_px and radius:
        scale = working_scale(raw, focal_px, radius, spec.working_radius_px, MAX_WORKING_PIXELS, UPSCALE_BELOW_PX)
    power = math.log2(scale)
    block = round(1.0 / scale) if scale < 1.0 else 1
    h, w = raw.shape
    if abs(power - round(power)) > 1e-9 or h % block or w % block:
        return None
    box = fluid_window(fluid, 0, 1)
    if box is None:
        return None
    r_px = median_radius_px(raw, focal_px, radius) * scale if focal_px and radius else 1.0
    reach = refiner.margin + refiner.stride + RELIEF_WINDOW_RADII * r_px + REFINED_REACH_PX + 2
    margin = math.ceil(reach / scale)
    align = refiner.stride * block  # a stride of working pixels, whole area blocks
    y0, x0 = (max(0, v - margin) // align * align for v in box[::2])
    y1, x1 = (min(n, -(-(v + margin) // align) * align) for v, n in ((box[1], h), (box[3], w)))
    if (y1 - y0) * (x1 - x0) > 0.8 * h * w:
        return None
    return slice(y0, y1), slice(x0, x1)


def refine_view(refiner: Refiner, channels: dict[str, np.ndarray], threshold: float = 0.5,
                focal_px: float | None = None, radius: float | None = None, timings: Timings | None = None,
                on_device: bool | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refined unit normals, their fluid mask and depth from a view's screen-space channels.

    The view goes to the refiner's working scale, upscaled only within ``MAX_WORKING_PIXELS`` and for
    particles under ``UPSCALE_BELOW_PX``, and its output back to the view's size
    (``pipeline.model.scale``); scale-free inputs need the image's focal length in pixels and the
    particle radius. Pixels whose predicted normal is shorter
    than ``threshold`` are dropped as noise (Choi et al., section 3.3), and so are pixels further from
    the splat's fluid than ``REFINED_REACH_PX`` working pixels (the reference surface is wider than
    the splat; its depth there is the nearest splat pixel's: ``extend_depth``, here from the same distance transform as
    the reach when the filtered depth covers the splat, as the screen-space filters make it).
    ``timings`` gets 'prepare', 'network' and 'post'. The input is made ``on_device`` (default: when
    the refiner is not on the CPU): its five maps go there once and become the input in torch, to
    within 5e-5 of numpy's (tested); on the CPU numpy makes it, as in training. The channels may be
    torch tensors on the device already (``ScreenSpace.inputs(on_device=True)``): the normals, mask
    and depth then stay tensors there, for the shader, and nothing waits for the network here.
    """
    t = timings or Timings()
    names = input_channels(refiner.splat)
    tensors = is_tensor(channels[names.raw])
    device_way = refiner.device.type != "cpu" if on_device is None else on_device
    if tensors or device_way:  # the reach and the depth where the network's output lies
        fluid = torch.as_tensor(channels[names.fluid], device=refiner.device) > 0
        blurred = torch.as_tensor(channels[names.blurred], device=refiner.device)
    else:
        fluid, blurred = channels[names.fluid] > 0, channels[names.blurred]
    with t("prepare"):
        source = channels
        if device_way:  # the filtered depth is on the device already (above)
            wanted = [c for c in refiner.spec.view_channels if c not in (names.blurred, names.fluid)]
            source = {c: torch.as_tensor(channels[c], device=refiner.device) for c in wanted}
            source[names.blurred] = blurred
        view = prepare(source, refiner.spec, focal_px, radius, max_pixels=MAX_WORKING_PIXELS,
                       upscale_below_px=UPSCALE_BELOW_PX)
    with t("network"):
        n = refiner.run(view.inputs, view.fluid)  # 3 x h x w, on the refiner's device (queued on a GPU)
    with t("post"):
        # on the device's tensors nothing waits for the network until the mask and depth come down
        reach = REFINED_REACH_PX / view.scale if refiner.spec.features == "radius" else 0.0
        nearest = NearestFluid.of(fluid, reach) if reach > 0 and (is_tensor(fluid) or fluid.any()) else None
        n = resize_normal_map(n, fluid.shape)
        lengths = length(n, axis=0)
        mask_t = refined_mask(n.movedim(0, -1), fluid, threshold, reach, lengths, nearest)
        out = torch.where(mask_t, n / lengths.clamp_min(1e-6), 0.0).permute(1, 2, 0).contiguous()
        out = out if tensors else out.cpu().numpy()
        if is_tensor(fluid):  # the depth's own transform (asking if its support is the fluid's would wait)
            depth, mask = extend_depth(blurred, mask_t), mask_t
            if not tensors:
                depth, mask = host(depth), host(mask)
        else:
            mask = mask_t.cpu().numpy()
            if nearest is not None and np.array_equal(blurred > 0, fluid):
                depth = nearest.spread(blurred, mask)
            else:
                depth = extend_depth(blurred, mask)
    return out, mask, depth


def extend_depth(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``depth`` (0 = empty) on ``mask``, each masked pixel without a depth of its own taking its
    nearest depth pixel's (refined silhouettes reach past the splat); 0 off the mask. Numpy arrays
    or torch tensors (``NearestFluid``)."""
    have = depth > 0
    if is_tensor(depth):  # where the tensors lie, the same numbers (no emptiness check: no wait)
        return NearestFluid.of(have, 0.0).spread(depth, mask)
    if not have.any() or not mask.any():
        return np.zeros_like(depth)
    from scipy.ndimage import distance_transform_edt

    # on the box of both grown by a pixel: it holds every depth pixel, so each masked pixel finds
    # the same nearest one as on the whole image (tested), in a fraction of the time
    window = bounding_window(have | (mask > 0), 1)
    rows, cols = distance_transform_edt(~have[window], return_distances=False, return_indices=True)
    out = np.zeros(depth.shape, np.float32)
    out[window] = np.where(mask[window], depth[window][rows, cols], 0.0)
    return out


SPHERE_FILTERS = "sphere_filters"
"""``frame_cache`` key: the sphere-splat filters every method of the frame will ask for, so the
first one splats once for all of them (``sphere_filters_of``)."""


def sphere_filters_of(methods) -> tuple[str, ...]:
    """The sphere-splat filters of these methods (a sphere-input refiner adds its bilateral when it
    comes)."""
    return tuple(dict.fromkeys(m for m in methods if m in ("gaussian", "bilateral", "nrf")))


def normal_source(method: str, positions: np.ndarray, radius: float, camera: Camera, filters: DatasetConfig,
                  ss: ScreenSpace, launch: Launcher, refiner: Refiner | None = None, threshold: float = 0.5,
                  timings: Timings | None = None, frame_cache: dict | None = None,
                  metaball: MetaballNet | None = None, on_device: bool | None = None) -> dict[str, np.ndarray]:
    """Normals, depth, mask and thickness of a method for one view.

    ``frame_cache`` (a dict the caller keeps per frame) shares the particles' anisotropic kernels
    between the methods and views of one frame that need them (ellipsoids, refined on ellipsoids,
    the mesh; the splat methods alone compute only what their camera sees: ``seen_kernels``), the
    sphere splat of the last view seen with the filters of ``SPHERE_FILTERS`` (set by
    the caller from ``sphere_filters_of``), whose thickness the metaballs and the mesh shade with.

    The refined method on the ellipsoid splat keeps its maps ``on_device`` (default: when the
    refiner is not on the CPU): its input channels, normals and thickness stay torch tensors there
    from the splat to the shader (``shade_frame``), which saves the round trips through the host."""
    t = timings or Timings()
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if method == "refined" and refiner is None:
        raise ValueError("the refined method needs a generator")
    cache = frame_cache if frame_cache is not None else {}

    def sphere_inputs(screen_filter: str | None = None) -> dict[str, np.ndarray]:
        """The sphere splat's channels of this view, shared by the frame's methods: splatted once
        with every filter of ``SPHERE_FILTERS`` (and ``screen_filter``), again only for a filter
        it lacks or another view."""
        seen, ch = cache.get("sphere_inputs", (None, {}))
        if seen is not camera or (screen_filter is not None and f"{screen_filter}.Z" not in ch):
            wanted = (screen_filter,) if screen_filter is not None else ()
            wanted = tuple(dict.fromkeys((*wanted, *cache.get(SPHERE_FILTERS, ()))))
            with t("inputs"):
                ch = screen_space_inputs(positions, radius, camera, filters, ss, t, filters=wanted)
            cache["sphere_inputs"] = (camera, ch)
        return ch

    def sphere_thickness() -> np.ndarray:
        """The sphere splat's thickness: the shader's absorption for the methods that make their
        own normals and depth (metaballs, the mesh)."""
        return sphere_inputs()["thickness"]

    def kernels():
        if "kernels" not in cache:
            with t("anisotropy"):
                cache["kernels"] = anisotropic_kernels(np.asarray(positions, np.float32), radius, filters, launch,
                                                       ss.device)
        return cache["kernels"]

    def camera_ellipsoids(on_device: bool | None = None, density: bool = False) -> Ellipsoids:
        """The particles' ellipsoids for this camera: from the frame's kernels when they were made,
        else from the anisotropy of the particles it sees (``seen_kernels``); with ``density`` each
        one's density at its centre too (the refiner's density feature)."""
        if "kernels" in cache:
            kernels_here, dens = cache["kernels"], None
            if density:
                if "densities" not in cache:
                    with t("anisotropy"):
                        cache["densities"] = kernel_densities(positions, radius, filters, launch, ss.device,
                                                              kernels_here)
                dens = cache["densities"]
        else:
            seen = cache.get("seen_kernels", (None,))
            if seen[0] is not camera or (density and seen[3] is None):
                with t("anisotropy"):
                    seen = (camera, *seen_kernels(np.asarray(positions, np.float32), radius, filters, camera, launch,
                                                  ss.device, densities=density))
                cache["seen_kernels"] = seen
            kernels_here, dens = seen[1], seen[3] if density else None
        return particle_ellipsoids(positions, radius, filters, launch, ss.device, kernels_here, on_device, dens)

    if method == "metaball":
        if metaball is None:
            raise ValueError("the metaball method needs a metaball generator")
        ellipsoids = camera_ellipsoids(on_device=False) if metaball.config.anisotropic else None
        with t("metaball"):
            g = metaball.gbuffers(positions, radius, camera, launch, ellipsoids)
        return {"normals": g["normals"], "depth": g["depth"], "mask": g["mask"], "thickness": sphere_thickness()}

    if method == "mesh":
        with t("mesh"):
            if filters.target == "raytrace":
                tc = raytraced_target_channels(kernels(), radius, filters, camera, ss, launch, ss.device)
            else:
                if "mesh" not in cache:
                    cache["mesh"] = reconstruct(positions, radius, filters, launch, ss.device, kernels())
                tc = target_channels(cache["mesh"], camera, launch)
        n = np.stack([tc[f"target.N.{a}"] for a in "XYZ"], -1)
        return {"normals": n, "depth": tc["target.Z"], "mask": tc["target.A"], "thickness": sphere_thickness()}
    if method in ANISO_METHODS or (method == "refined" and refiner.splat == "ellipsoid"):
        # made where the kernels lie (host memory on the CPU) for the splat to read in place: at 1M
        # particles on the CPU the splat takes 160 instead of 225 ms (no host copies transformed, uploaded)
        ellipsoids = camera_ellipsoids(on_device=True, density=method == "refined" and refiner.spec.density)
        aniso_filter = {"aniso": (), "aniso_nrf": ("nrf",), "refined": ("bilateral",)}[method]
        keep = method == "refined" and (refiner.device.type != "cpu" if on_device is None else on_device)
        with t("inputs"):
            # the unfiltered ellipsoid depth's normals only for the method that shows them (at 1080p
            # a normals pass, its download and split: about 25 ms)
            ch = screen_space_inputs(positions, radius, camera, filters, ss, t, filters=None, ellipsoids=ellipsoids,
                                     aniso_filters=aniso_filter, on_device=keep, raw_normals=method == "aniso")
        if method != "refined":
            return method_maps(method, ch)
    else:
        ch = sphere_inputs("bilateral" if method == "refined" else method)
    if method == "refined":
        with t("refiner"):
            n, mask, depth = refine(refiner, ch, threshold, camera.focal_px, radius, t, on_device)
        return {"normals": n, "depth": depth, "mask": as_float32(mask),
                "thickness": ch[input_channels(refiner.splat).thickness]}
    return method_maps(method, ch)


def shade_frame(source: dict[str, np.ndarray], background: np.ndarray, background_depth: np.ndarray,
                camera: Camera, p: RenderConfig, shader: Shader, timings: Timings | None = None) -> RenderedFrame:
    """Deferred shading of a normal source over the background (``p.background`` 'scene') or over
    nothing ('none': pass a background of the environment alone and a background depth of 0). The
    source's maps may be torch tensors on the shader's device (``normal_source`` on a GPU)."""
    t = timings or Timings()
    with t("shading"):
        thickness = shading_thickness(source["thickness"], source["mask"])
        out = shader.shade(source["normals"], source["depth"], thickness, source["mask"], background,
                           background_depth, camera, p)
        thickness = host(thickness)
    return RenderedFrame(out.beauty, out.fluid, out.depth, out.normals_view, out.normals_world, thickness,
                         np.asarray(host(source["mask"]), np.float32))


def shading_thickness(thickness, mask):
    """The thickness the shader absorbs over: the splat's, and at pixels of the method's ``mask``
    that no particle covered (a refined or mesh silhouette reaching past the splat) a covered
    neighbour's, ring by ring (``fill_rims``). The shader shows no fluid where the thickness is 0:
    without this the image cut every such silhouette back to the splat's while the Mask pass kept
    it (4-13% of the refined mask in the demo's frames). A tensor stays one, on its device, and
    comes back as it was when there is nothing to fill."""
    inside = mask > 0
    inside = torch.as_tensor(inside, device=thickness.device) if is_tensor(thickness) else host(inside)
    return fill_rims(thickness, thickness > 0, inside, steps=None)


RIM_FILL_STEPS = 16
"""Rings of pixels a visible fluid pixel that no particle sphere covered may lie from a covered one
and still take its motion (beyond: 0)."""


RING_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))
"""The 8-neighbours in the order ``fill_rims`` asks them (the first covered one gives its value)."""


def fill_rims(values, covered, wanted, steps: int | None = RIM_FILL_STEPS):
    """``values`` (H x W [x k]) with every ``wanted`` pixel that ``covered`` misses given a covered
    8-neighbour's value, ring by ring outwards from the covered pixels (the first covered neighbour
    in a fixed order), for at most ``steps`` rings (None: until no more can be reached); pixels
    further out keep their own. numpy arrays or torch tensors, the same values either way; a new
    array, or ``values`` itself when there is nothing to fill."""
    if is_tensor(values):
        return _fill_rims_on_device(values, covered, wanted, steps)
    x = xp(values)
    holes = x.argwhere(wanted & ~covered)
    if not len(holes) or not covered.any():
        return values
    values, covered = ((a.clone() if is_tensor(a) else a.copy()) for a in (values, covered))
    h, w = covered.shape
    ring = 0
    while steps is None or ring < steps:  # grow the covered pixels into the holes, one ring per step
        ring += 1
        filled = x.zeros_like(holes[:, 0], dtype=x.bool)
        for dr, dc in RING_NEIGHBOURS:
            r, c = x.clip(holes[:, 0] + dr, 0, h - 1), x.clip(holes[:, 1] + dc, 0, w - 1)
            take = ~filled & covered[r, c]
            values[holes[take, 0], holes[take, 1]] = values[r[take], c[take]]
            filled |= take
        covered[holes[filled, 0], holes[filled, 1]] = True
        holes = holes[~filled]
        if not len(holes) or not filled.any():
            break
    return values


RINGS_PER_WAIT = 4
"""Rings the rim fill on tensors queues between two looks at their counts. A ring after one that
filled nothing fills nothing either (the covered pixels are the same), so the extra rings of a batch
change no value; a GPU then waits once for up to this many rings."""


def _fill_rims_on_device(values, covered, wanted, steps: int | None):
    """``fill_rims`` on torch tensors, where they lie: two Warp passes a ring (``fill_ring``,
    ``close_ring``) on torch's stream. The pixel list would make a GPU wait for the device at every
    boolean index (some 500 waits a 1024 frame); this waits once to see whether there is anything
    to fill, then once every ``RINGS_PER_WAIT`` rings, for the counts of pixels they filled, to stop
    after a ring that filled none."""
    if values.dtype != torch.float32:
        raise TypeError(f"fill_rims on tensors fills float32 maps, not {values.dtype}")
    hole = wanted & ~covered
    if not all(torch.stack([hole.any(), covered.any()]).tolist()):
        return values
    wp.init()
    h, w = covered.shape
    out = values.clone().contiguous()
    covered_u8, hole_u8 = covered.to(torch.uint8).contiguous(), hole.to(torch.uint8).contiguous()
    filled = torch.zeros_like(hole_u8)
    counts = torch.zeros(RINGS_PER_WAIT, dtype=torch.int32, device=values.device)
    arrays = [wp.from_torch(a) for a in (covered_u8, hole_u8, out.reshape(h, w, -1), filled)]
    count_of = [wp.from_torch(counts[k:k + 1]) for k in range(RINGS_PER_WAIT)]
    device = wp.device_from_torch(values.device)
    ring = 0
    while steps is None or ring < steps:
        batch = RINGS_PER_WAIT if steps is None else min(RINGS_PER_WAIT, steps - ring)
        counts.zero_()
        with on_torch_stream(values.device):
            for k in range(batch):
                wp.launch(K.fill_ring, (h, w), [*arrays, count_of[k]], device=device)
                wp.launch(K.close_ring, (h, w), [arrays[0], arrays[1], arrays[3]], device=device)
        ring += batch
        if 0 in counts[:batch].tolist():
            break
    return out


def motion_pass(fluid_alpha: np.ndarray, fluid_motion: np.ndarray, covered: np.ndarray,
                background_motion: np.ndarray | None = None) -> np.ndarray:
    """H x W x 4 motion of what each pixel shows: the particles' motion where the fluid is visible
    (a visible pixel no sphere covered, e.g. at an ellipsoid's or the mesh's rim, takes a covered
    neighbour's, ring by ring: ``fill_rims``), the camera-induced motion of the background elsewhere
    (or 0).

    ``fluid_motion`` and ``covered`` may be torch tensors on a GPU (``ScreenSpace.motion`` with
    ``on_device``): the pass is then made there, the same values, and returned as a tensor."""
    if is_tensor(fluid_motion):
        fluid_alpha, covered = (torch.as_tensor(a, device=fluid_motion.device) for a in (fluid_alpha, covered))
        motion = (torch.zeros_like(fluid_motion) if background_motion is None
                  else torch.as_tensor(background_motion, device=fluid_motion.device).float().clone())
    else:
        motion = (np.zeros(fluid_motion.shape, np.float32) if background_motion is None
                  else np.array(background_motion, np.float32, order="C"))
    visible = fluid_alpha > 0
    if not visible.any():
        return motion
    if is_tensor(motion):
        return torch.where(visible[..., None], fill_rims(fluid_motion, covered, visible), motion)
    # on the host only the visible pixels' box grown by a pixel (every neighbour a rim fill reads):
    # the same values, without copying and scanning the empty rest of a wide frame (9-11 -> 5 ms
    # alone at 1920 x 1080 with the fluid on a fifth of it)
    win = bounding_window(visible, 1)
    filled = fill_rims(fluid_motion[win], covered[win], visible[win])
    # each pixel's four floats copied as one 16-byte value: the same bits, 0.5 ms instead of 15 at
    # 1024 x 1024 for a boolean-indexed copy of four floats a pixel
    np.copyto(_as_pixels(motion[win]), _as_pixels(np.ascontiguousarray(filled, np.float32)), where=visible[win])
    return motion


def _as_pixels(a: np.ndarray) -> np.ndarray:
    """An H x W x 4 float32 array viewed as H x W values of 16 bytes (no copy)."""
    return a.view(np.complex128)[..., 0]
