"""What a run will need, estimated before any work, so that one that cannot finish is refused up front.

The render figures are fits to ``/usr/bin/time -f %M deep-ssfr render`` of the 1M-particle split frame
of ``benchmarks/bench_scale.py`` at 960x540 (1.04 GB) and 3840x2160 (3.73 GB), refined method; the EXR
bytes are the ZIP-compressed frame of that render (4.7 bytes a pixel) rounded down, so the estimates
refuse only what clearly cannot fit.
"""

from __future__ import annotations

import ctypes
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


MALLOC_MMAP_THRESHOLD = 32 << 20
"""Allocations up to this size come from malloc's heap rather than a mapping of their own: a 1080p
map (8 MB a float32 channel, 25 MB a vec3) does, a 4K one (33 MB and up) keeps its own, which held
a 4K frame's peak at 3.6-3.8 GB (64 MB here: 4.0 GB)."""
MALLOC_TRIM_THRESHOLD = 1 << 30
"""Freed heap memory kept for the next allocations before malloc returns it to the system."""


def keep_freed_memory() -> None:
    """Let glibc's malloc reuse the memory of freed image-sized arrays instead of mapping fresh pages
    for each: a frame allocates and frees dozens of full-frame maps, and every fresh page faults on
    first touch. bench_scale's 38k frame at 1080p: 498 -> 440 ms (mean of four runs each). By default
    glibc maps each block over 128 kB on its own (raising that bar to the largest one freed, at most
    32 MB) and gives freed heap back past twice the bar. Does nothing where the C library is not
    glibc."""
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # malloc.h
    mallopt(M_MMAP_THRESHOLD, MALLOC_MMAP_THRESHOLD)
    mallopt(M_TRIM_THRESHOLD, MALLOC_TRIM_THRESHOLD)


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
