"""Timers shared by the stages (for their summaries) and the benchmarks."""

from __future__ import annotations

import os
import sys
import time
from collections import defaultdict
from contextlib import contextmanager, nullcontext

SYNC_ENV = "DEEP_SSFR_SYNC_TIMINGS"
"""Set to 1 to make every timer wait for the GPU at its start and end (``Timings(sync=True)``)."""


def synchronize() -> None:
    """Wait for the work queued on every CUDA device, Warp's and torch's (nothing without one)."""
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()
        import warp as wp

        if wp.is_cuda_available():
            wp.synchronize()


_RANGES = [False]  # set by pipeline.profiling.profiled while it records, for every thread


def named_range(name: str):
    """A range of torch's profiler named ``name`` while one records (``pipeline.profiling``'s on
    any thread, or the calling thread's own), so a trace shows the steps and which device work each
    queued; nothing otherwise (torch is not imported for it; the check costs tens of nanoseconds)."""
    torch = sys.modules.get("torch")
    if torch is not None and (_RANGES[0] or torch.autograd._profiler_enabled()):
        return torch.profiler.record_function(name)
    return nullcontext()


class Timings:
    """Accumulates wall time per named step; ``with timings("splat"): ...``.

    On a GPU kernels and the network run behind the host, so a step's wall time holds whatever
    finished during it. ``sync`` (default: the ``DEEP_SSFR_SYNC_TIMINGS`` environment variable)
    waits for the GPU at each timer's start and end: every step then holds its own work, at the
    cost of the overlap (for breakdowns, not for frame rates). While torch's profiler records,
    each step is a named range of its trace (``named_range``)."""

    def __init__(self, sync: bool | None = None) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.count: dict[str, int] = defaultdict(int)
        self.sync = os.environ.get(SYNC_ENV, "") == "1" if sync is None else sync

    @contextmanager
    def __call__(self, name: str):
        if self.sync:
            synchronize()
        start = time.perf_counter()
        try:
            with named_range(name):
                yield
        finally:
            if self.sync:
                synchronize()
            self.total[name] += time.perf_counter() - start
            self.count[name] += 1

    def merge(self, other: Timings, skip: tuple[str, ...] = ()) -> None:
        """Add another timer's totals and counts (a worker's, a writer thread's) to these."""
        for name, seconds in other.total.items():
            if name not in skip:
                self.total[name] += seconds
                self.count[name] += other.count[name]

    def per_call_ms(self) -> dict[str, float]:
        """Milliseconds per call of every step, rounded for logs and manifests."""
        return {k: round(self.mean_ms(k), 2) for k in self.total}

    def mean_ms(self, name: str) -> float:
        """Mean milliseconds per call of a step."""
        return 1000.0 * self.total[name] / max(self.count[name], 1)

    def as_dict(self) -> dict[str, dict[str, float]]:
        """Totals (s) and call counts, for manifests."""
        return {k: {"seconds": round(v, 4), "calls": self.count[k]} for k, v in self.total.items()}
