"""Timers shared by the stages (for their summaries) and the benchmarks."""

from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager


class Timings:
    """Accumulates wall time per named step; ``with timings("splat"): ...``."""

    def __init__(self) -> None:
        self.total: dict[str, float] = defaultdict(float)
        self.count: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, name: str):
        start = time.perf_counter()
        try:
            yield
        finally:
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
