"""Refiner training data: dataset-stage EXR frames as tensors, random crops, flips and quarter turns,
and the two sources of training batches: every frame decoded into memory (``MemoryBatches``) or
crops read lazily from the EXRs by DataLoader workers (``CropDataset``, ``DiskBatches``), both cut
by one crop rule (``draw_crop``) and both split over data-parallel processes by global-batch slices.

A view first goes to the working scale (``pipeline.model.scale``: particles at most
``working_radius_px`` on screen). Input channels (in order): the bilateral screen-space normal (3),
then, with auxiliary features, depth features of the sphere splat (``splat="sphere"``:
``bilateral.N.*``, ``Z``, ``bilateral.Z``) or of the ellipsoid splat (``"ellipsoid"``:
``aniso_bilateral.N.*``, ``aniso.Z``, ``aniso_bilateral.Z``). With ``features="radius"`` they are
scale-free: depth differences in particle radii and the projected radius in pixels
(``depth_features``), so the same fluid seen from further away or at another resolution gives the
network the same inputs. ``"frame"`` (the weights shipped before 2026-12) normalises the depths by
the frame's mean and spread, which depends on how large the scene is against its particles. Target:
the mesh normal (3), the zero vector where the mesh shows no fluid.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.utils.data

from pipeline.cache import CacheError
from pipeline.ellipsoids import DENSITY_CHANNEL
from pipeline.exr import header_focal_px, read_exr, read_exr_header
from pipeline.model.scale import ScaledView, median_radius_px, projected_radius_px, scale_view
from pipeline.vectors import as_float32, box_mean, is_tensor, xp

Splat = Literal["sphere", "ellipsoid"]
TARGET = ["target.N.X", "target.N.Y", "target.N.Z"]


@dataclass(frozen=True)
class InputChannels:
    """The dataset channels a refiner input is made of."""

    normal: list[str]
    raw: str
    blurred: str
    fluid: str
    thickness: str
    density: str = DENSITY_CHANNEL  # the ellipsoid splat's (``density_feature``)


def input_channels(splat: Splat = "sphere") -> InputChannels:
    """Channel names of the generator input for a splat kind."""
    pre = {"sphere": "", "ellipsoid": "aniso_"}[splat]
    raw = {"sphere": "", "ellipsoid": "aniso."}[splat]
    return InputChannels([f"{pre}bilateral.N.{a}" for a in "XYZ"], f"{raw}Z", f"{pre}bilateral.Z", f"{raw}A",
                         f"{raw}thickness")


Features = Literal["radius", "frame"]


@dataclass(frozen=True)
class InputSpec:
    """How a refiner's input is made from a view (recorded in its checkpoint's training config):
    ``auxiliary`` depth features, the ``splat`` kind, the depth ``features`` ('radius' or 'frame')
    and the ``working_radius_px`` the view is scaled to (``pipeline.model.scale``; 0: never), and
    whether the ``density`` feature of the ellipsoid splat comes last (``density_feature``)."""

    auxiliary: bool = True
    splat: Splat = "ellipsoid"
    features: Features = "radius"
    working_radius_px: float = 3.0
    density: bool = False

    @classmethod
    def of(cls, cfg) -> InputSpec:
        """The spec of a training config (a ``TrainConfig`` or its plain dict in a checkpoint).

        Checkpoints from before the scale-free inputs lack the keys: frame features, no rescale."""
        get = (lambda k, d: cfg.get(k, d)) if isinstance(cfg, dict) else (lambda k, d: getattr(cfg, k, d))
        features = get("input_features", "frame")
        return cls(bool(get("auxiliary_features", True)), get("input_splat", "sphere"), features,
                   float(get("working_radius_px", 0.0)) if features == "radius" else 0.0,
                   bool(get("density_feature", False)))

    @property
    def channels(self) -> int:
        """Generator input channels: the normal (3), with depth features 2 more ('frame') or 3
        ('radius': bumps, relief, projected radius), and 1 for the density."""
        depth = 0 if not self.auxiliary else 3 if self.features == "radius" else 2
        return 3 + depth + int(self.density)

    @property
    def view_channels(self) -> tuple[str, ...]:
        """The channels of a view this refiner reads: the filtered normal, raw and filtered depth,
        the splat's fluid and, with the density feature, the density map."""
        names = input_channels(self.splat)
        return (*names.normal, names.raw, names.blurred, names.fluid, *((names.density,) if self.density else ()))


