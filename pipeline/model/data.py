"""Refiner training data: dataset-stage EXR frames as tensors, random crops, flips, and the two
sources of training batches: every frame decoded into memory (``MemoryBatches``) or crops read
lazily from the EXRs by DataLoader workers (``CropDataset``, ``DiskBatches``), both cut by one
crop rule (``draw_crop``) and both split over data-parallel processes by global-batch slices.

Input channels (in order): the bilateral screen-space normal (3), then, with auxiliary features,
the raw splat depth and the bilateral (blurred) depth, of the sphere splat (``splat="sphere"``:
``bilateral.N.*``, ``Z``, ``bilateral.Z``) or of the ellipsoid splat (``"ellipsoid"``:
``aniso_bilateral.N.*``, ``aniso.Z``, ``aniso_bilateral.Z``). Depths are normalised per frame as
(d - mu) / sigma with mu, sigma the mean and standard deviation of the raw depth over fluid
pixels, and 0 on background: scale-free, so scenes of any size and distance look alike, while
the difference between raw and blurred depth (the bumps) survives. Target: the mesh normal (3),
the zero vector where the mesh shows no fluid.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.utils.data

from pipeline.exr import read_exr

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


def input_channels(splat: Splat = "sphere") -> InputChannels:
    """Channel names of the generator input for a splat kind."""
    pre = {"sphere": "", "ellipsoid": "aniso_"}[splat]
    raw = {"sphere": "", "ellipsoid": "aniso."}[splat]
    return InputChannels([f"{pre}bilateral.N.{a}" for a in "XYZ"], f"{raw}Z", f"{pre}bilateral.Z", f"{raw}A",
                         f"{raw}thickness")


def input_channel_count(auxiliary: bool) -> int:
    """5 with the depth features, 3 without."""
    return 5 if auxiliary else 3


def make_input(channels: dict[str, np.ndarray], auxiliary: bool = True, splat: Splat = "sphere") -> np.ndarray:
    """C x H x W float32 generator input from a frame's channels."""
    names = input_channels(splat)
    normal = np.stack([channels[c] for c in names.normal])
    if not auxiliary:
        return normal.astype(np.float32)
    raw, blurred = channels[names.raw], channels[names.blurred]
    fluid = raw > 0
    if fluid.any():
        mu = float(raw[fluid].mean())
        sigma = float(raw[fluid].std()) + 1e-6
    else:
        mu, sigma = 0.0, 1.0
    depths = [np.where(fluid, (d - mu) / sigma, 0.0) for d in (raw, blurred)]
    return np.concatenate([normal, np.stack(depths)]).astype(np.float32)


@dataclass
class Frame:
    """One training example held in memory."""

    inputs: np.ndarray   # C x H x W
    target: np.ndarray   # 3 x H x W
    name: str
    fluid: np.ndarray    # H x W bool: pixels the input splat shows as fluid


def load_frame(path, auxiliary: bool = True, splat: Splat = "sphere") -> Frame:
    """Read the channels a training example needs from a dataset EXR."""
    names = input_channels(splat)
    ch = read_exr(path, [*names.normal, names.raw, names.blurred, names.fluid, *TARGET])
    return Frame(make_input(ch, auxiliary, splat), np.stack([ch[c] for c in TARGET]).astype(np.float32), str(path),
                 ch[names.fluid] > 0)


def flip_horizontal(arr: np.ndarray, normal_slices: tuple[slice, ...]) -> np.ndarray:
    """Mirror left-right; N.X of every normal block changes sign (view-space correct)."""
    out = arr[..., ::-1].copy()
    for s in normal_slices:
        out[s.start] *= -1.0
    return out


