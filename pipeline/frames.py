"""Cached particle frames (``frame_0001.npz``) and sequence metadata, shared by every stage."""

from __future__ import annotations

import zipfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.cache import CacheError, atomic_path, read_json, redo_hint, write_json_atomic
from pipeline.vectors import bounds

SEQUENCE_FILE = "sequence.json"


def frame_name(index: int, ext: str = "npz") -> str:
    """1-based, zero-padded frame file name (``frame_0001.npz``)."""
    return f"frame_{index:04d}.{ext}"


def select_frames(total: int, stride: int = 1, first: int = 0) -> list[int]:
    """Frame numbers of a sequence of ``total`` frames that a stage uses: every ``stride``-th from
    frame 1, then the first ``first`` of those (0: all). One rule for dataset, render and the CLI."""
    frames = list(range(1, total + 1, stride))
    return frames[:first] if first else frames


def spread(items: list, count: int) -> list:
    """``count`` items evenly spread over ``items``, first and last included (all of them when
    ``count`` is 0 or at least their number): samples that cover a whole sequence."""
    if not count or len(items) <= count:
        return list(items)
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, count).round()]


@dataclass(frozen=True)
class SequenceInfo:
    """What downstream stages need to know about a particle sequence."""

    scene: str
    frames: int
    particle_radius: float
    rest_density: float
    fps: float
    domain_lo: tuple[float, float, float]
    domain_hi: tuple[float, float, float]
    source: str


def save_frame(path: Path, positions: np.ndarray, velocities: np.ndarray | None) -> None:
    """Write positions (and velocities) as float32 through a temporary file."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        arrays = {"positions": np.asarray(positions, np.float32)}
        if velocities is not None:
            arrays["velocities"] = np.asarray(velocities, np.float32)
        np.savez(fh, **arrays)


def load_frame(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Positions and velocities of a cached frame; a damaged file raises CacheError naming it."""
    try:
        with np.load(path) as z:
            x = z["positions"]
            v = z["velocities"] if "velocities" in z.files else None
    except FileNotFoundError:
        raise CacheError(f"missing cache file {path}; {redo_hint(path)}") from None
    except (zipfile.BadZipFile, ValueError, KeyError, OSError, EOFError) as exc:
        raise CacheError(f"corrupt cache file {path} ({exc}); {redo_hint(path)}") from None
    if x.ndim != 2 or x.shape[1] != 3:
        raise CacheError(f"corrupt cache file {path}: positions have shape {x.shape}")
    return x, v


def sequence_bounds(folder: Path, count: int, stray: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The box holding the particles of cached frames 1..count (what a camera must keep in view):
    every one, or with ``stray`` > 0 the bulk of each frame, leaving out up to that share of its
    particles beyond each side on each axis (flying droplets, which may then leave the picture)."""
    boxes = [frame_bounds(load_frame(Path(folder) / frame_name(i))[0], stray) for i in range(1, count + 1)]
    return union_bounds(boxes)


def frame_bounds(x: np.ndarray, stray: float = 0.0) -> tuple[np.ndarray, np.ndarray] | None:
    """One frame's part of ``sequence_bounds``: the box of its particles, or of their bulk with
    ``stray`` > 0; None for a frame without particles."""
    if not len(x):
        return None
    if stray > 0:
        x = x[:: max(1, len(x) // 200_000)]  # the quantiles of a sample
        return tuple(np.quantile(x, [stray, 1.0 - stray], axis=0, method="inverted_cdf"))
    return bounds(x)


def union_bounds(boxes) -> tuple[np.ndarray, np.ndarray]:
    """The box around every box of ``frame_bounds`` (None: an empty frame); infinite when all are."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for box in boxes:
        if box is not None:
            lo, hi = np.minimum(lo, box[0]), np.maximum(hi, box[1])
    return lo, hi


def write_sequence_info(folder: Path, info: SequenceInfo) -> None:
    """Write ``sequence.json``."""
    write_json_atomic(Path(folder) / SEQUENCE_FILE, asdict(info))


def read_sequence_info(folder: Path) -> SequenceInfo:
    """Read ``sequence.json`` of a simulate cache entry."""
    data = read_json(Path(folder) / SEQUENCE_FILE)
    try:
        data["domain_lo"] = tuple(data["domain_lo"])
        data["domain_hi"] = tuple(data["domain_hi"])
        return SequenceInfo(**data)
    except (TypeError, KeyError) as exc:
        raise CacheError(f"corrupt cache file {Path(folder) / SEQUENCE_FILE}: {exc}") from None


def completed_frames(folder: Path, total: int) -> int:
    """Number of leading frames 1..k already written (a killed run resumes after them)."""
    k = 0
    while k < total and (Path(folder) / frame_name(k + 1)).exists():
        k += 1
    return k


__all__ = ["SequenceInfo", "frame_name", "select_frames", "spread", "sequence_bounds", "frame_bounds", "union_bounds",
           "save_frame", "load_frame", "write_sequence_info", "read_sequence_info", "completed_frames"]
