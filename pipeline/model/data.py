"""Refiner training data: dataset-stage EXR frames as tensors, random crops, flips.

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

from dataclasses import dataclass
from typing import Literal

import numpy as np

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


def random_crops(frames: list[Frame], crop: int, count: int, rng: np.random.Generator,
                 flip: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random crops (translation only, plus an optional horizontal flip) with their
    targets; crops are drawn where the frame shows fluid when it can."""
    xs, ys = [], []
    for _ in range(count):
        f = frames[int(rng.integers(len(frames)))]
        _, h, w = f.inputs.shape
        fluid = np.argwhere(np.abs(f.target).sum(0) > 0)
        if len(fluid) and rng.random() < 0.9:
            cy, cx = fluid[int(rng.integers(len(fluid)))]
            y0 = int(np.clip(cy - crop // 2, 0, h - crop))
            x0 = int(np.clip(cx - crop // 2, 0, w - crop))
        else:
            y0, x0 = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
        x = f.inputs[:, y0:y0 + crop, x0:x0 + crop]
        y = f.target[:, y0:y0 + crop, x0:x0 + crop]
        if flip and rng.random() < 0.5:
            x = flip_horizontal(x, (slice(0, 3),))
            y = flip_horizontal(y, (slice(0, 3),))
        xs.append(np.ascontiguousarray(x))
        ys.append(np.ascontiguousarray(y))
    return np.stack(xs), np.stack(ys)