BUMP_CLIP_RADII = 3.0
"""Raw minus filtered depth is clipped to this many particle radii (a step to a layer behind)."""
RELIEF_WINDOW_RADII = 6.0
"""Half width of the neighbourhood the relief feature compares the filtered depth with (projected radii)."""
RELIEF_SCALE_RADII = 4.0
"""Relief of this many particle radii maps to tanh(1)."""


def depth_features(raw, blurred, fluid, focal_px: float, radius: float):
    """The scale-free depth features of a view (3 x H x W, 0 outside the fluid).

    1. bumps: raw minus filtered depth in particle radii (clipped to +-3), the particles' own shape;
    2. relief: tanh of the filtered depth minus its fluid average over a window of +-6 projected
       radii, in units of 4 radii: which parts stand in front of their neighbourhood, what lies behind
       a discontinuity; depth as such (metres from the camera) never enters;
    3. log2 of the projected particle radius in pixels, halved: how large the particles are here.
    Depths are metres and ``focal_px`` the focal length in pixels of this (possibly scaled) image.
    numpy arrays or torch tensors (``pipeline.vectors``)."""
    x = xp(raw)
    m = as_float32(fluid)
    bumps = x.clip((raw - blurred) / radius, -BUMP_CLIP_RADII, BUMP_CLIP_RADII)
    r_px = projected_radius_px(raw, focal_px, radius)
    size = 2 * max(1, round(RELIEF_WINDOW_RADII * (median_radius_px(raw, focal_px, radius) or 1.0))) + 1
    local = box_mean(blurred * m, size) / x.clip(box_mean(m, size), 1e-6, None)
    relief = x.tanh((blurred - local) / (RELIEF_SCALE_RADII * radius))
    size_px = 0.5 * x.log2(x.clip(r_px, 1e-3, None))
    return as_float32(x.where(fluid, x.stack([bumps, relief, size_px]), 0.0))


DENSITY_SCALE = 0.5
"""The density feature is tanh(this times the density in iso-levels): 0.46 at the iso-level, 0.76
at the rest density (2 iso-levels), 0.96 at a flattened surface particle's 4."""


def density_feature(density, fluid):
    """The ellipsoid splat's largest density at a drawn particle's kernel centre (``aniso.density``,
    in iso-levels), tanh-compressed (1 x H x W, 0 outside the fluid). The mesh leaves a sparse
    spray cloud or a thin sheet open where their centres' density is low, which the splat's depths
    cannot tell; this can (docs/evaluation.md)."""
    x = xp(density)
    return as_float32(x.where(fluid, x.tanh(DENSITY_SCALE * density), 0.0)[None])


def frame_features(raw, blurred, fluid):
    """The depth features of the weights shipped before 2026-12 (2 x H x W): raw and filtered depth
    as (d - mu) / sigma over the frame's fluid pixels."""
    x = xp(raw)
    if fluid.any():
        values = raw[fluid]
        mu = float(values.mean())
        sigma = float(values.std(correction=0) if is_tensor(values) else values.std()) + 1e-6
    else:
        mu, sigma = 0.0, 1.0
    return as_float32(x.stack([x.where(fluid, (d - mu) / sigma, 0.0) for d in (raw, blurred)]))


@dataclass
class Prepared:
    """A view ready for the generator: ``inputs`` (C x h x w) at the working ``scale`` against the
    full image, its ``fluid`` mask there and, for training views, the ``target`` (3 x h x w)."""

    inputs: np.ndarray  # (or torch tensors, all of them, when the channels were)
    fluid: np.ndarray
    scale: float
    target: np.ndarray | None = None