def draw_crop(frame: Frame, crop: int, rng: np.random.Generator, flip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """One ``crop`` x ``crop`` window of a frame's input and target: centred on a random pixel where the
    target shows fluid 90% of the time (anywhere when it shows none), mirrored left-right half the time
    with ``flip``. The one crop rule of memory and disk training; the draws come from ``rng`` in a
    fixed order, so equal generators give equal crops."""
    _, h, w = frame.inputs.shape
    fluid = np.flatnonzero(np.abs(frame.target).sum(0) > 0)
    if len(fluid) and rng.random() < 0.9:
        cy, cx = divmod(int(fluid[int(rng.integers(len(fluid)))]), w)
        y0 = int(np.clip(cy - crop // 2, 0, h - crop))
        x0 = int(np.clip(cx - crop // 2, 0, w - crop))
    else:
        y0, x0 = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
    x = frame.inputs[:, y0:y0 + crop, x0:x0 + crop]
    y = frame.target[:, y0:y0 + crop, x0:x0 + crop]
    if flip and rng.random() < 0.5:
        x = flip_horizontal(x, (slice(0, 3),))
        y = flip_horizontal(y, (slice(0, 3),))
    return np.ascontiguousarray(x), np.ascontiguousarray(y)


def random_crops(frames: list[Frame], crop: int, count: int, rng: np.random.Generator,
                 flip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``count`` crops (:func:`draw_crop`) of frames picked at random, stacked with their targets."""
    pairs = [draw_crop(frames[int(rng.integers(len(frames)))], crop, rng, flip) for _ in range(count)]
    return np.stack([x for x, _ in pairs]), np.stack([y for _, y in pairs])


class CropDataset(torch.utils.data.Dataset[tuple[np.ndarray, np.ndarray]]):
    """Training crops read lazily from the dataset EXRs (``train.data: disk``).

    Sample ``(epoch, index)`` draws its frame and its crop from a generator seeded by (seed, epoch,
    index), so it is the same crop whichever DataLoader worker or training process reads it, and a
    resumed run reads what a straight one would. Each worker keeps its last ``cached_frames`` decoded
    frames (about 33 MiB each at 1024 x 1024), so memory no longer grows with the dataset."""

    def __init__(self, paths: list[Path], crop: int, seed: int, auxiliary: bool = True, splat: Splat = "sphere",
                 cached_frames: int = 4, flip: bool = True):
        self.paths, self.crop, self.seed, self.flip = [Path(p) for p in paths], crop, seed, flip
        self.auxiliary, self.splat, self.cached_frames = auxiliary, splat, cached_frames
        self._frames: OrderedDict[int, Frame] = OrderedDict()

    def frame(self, k: int) -> Frame:
        """Frame ``k``, decoded from its EXR unless it is among the recently used ones."""
        if k in self._frames:
            self._frames.move_to_end(k)
            return self._frames[k]
        frame = load_frame(self.paths[k], self.auxiliary, self.splat)
        if self.cached_frames:
            self._frames[k] = frame
            while len(self._frames) > self.cached_frames:
                self._frames.popitem(last=False)
        return frame

    def __getitem__(self, key: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The crop (C x crop x crop) and its target (3 x crop x crop) of sample ``(epoch, index)``."""
        epoch, index = key
        rng = np.random.default_rng([self.seed, epoch, index])
        return draw_crop(self.frame(int(rng.integers(len(self.paths)))), self.crop, rng, self.flip)


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

    def __init__(self, frames: list[Frame], crop: int, batch_size: int, seed: int, rank: int = 0, world: int = 1):
        self.frames, self.crop, self.batch_size, self.seed = frames, crop, batch_size, seed
        share = batch_size // world
        self.rows = slice(rank * share, (rank + 1) * share)

    @property
    def frame_size(self) -> tuple[int, int]:
        """(height, width) of the training frames."""
        _, h, w = self.frames[0].inputs.shape
        return h, w

    def batches(self, epoch: int, steps: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """This process's (inputs, targets) batch of each step of ``epoch``."""
        rng = np.random.default_rng([self.seed, epoch])
        for _ in range(steps):
            x, y = random_crops(self.frames, self.crop, self.batch_size, rng)
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
