"""The benchmark problem every simulator runs: a dam break of one fluid block in a closed box.

A 0.5 x 0.7 x 0.8 m block of water at the corner of a 1.6 x 1.2 x 0.8 m container, particles of
radius r on a lattice of spacing 2r (r chosen so the block holds about the requested count), SPH
support h = 4r, time step 1/120 s, 4 density iterations. The project's solver, the Taichi peer and
the SPlisHSPlasH peer all take their scene from here, so they cannot drift apart; each peer is a
script run in its own process (its threads, its memory) that prints one JSON line.
"""

from __future__ import annotations

import json
import resource
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from pipeline.config import Cameras, FluidShape, SceneConfig, SimulateConfig, from_dict

BLOCK_HI = (0.5, 0.7, 0.8)
"""Fluid block, from the container's corner at the origin (m)."""
DOMAIN_HI = (1.6, 1.2, 0.8)
"""Container, from the origin (m)."""
ITERATIONS = 4
"""Density-constraint iterations per step."""
WARMUP_STEPS = 8
"""Untimed steps first: compilation, first sorts, the column starts to fall."""
BLOCK_STEPS = 8
"""Steps per timed block: a shared host is noisy, so the spread of blocks is reported too."""
CAMERAS = {"static": {"eye": [0, 0, 3], "target": [0, 0, 0]}, "orbit": {"target": [0, 0, 0]}}


def radius_for(particles: int) -> float:
    """Particle radius r (m) that fills the block with about ``particles`` on a lattice of spacing 2r."""
    return 0.5 * (float(np.prod(BLOCK_HI)) / particles) ** (1.0 / 3.0)


def scene() -> SceneConfig:
    """The container and the block, as the project's solver reads them."""
    return SceneConfig(name="bench_dam_break", cameras=from_dict(Cameras, CAMERAS), domain_hi=DOMAIN_HI,
                       fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=BLOCK_HI),))


def params(particles: int, threads: int = 0) -> SimulateConfig:
    """Solver parameters: the project's defaults (dt = 1/120 s, h = 4r, the PBF constants) at this size."""
    return SimulateConfig(particle_radius=radius_for(particles), iterations=ITERATIONS, substeps=4, threads=threads)


def resident_bytes() -> int:
    """Resident memory of this process now (bytes, from /proc/self/statm)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


@dataclass
class Measurement:
    """What one simulator did on the problem: one JSON line on a peer's stdout."""

    name: str
    """Simulator and method, as printed."""
    particles: int
    """Particles simulated."""
    steps: int
    """Timed steps (after the warm-up)."""
    seconds: float
    """Wall time of the timed steps (s)."""
    block_rates: list[float]
    """Steps/s of each timed block of ``BLOCK_STEPS`` steps."""
    memory_bytes: int
    """Resident memory the simulator added: after the run minus before its set-up (bytes)."""
    threads: int
    """CPU threads it ran on."""
    extra: dict = field(default_factory=dict)
    """Method-specific facts (iterations, radius, ...)."""

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds

    @property
    def particle_steps_per_s(self) -> float:
        return self.steps_per_s * self.particles

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, line: str) -> Measurement:
        return cls(**json.loads(line))


def time_steps(step: Callable[[], None], sync: Callable[[], None], steps: int) -> tuple[float, list[float]]:
    """Run ``steps`` steps in blocks of ``BLOCK_STEPS``; the total wall time and each block's steps/s."""
    rates, total = [], 0.0
    for b in range(0, steps, BLOCK_STEPS):
        count = min(BLOCK_STEPS, steps - b)
        start = time.perf_counter()
        for _ in range(count):
            step()
        sync()
        seconds = time.perf_counter() - start
        total += seconds
        rates.append(count / seconds)
    return total, rates