def prepare(channels: dict[str, np.ndarray], spec: InputSpec, focal_px: float | None = None,
            radius: float | None = None, with_target: bool = False, max_pixels: int = 0,
            upscale_below_px: float = math.inf) -> Prepared:
    """The generator input of a view's channels (and with ``with_target`` its ``target.N.*``), scaled
    to the working scale (upscaled within ``max_pixels``, 0: no bound, and only particles under
    ``upscale_below_px``). 'radius' features need the image's focal length (px) and the particle
    radius (the dataset writes both into every view's header: ``view_geometry``). The channels may
    be torch tensors on the refiner's device: the input is then made there (``pipeline.vectors``)."""
    names = input_channels(spec.splat)
    raw, blurred = channels[names.raw], channels[names.blurred]
    x = xp(raw)
    normal = x.stack([channels[c] for c in names.normal])
    target = as_float32(x.stack([channels[c] for c in TARGET])) if with_target else None
    if spec.features == "radius" and (not focal_px or not radius):
        raise ValueError("scale-free refiner inputs need the focal length in pixels and the particle radius")
    if spec.density and names.density not in channels:
        raise ValueError(f"this refiner reads the ellipsoid splat's density ({names.density}): draw the particles "
                         "with particle_ellipsoids(..., density=True)")
    extra = density_feature(channels[names.density], raw > 0) if spec.density else None
    if spec.features == "radius":
        view = scale_view(normal, raw, blurred, float(focal_px), float(radius), spec.working_radius_px, target,
                          max_pixels, upscale_below_px, extra)
    else:
        view = ScaledView(as_float32(normal), raw, blurred, raw > 0, 0.0, 1.0, target, extra)
    if not spec.auxiliary:
        inputs = view.normals
    elif spec.features == "radius":
        inputs = x.concatenate([view.normals, depth_features(view.raw, view.blurred, view.fluid, view.focal_px,
                                                             float(radius))])
    else:
        inputs = x.concatenate([view.normals, frame_features(view.raw, view.blurred, view.fluid)])
    if spec.density:
        inputs = x.concatenate([inputs, view.extra])
    inputs = inputs.to(torch.float32).contiguous() if is_tensor(inputs) else np.ascontiguousarray(inputs, np.float32)
    return Prepared(inputs, view.fluid, view.scale, view.target)


def view_geometry(header: dict) -> tuple[float | None, float | None]:
    """(focal length in pixels, particle radius) from a dataset view's EXR header (None for what it
    lacks): the camera's standard attributes give the pixels, ``particleRadius`` the radius."""
    radius = header.get("particleRadius")
    return header_focal_px(header), None if radius is None else float(radius)


@dataclass
class Frame:
    """One training example held in memory (at the working scale)."""

    inputs: np.ndarray   # C x H x W
    target: np.ndarray   # 3 x H x W
    name: str
    fluid: np.ndarray    # H x W bool: pixels the input splat shows as fluid


