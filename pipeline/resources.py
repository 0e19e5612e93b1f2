"""What a run will need, estimated before any work, so that one that cannot finish is refused up front.

The render figures are fits to ``/usr/bin/time -f %M deep-ssfr render`` of the 1M-particle split frame
of ``benchmarks/bench_scale.py`` at 960x540 (1.04 GB) and 3840x2160 (3.73 GB), refined method; the EXR
bytes are the ZIP-compressed frame of that render (4.7 bytes a pixel) rounded down, so the estimates
refuse only what clearly cannot fit.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

RENDER_BASE_BYTES = 0.7e9
"""A render process's memory before its frames: torch, Warp, the GL context, the refiner."""
RENDER_BYTES_PER_PIXEL = 350
"""Memory a rendered pixel holds: the screen-space maps, the refiner's activations, the passes."""
RENDER_BYTES_PER_PARTICLE = 200
"""Memory a particle holds while its frame renders: positions, kernels, the hash grid."""
EXR_BYTES_PER_PIXEL = 4
"""Disk a compressed frame EXR takes a pixel (its passes, ZIP-compressed)."""


def available_memory() -> int:
    """Bytes of memory this machine can give a new process now (MemAvailable; total memory where
    /proc/meminfo is missing)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_disk(folder: Path, need: float, what: str, advice: str) -> None:
    """Refuse ``what`` (its option and size, in words) when ``need`` bytes exceed the free space of the
    disk under ``folder`` (its nearest existing parent)."""
    folder = Path(folder).resolve()
    while not folder.exists():
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if need > free:
        raise ValueError(f"{what} need about {need / 1e9:.3g} GB, but {folder} has {free / 1e9:.3g} GB free; "
                         f"{advice}")


def render_memory(width: int, height: int, particles: int) -> float:
    """Estimated peak bytes of a render process at this image size and particle count."""
    return RENDER_BASE_BYTES + RENDER_BYTES_PER_PIXEL * width * height + RENDER_BYTES_PER_PARTICLE * particles


def check_render(out: Path, width: int, height: int, frames: int, particles: int, size_option: str,
                 copies: int = 2) -> None:
    """Refuse a render whose frames would not fit in memory or whose EXRs (``copies`` of each: the
    cache's and the published one) would not fit on ``out``'s disk; ``size_option`` names where the
    image size came from."""
    need = render_memory(width, height, particles)
    have = available_memory()
    if need > have:
        raise ValueError(f"{size_option}: a {width}x{height} frame of {particles:,} particles needs about "
                         f"{need / 1e9:.3g} GB of memory, but {have / 1e9:.3g} GB are available; render a smaller "
                         f"size")
    check_disk(out, copies * frames * EXR_BYTES_PER_PIXEL * width * height,
               f"{size_option}: {frames:,} frames of {width}x{height}", "render fewer frames or a smaller size, or "
               "free some space")
