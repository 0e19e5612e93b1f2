"""PBF throughput: a 50k-particle dam break, 4 solver iterations, on the current device.

Prints steps/s and particle-steps/s over ``--steps`` steps (median, slowest and fastest of blocks
of 8 steps too: this shared 2-core host is noisy, and a step grows dearer as the column collapses
and packs), the ratio to the reference figures measured on this machine class (Taichi 1.7.4 PBF of
the same size: 9.6 steps/s; a plain single-threaded Warp PBF: about 3; see shared/NOTES.md), and
with ``--profile`` the milliseconds per step of each kernel.

    .venv/bin/python benchmarks/bench_sim.py [--particles 50000] [--steps 40] [--threads 0] [--profile]
"""

from __future__ import annotations

import argparse
import math
import time
from collections import defaultdict
from typing import Any

import numpy as np
import warp as wp

from pipeline.config import Cameras, FluidShape, SceneConfig, SimulateConfig, from_dict
from pipeline.device import choose_device, warp_device
from pipeline.sim.pbf import PBFSolver

TAICHI_STEPS_PER_S = 9.6
PLAIN_WARP_STEPS_PER_S = 3.0
CAMERAS = {"static": {"eye": [0, 0, 3], "target": [0, 0, 0]}, "orbit": {"target": [0, 0, 0]}}
BLOCK = 8


class KernelTimer:
    """Wraps a solver's Launcher and adds up the wall time of each kernel (synchronising each launch)."""

    def __init__(self, launch: Any):
        self.launch, self.ms = launch, defaultdict(float)
        self.cpu = launch.cpu

    def _timed(self, kernel: Any, call: Any) -> None:
        start = time.perf_counter()
        call()
        wp.synchronize()
        self.ms[kernel.key] += 1000 * (time.perf_counter() - start)

    def __call__(self, kernel: Any, n: int, inputs: list[Any]) -> None:
        self._timed(kernel, lambda: self.launch(kernel, n, inputs))

    def scatter(self, kernel: Any, blocks: list[tuple[int, int]], inputs: list[Any]) -> None:
        self._timed(kernel, lambda: self.launch.scatter(kernel, blocks, inputs))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.launch, name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--threads", type=int, default=0)
    parser.add_argument("--profile", action="store_true", help="time each kernel (adds a sync per launch)")
    args = parser.parse_args()
    wp.config.quiet = True
    block = (0.5, 0.7, 0.8)
    radius = 0.5 * (np.prod(block) / args.particles) ** (1.0 / 3.0)
    scene = SceneConfig(name="bench_dam_break", cameras=from_dict(Cameras, CAMERAS),
                        domain_hi=(1.6, 1.2, 0.8), fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=block),))
    params = SimulateConfig(particle_radius=float(radius), iterations=4, substeps=4, threads=args.threads)
    device = choose_device("auto")
    solver = PBFSolver(scene, params, warp_device(device), seed=0)
    for _ in range(8):  # warm-up: compile, first sorts, the column starts to fall
        solver.step()
    wp.synchronize()
    if args.profile:
        solver.launch = KernelTimer(solver.launch)
    blocks = []
    for b in range(0, args.steps, BLOCK):
        count = min(BLOCK, args.steps - b)
        start = time.perf_counter()
        for _ in range(count):
            solver.step()
        wp.synchronize()
        blocks.append((count, time.perf_counter() - start))
    wall = sum(t for _, t in blocks)
    steps_per_s = args.steps / wall
    rates = [c / t for c, t in blocks]
    print(f"device {device}, threads {solver.launch.threads}, {solver.n} particles "
          f"(r = {radius * 1000:.2f} mm, h = {solver.h * 1000:.1f} mm), {params.iterations} iterations, "
          f"{args.steps} steps")
    print(f"steps/s            {steps_per_s:8.2f}   (blocks of {BLOCK}: median {np.median(rates):.2f}, "
          f"{min(rates):.2f}-{max(rates):.2f})")
    print(f"particle-steps/s   {steps_per_s * solver.n:8.3g}")
    print(f"ms/step            {1000 * wall / args.steps:8.1f}")
    print(f"vs Taichi 1.7.4 PBF ({TAICHI_STEPS_PER_S} steps/s):  {steps_per_s / TAICHI_STEPS_PER_S:.2f}x")
    print(f"vs plain Warp PBF   ({PLAIN_WARP_STEPS_PER_S} steps/s):  {steps_per_s / PLAIN_WARP_STEPS_PER_S:.2f}x")
    if args.profile:
        print("per kernel, ms/step (each launch synchronised):")
        for key, ms in sorted(solver.launch.ms.items(), key=lambda kv: -kv[1]):
            print(f"  {key:28s} {ms / args.steps:7.2f}")
        solver.launch = solver.launch.launch
    solver.close()
    assert math.isfinite(steps_per_s)


if __name__ == "__main__":
    main()