def window_start(centre: int, side: int, extent: int) -> int:
    """First row (or column) of a window of ``side`` centred on ``centre``, kept inside ``extent``."""
    return int(np.clip(centre - side // 2, 0, max(0, extent - side)))


def held_window(frame: Frame, side: int, rng: np.random.Generator) -> Frame:
    """The frame as memory training holds it: inputs and target in float16 and, when it is larger
    than ``side`` a side, only the ``side`` x ``side`` window around a random pixel of the target's
    fluid (random views reach 1024 px: whole, 2,600 of them would take 30 GiB)."""
    _, h, w = frame.inputs.shape
    y0 = x0 = 0
    if h > side or w > side:
        fluid = np.flatnonzero(np.abs(frame.target).sum(0) > 0)
        cy, cx = divmod(int(fluid[int(rng.integers(len(fluid)))]), w) if len(fluid) else (h // 2, w // 2)
        y0, x0 = window_start(cy, side, h), window_start(cx, side, w)
    cut = (slice(None), slice(y0, y0 + side), slice(x0, x0 + side))
    return Frame(frame.inputs[cut].astype(np.float16), frame.target[cut].astype(np.float16), frame.name,
                 frame.fluid[cut[1:]])


def load_frame(path, spec: InputSpec) -> Frame:
    """Read the channels a training example needs from a dataset EXR, at the working scale."""
    ch = read_exr(path, [*spec.view_channels, *TARGET])
    focal_px, radius = view_geometry(read_exr_header(path)) if spec.features == "radius" else (None, None)
    if spec.features == "radius" and (focal_px is None or radius is None):
        raise CacheError(f"{path}: no camera or particleRadius in its header (a dataset from before the scale-free "
                         f"inputs); rebuild it with `make dataset FORCE=1`")
    view = prepare(ch, spec, focal_px, radius, with_target=True)
    return Frame(view.inputs, view.target, str(path), view.fluid)


def flip_horizontal(arr: np.ndarray, normal_slices: tuple[slice, ...]) -> np.ndarray:
    """Mirror left-right; N.X of every normal block changes sign (view-space correct)."""
    out = arr[..., ::-1].copy()
    for s in normal_slices:
        out[s.start] *= -1.0
    return out


def rotate_quarter(arr: np.ndarray, turns: int, normal_slices: tuple[slice, ...]) -> np.ndarray:
    """Turn C x H x W images ``turns`` quarter turns anticlockwise, as a camera rolled the other way
    would see them; every normal block's (X, Y) turns with the image: one turn maps (x, y) to (-y, x)."""
    out = np.rot90(arr, turns, axes=(-2, -1)).copy()
    for s in normal_slices:
        x, y = out[s.start].copy(), out[s.start + 1].copy()
        for _ in range(turns % 4):
            x, y = -y, x
        out[s.start], out[s.start + 1] = x, y
    return out


def pad_to(arr: np.ndarray, size: int) -> np.ndarray:
    """C x H x W padded with zeros (empty pixels) at the bottom and right to at least ``size`` a side."""
    _, h, w = arr.shape
    if h >= size and w >= size:
        return arr
    return np.pad(arr, ((0, 0), (0, max(0, size - h)), (0, max(0, size - w))))


def draw_crop(frame: Frame, crop: int, rng: np.random.Generator, flip: bool = True,
              rotate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """One ``crop`` x ``crop`` window of a frame's input and target: centred on a random pixel where the
    target shows fluid 90% of the time (anywhere when it shows none), mirrored left-right half the time
    with ``flip`` and turned by a random number of quarter turns with ``rotate``; frames smaller than
    the crop are padded with empty pixels. The one crop rule of memory and disk training; the draws
    come from ``rng`` in a fixed order, so equal generators give equal crops."""
    inputs, target = pad_to(frame.inputs, crop), pad_to(frame.target, crop)
    _, h, w = inputs.shape
    fluid = np.flatnonzero(np.abs(target).sum(0) > 0)
    if len(fluid) and rng.random() < 0.9:
        cy, cx = divmod(int(fluid[int(rng.integers(len(fluid)))]), w)
        y0, x0 = window_start(cy, crop, h), window_start(cx, crop, w)
    else:
        y0, x0 = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
    x = inputs[:, y0:y0 + crop, x0:x0 + crop]
    y = target[:, y0:y0 + crop, x0:x0 + crop]
    if flip and rng.random() < 0.5:
        x = flip_horizontal(x, (slice(0, 3),))
        y = flip_horizontal(y, (slice(0, 3),))
    if rotate:
        turns = int(rng.integers(4))
        if turns:
            x = rotate_quarter(x, turns, (slice(0, 3),))
            y = rotate_quarter(y, turns, (slice(0, 3),))
    return np.ascontiguousarray(x, np.float32), np.ascontiguousarray(y, np.float32)


def random_crops(frames: list[Frame], crop: int, count: int, rng: np.random.Generator,
                 flip: bool = True, rotate: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``count`` crops (:func:`draw_crop`) of frames picked at random, stacked with their targets."""
    pairs = [draw_crop(frames[int(rng.integers(len(frames)))], crop, rng, flip, rotate) for _ in range(count)]
    return np.stack([x for x, _ in pairs]), np.stack([y for _, y in pairs])


class CropDataset(torch.utils.data.Dataset[tuple[np.ndarray, np.ndarray]]):
    """Training crops read lazily from the dataset EXRs (``train.data: disk``).

    Sample ``(epoch, index)`` draws its frame and its crop from a generator seeded by (seed, epoch,
    index), so it is the same crop whichever DataLoader worker or training process reads it, and a
    resumed run reads what a straight one would. Each worker keeps its last ``cached_frames`` decoded
    frames (about 33 MiB each at 1024 x 1024), so memory does not grow with the dataset."""

    def __init__(self, paths: list[Path], crop: int, seed: int, spec: InputSpec, cached_frames: int = 4,
                 flip: bool = True, rotate: bool = False):
        self.paths, self.crop, self.seed, self.flip, self.rotate = [Path(p) for p in paths], crop, seed, flip, rotate
        self.spec, self.cached_frames = spec, cached_frames
        self._frames: OrderedDict[int, Frame] = OrderedDict()

    def frame(self, k: int) -> Frame:
        """Frame ``k``, decoded from its EXR unless it is among the recently used ones."""
        if k in self._frames:
            self._frames.move_to_end(k)
            return self._frames[k]
        frame = load_frame(self.paths[k], self.spec)
        if self.cached_frames:
            self._frames[k] = frame
            while len(self._frames) > self.cached_frames:
                self._frames.popitem(last=False)
        return frame

    def __getitem__(self, key: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The crop (C x crop x crop) and its target (3 x crop x crop) of sample ``(epoch, index)``."""
        epoch, index = key
        rng = np.random.default_rng([self.seed, epoch, index])
        return draw_crop(self.frame(int(rng.integers(len(self.paths)))), self.crop, rng, self.flip, self.rotate)


class EpochShard(torch.utils.data.Sampler[tuple[int, int]]):
    """This process's share of an epoch's samples, as ``(epoch, index)`` keys of :class:`CropDataset`.

    Step ``s`` of the global batch ``B`` holds indices ``s*B .. s*B+B-1``; process ``rank`` of
    ``world`` reads the ``rank``-th contiguous slice of ``B / world`` of them (DistributedSampler
    without shuffling, the draw itself being random), so any number of processes trains on the same
    crops, in the same global batches."""

    def __init__(self, steps: int, batch_size: int, rank: int = 0, world: int = 1):
        self.steps, self.batch_size, self.rank, self.world = steps, batch_size, rank, world
        self.share = batch_size // world
        self.epoch = 1

    def set_epoch(self, epoch: int) -> None:
        """Choose the epoch the next iteration yields keys of."""
        self.epoch = epoch

    def __iter__(self) -> Iterator[tuple[int, int]]:
        """This process's keys of the current epoch, step after step."""
        first = self.rank * self.share
        return ((self.epoch, s * self.batch_size + first + j) for s in range(self.steps) for j in range(self.share))

    def __len__(self) -> int:
        """Samples this process reads an epoch."""
        return self.steps * self.share


class MemoryBatches:
    """Every training frame decoded up front (``train.data: memory``); each epoch's crops come from one
    generator seeded by (seed, epoch), as they always have. Under several processes each one draws the
    whole global batch and keeps its slice."""

    def __init__(self, frames: list[Frame], crop: int, batch_size: int, seed: int, rank: int = 0, world: int = 1,
                 rotate: bool = False):
        self.frames, self.crop, self.batch_size, self.seed, self.rotate = frames, crop, batch_size, seed, rotate
        share = batch_size // world
        self.rows = slice(rank * share, (rank + 1) * share)

    @property
    def frame_size(self) -> tuple[int, int]:
        """(height, width) of the largest training frame (frames differ in size at the working scale)."""
        return max(f.inputs.shape[1] for f in self.frames), max(f.inputs.shape[2] for f in self.frames)

    def batches(self, epoch: int, steps: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """This process's (inputs, targets) batch of each step of ``epoch``."""
        rng = np.random.default_rng([self.seed, epoch])
        for _ in range(steps):
            x, y = random_crops(self.frames, self.crop, self.batch_size, rng, rotate=self.rotate)
            yield x[self.rows], y[self.rows]


class DiskBatches:
    """Crops read from the EXRs by DataLoader workers (``train.data: disk``), this process's shard of
    each step's global batch; the workers live as long as the object, with their frame caches."""

    def __init__(self, dataset: CropDataset, steps: int, batch_size: int, workers: int, rank: int = 0,
                 world: int = 1, pin_memory: bool = False):
        self.dataset, self.steps = dataset, steps
        self.sampler = EpochShard(steps, batch_size, rank, world)
        self.loader = torch.utils.data.DataLoader(
            dataset, batch_size=self.sampler.share, sampler=self.sampler, num_workers=workers,
            persistent_workers=workers > 0, pin_memory=pin_memory,
            generator=torch.Generator().manual_seed(dataset.seed))  # leaves torch's global generator alone

    @property
    def frame_size(self) -> tuple[int, int]:
        """(height, width) of the training frames (the first one's, decoded once)."""
        _, h, w = self.dataset.frame(0).inputs.shape
        return h, w

    def batches(self, epoch: int, steps: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """This process's (inputs, targets) batch of each step of ``epoch``."""
        if steps != self.steps:
            raise ValueError(f"DiskBatches was built for {self.steps} steps per epoch, asked for {steps}")
        self.sampler.set_epoch(epoch)
        yield from self.loader
