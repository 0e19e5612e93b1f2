"""PBF throughput of the project's solver on a 49k-particle dam break, side by side with its peers.

The problem (``peers/dam_break.py``): a 0.5 x 0.7 x 0.8 m block in a 1.6 x 1.2 x 0.8 m box, h = 4r,
dt = 1/120 s, 4 iterations. The project's solver prints steps/s, particle-steps/s and the spread of
blocks of 8 steps (this shared host is noisy, and a step grows dearer as the column collapses).
A ratio is printed only against a peer measured in the same run, on the same machine:

- ``--peers``: right after the project's own measurement, each in its own process with as many
  threads: a Taichi 1.7.4 PBF of the identical problem (``peers/taichi_pbf.py``: the same
  algorithm and constants, Taichi's CPU backend), SPlisHSPlasH 2.19's PBF (4 iterations) and its
  DFSPH on the same block (``peers/splishsplash.py``, through the ``pysplishsplash`` wheel).
  ``--repeat R`` alternates the whole round R times and reports medians. ``--peers --device cuda``
  runs the project's solver and Taichi's CUDA backend on the same GPU (the issue-13 comparison;
  SPlisHSPlasH has no GPU backend and is left out): the solver's default gather passes and its
  scatter passes each round, so the first row's ratios are gather / scatter and gather / Taichi.
- ``--pair-passes scatter|gather``: the project's measurement with those pair passes
  (``simulate.pair_passes``; auto: gather on CUDA, scatter on the CPU).
- ``--scaling``: the project, Taichi and SPlisHSPlasH's PBF at 10k, 50k, 200k and 1M particles,
  the same steps at every size, each in a fresh process: particle-steps/s and resident memory per
  particle, and a log-log plot (``--plot docs/images/sim_scaling.png``); about 8 minutes here.
- ``--check``: the Taichi peer against the project's solver from the same initial block: centre of
  mass, kinetic energy, density and the extent of the fluid after 90 steps agree within 3x the
  largest difference between the project's run and its runs with four other seeds or one thread; a
  Taichi run with a parameter changed (two iterations) must not.
- ``--profile``: milliseconds per step of each kernel of the project's solver (its pair passes
  launched phase by phase, so each can be timed).
- ``--gang``: the CPU's gang launch of the pair passes (``Launcher.gang``) against launching them
  phase by phase: two solvers in one process, alternating blocks of 8 steps so the host's drift
  hits both alike; both must end in the same state.

The peers install with the ``bench`` extra (``pip install -e '.[bench]'``); with them the project's
solver runs on the CPU, as they do.

    .venv/bin/python benchmarks/bench_sim.py [--particles 50000] [--steps 40] [--threads 0] [--profile]
    .venv/bin/python benchmarks/bench_sim.py --peers [--repeat 3] [--device cuda]
    .venv/bin/python benchmarks/bench_sim.py --scaling [--plot docs/images/sim_scaling.png]
    .venv/bin/python benchmarks/bench_sim.py --check
    .venv/bin/python benchmarks/bench_sim.py --gang [--repeat 10]
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import warp as wp
from peers import dam_break
from peers.dam_break import Measurement

from pipeline.device import choose_device, warp_device
from pipeline.parallel import init_warp
from pipeline.sim import kernels as K
from pipeline.sim.pbf import PBFSolver

HERE = Path(__file__).resolve().parent
PEERS = HERE / "peers"
SCALING_SIZES = (10_000, 50_000, 200_000, 1_000_000)
CHECK_STEPS = 90
CHECK_SEEDS = 4
"""Perturbed runs of the project (another initial jitter) that, with a one-thread run, measure the flow's chaos."""


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

    def scatter_passes(self, blocks: list[tuple[int, int]], passes: list[tuple[Any, list, Any, list]]) -> None:
        # one pass at a time, each with its finish: a fused run shares the finish's hand-off with the next pass
        for kernel, inputs, finish, finish_inputs in passes:
            start = time.perf_counter()
            self.launch.scatter_passes(blocks, [(kernel, inputs, finish, finish_inputs)])
            wp.synchronize()
            self.ms[f"{kernel.key} + {finish.key}"] += 1000 * (time.perf_counter() - start)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.launch, name)


# -- the project's solver ---------------------------------------------------------------------
def project_solver(particles: int, threads: int, device: str, seed: int = 0, pair_passes: str = "auto",
                   gang: bool = True) -> PBFSolver:
    """The project's PBF solver on the benchmark's dam break (``simulate.pair_passes``: auto, scatter
    or gather; ``gang``: one launch per thread for a step's pair passes)."""
    params = dataclasses.replace(dam_break.params(particles, threads), pair_passes=pair_passes)
    return PBFSolver(dam_break.scene(), params, device, seed=seed, gang=gang)


def measure_project(particles: int, steps: int, threads: int, device: str, warmup: int = dam_break.WARMUP_STEPS,
                    profile: bool = False, pair_passes: str = "auto") -> tuple[Measurement, dict[str, float]]:
    """Step the project's solver; its measurement and, with ``profile``, ms/step per kernel."""
    init_warp((K,), device)
    before = dam_break.resident_bytes()
    # profiled pass by pass, to time each (the gang runs them in one launch per thread)
    solver = project_solver(particles, threads, device, pair_passes=pair_passes, gang=not profile)
    for _ in range(warmup):  # compile, first sorts, the column starts to fall
        solver.step()
    wp.synchronize()
    if profile:
        solver.launch = KernelTimer(solver.launch)
    seconds, rates = dam_break.time_steps(solver.step, wp.synchronize, steps)
    memory = dam_break.resident_bytes() - before
    kernels = {}
    if profile:
        kernels = {key: ms / steps for key, ms in solver.launch.ms.items()}
        solver.launch = solver.launch.launch
    name = "project PBF (Warp)" if pair_passes == "auto" else f"project PBF ({pair_passes})"
    result = Measurement(name, solver.n, steps, seconds, rates, memory, solver.launch.threads,
                         {"device": device, "radius": solver.radius, "h": solver.h,
                          "pair passes": "gather" if solver.gather else "scatter"})
    solver.close()
    assert math.isfinite(result.steps_per_s)
    return result, kernels


# -- peers, each in its own process -----------------------------------------------------------
PEER_RUNS = {
    "taichi": ("taichi", PEERS / "taichi_pbf.py", []),
    "splishsplash-pbf": ("pysplishsplash", PEERS / "splishsplash.py", ["--method", "pbf"]),
    "splishsplash-dfsph": ("pysplishsplash", PEERS / "splishsplash.py", ["--method", "dfsph"]),
}


def missing_module(module: str) -> bool:
    return importlib.util.find_spec(module) is None


def run_script(script: Path, args: list[str], what: str) -> Measurement:
    """Run a benchmark script in a fresh process and read the JSON line it prints last."""
    command = [sys.executable, str(script), *args]
    done = subprocess.run(command, capture_output=True, text=True, cwd=HERE.parent)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0 or not lines:
        tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-15:])
        raise RuntimeError(f"bench_sim: {what} failed (exit {done.returncode}): {' '.join(command)}\n{tail}")
    return Measurement.from_json(lines[-1])


def run_peer(peer: str, particles: int, steps: int, threads: int, warmup: int = dam_break.WARMUP_STEPS,
             extra: list[str] | None = None) -> Measurement:
    module, script, args = PEER_RUNS[peer]
    if missing_module(module):
        raise RuntimeError(f"bench_sim: the {peer} peer needs {module}: .venv/bin/pip install -e '.[bench]'")
    return run_script(script, [*args, "--particles", str(particles), "--steps", str(steps),
                               "--threads", str(threads), "--warmup", str(warmup), *(extra or [])], peer)


def run_project_process(particles: int, steps: int, threads: int, warmup: int) -> Measurement:
    """The project's measurement in a fresh process (for memory comparable with the peers')."""
    return run_script(Path(__file__), ["--json", "--particles", str(particles), "--steps", str(steps),
                                       "--threads", str(threads), "--warmup", str(warmup)], "project")


# -- printing ---------------------------------------------------------------------------------
def load() -> str:
    with open("/proc/loadavg") as f:
        return f.read().split()[0]


def header(threads: int, particles: int | None = None, steps: int | None = None) -> str:
    """The problem, the machine and how busy it is, in one line."""
    size = ""
    if particles is not None:
        size = f", r = {dam_break.radius_for(particles) * 1000:.2f} mm"
    timing = f"; {steps} steps after {dam_break.WARMUP_STEPS} of warm-up" if steps is not None else ""
    return (f"dam break {' x '.join(map(str, dam_break.BLOCK_HI))} m in {' x '.join(map(str, dam_break.DOMAIN_HI))} m"
            f"{size}, h = 4r, dt = 1/120 s, {dam_break.ITERATIONS} iterations{timing}; CPU, {threads} threads; "
            f"load average {load()} (this host is shared)")


def print_project(m: Measurement, kernels: dict[str, float]) -> None:
    print(f"device {m.extra['device']}, threads {m.threads}, {m.particles} particles "
          f"(r = {m.extra['radius'] * 1000:.2f} mm, h = {m.extra['h'] * 1000:.1f} mm), {dam_break.ITERATIONS} "
          f"iterations, {m.steps} steps")
    print(f"steps/s            {m.steps_per_s:8.2f}   (blocks of {dam_break.BLOCK_STEPS}: median "
          f"{np.median(m.block_rates):.2f}, {min(m.block_rates):.2f}-{max(m.block_rates):.2f})")
    print(f"particle-steps/s   {m.particle_steps_per_s:8.3g}")
    print(f"ms/step            {1000 * m.seconds / m.steps:8.1f}")
    if kernels:
        print("per kernel, ms/step (each launch synchronised):")
        for key, ms in sorted(kernels.items(), key=lambda kv: -kv[1]):
            print(f"  {key:28s} {ms:7.2f}")
        rest = 1000 * m.seconds / m.steps - sum(kernels.values())
        print(f"  {'rest: radix sort, zeroing, host copies':38s} {rest:7.2f}")


def describe(m: Measurement) -> str:
    """What a peer ran with, in a few words."""
    e = m.extra
    if "taichi" in e:
        return "Taichi " + ".".join(map(str, e["taichi"])) + f", {e.get('arch', 'cpu').upper()} backend"
    if "pysplishsplash" in e:
        its = ", ".join(f"{k.split(' - ')[-1]} {v:g}" for k, v in e["mean_iterations"].items())
        return f"pysplishsplash {e['pysplishsplash']}, mean {its}"
    return f"Warp {wp.config.version}, {e.get('device', 'cpu')}, {e.get('pair passes', 'scatter')} pair passes"


def print_side_by_side(rounds: list[list[Measurement]]) -> None:
    """Medians over rounds; a ratio is the median of each round's own ratio (project / peer)."""
    names = [m.name for m in rounds[0]]
    print(f"\n{'':26s} {'particles':>9s} {'steps/s':>8s} {'rounds':>11s} {'particle-steps/s':>16s} {'MB':>5s} "
          f"{'B/particle':>10s}   {'project / peer: steps/s':>23s} {'particle-steps/s':>16s}")
    for k, name in enumerate(names):
        runs = [r[k] for r in rounds]
        sps = statistics.median(m.steps_per_s for m in runs)
        psps = statistics.median(m.particle_steps_per_s for m in runs)
        spread = f"{min(m.steps_per_s for m in runs):.1f}-{max(m.steps_per_s for m in runs):.1f}"
        mem = runs[0].memory_bytes
        ratio = ratio_p = ""
        if k > 0:
            ratio = f"{statistics.median(r[0].steps_per_s / r[k].steps_per_s for r in rounds):.2f}x"
            ratio_p = f"{statistics.median(r[0].particle_steps_per_s / r[k].particle_steps_per_s for r in rounds):.2f}x"
        print(f"{name:26s} {runs[0].particles:9,d} {sps:8.2f} {spread if len(runs) > 1 else '':>11s} "
              f"{psps:16.3g} {mem / 2**20:5.0f} {mem / runs[0].particles:10.0f}   {ratio:>23s} {ratio_p:>16s}")
    print()
    for m in rounds[0]:
        print(f"  {m.name}: {describe(m)}")


# -- modes ------------------------------------------------------------------------------------
def peers_mode(args: argparse.Namespace, threads: int) -> None:
    print(header(threads, args.particles, args.steps))
    rounds = []
    # on a GPU the peer is Taichi on the same GPU (SPlisHSPlasH runs on the CPU only)
    device = warp_device(choose_device(args.device or "cpu"))
    peers = [p for p in PEER_RUNS if device == "cpu" or p == "taichi"]
    extra = [] if device == "cpu" else ["--arch", "cuda"]
    for r in range(args.repeat):
        project, _ = measure_project(args.particles, args.steps, threads, device)
        # on a GPU the default gather passes, and the scatter ones beside them (the first column's ratio)
        scatter = [] if device == "cpu" else [measure_project(args.particles, args.steps, threads, device,
                                                              pair_passes="scatter")[0]]
        results = [project, *scatter] + [run_peer(peer, args.particles, args.steps, threads, extra=extra)
                                         for peer in peers]
        rounds.append(results)
        print(f"round {r + 1}/{args.repeat}: " + ", ".join(f"{m.name} {m.steps_per_s:.2f}" for m in results)
              + f" steps/s; load average {load()}", flush=True)
    print_side_by_side(rounds)


def scaling_mode(args: argparse.Namespace, threads: int) -> None:
    print(header(threads) + "; each run in a fresh process")
    table: list[Measurement] = []
    print(f"{'':26s} {'particles':>9s} {'steps':>7s} {'steps/s':>8s} {'particle-steps/s':>16s} {'MB':>6s} "
          f"{'B/particle':>10s}")
    for n in args.sizes:
        # the same steps at every size, so every size times the same stretch of the flow
        warmup, steps = args.warmup, args.steps
        runs = [run_project_process(n, steps, threads, warmup),
                run_peer("taichi", n, steps, threads, warmup),
                run_peer("splishsplash-pbf", n, steps, threads, warmup)]
        for m in runs:
            table.append(m)
            print(f"{m.name:26s} {m.particles:9,d} {f'{warmup}+{steps}':>7s} {m.steps_per_s:8.3g} "
                  f"{m.particle_steps_per_s:16.3g} {m.memory_bytes / 2**20:6.0f} "
                  f"{m.memory_bytes / m.particles:10.0f}", flush=True)
    by_name: dict[str, list[Measurement]] = defaultdict(list)
    for m in table:
        by_name[m.name].append(m)
    print("\nmarginal memory between the two largest sizes (fixed costs such as compiled code cancel):")
    for name, ms in by_name.items():
        if len(ms) >= 2:
            a, b = ms[-2], ms[-1]
            print(f"  {name:26s} {(b.memory_bytes - a.memory_bytes) / (b.particles - a.particles):7.0f} B/particle")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps([json.loads(m.to_json()) for m in table], indent=1))
    if args.plot:
        plot_scaling(by_name, Path(args.plot), threads)


def plot_scaling(by_name: dict[str, list[Measurement]], path: Path, threads: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, mem) = plt.subplots(1, 2, figsize=(10, 4))
    for name, ms in by_name.items():
        n = [m.particles for m in ms]
        ax.loglog(n, [m.particle_steps_per_s for m in ms], "o-", label=name)
        mem.loglog(n, [m.memory_bytes / m.particles for m in ms], "o-", label=name)
    ax.set_xlabel("particles")
    ax.set_ylabel("particle-steps/s")
    ax.set_title(f"PBF dam break, 4 iterations, {threads} CPU threads")
    mem.set_xlabel("particles")
    mem.set_ylabel("resident memory per particle (B)")
    mem.set_title("memory the simulator added, per particle")
    for a in (ax, mem):
        a.grid(True, which="both", alpha=0.3)
        a.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def flow_summary(x: np.ndarray, v: np.ndarray, rho: np.ndarray, rest_density: float) -> dict[str, float]:
    """Aggregates of a fluid state that two chaotic runs of the same physics share."""
    hist, _ = np.histogram(x[:, 0], bins=32, range=(0.0, dam_break.DOMAIN_HI[0]))
    return {
        "centre of mass x (m)": float(x[:, 0].mean()), "centre of mass y (m)": float(x[:, 1].mean()),
        "centre of mass z (m)": float(x[:, 2].mean()),
        "kinetic energy (J/kg)": float(0.5 * (v * v).sum(1).mean()),
        "mean density / rest": float(rho.mean() / rest_density),
        "99th pct density / rest": float(np.percentile(rho, 99) / rest_density),
        "median x (m)": float(np.median(x[:, 0])),
        "top: 95th pct y (m)": float(np.percentile(x[:, 1], 95)),
        "spread: std of x (m)": float(x[:, 0].std()),
        "_histogram": hist / len(x),
    }


def id_ordered_state(solver: PBFSolver) -> dict[str, np.ndarray]:
    """Positions, velocities and densities of the project's solver in particle-id order."""
    x, v = solver.state()
    rho = np.empty(solver.n, np.float32)
    rho[solver.particle_id.numpy()[:solver.n]] = solver.particle_rho.numpy()[:solver.n]
    return {"x": x, "v": v, "rho": rho}


def check_mode(args: argparse.Namespace, threads: int) -> None:
    """The Taichi peer against the project's solver: the same physics, within the flow's own chaos.

    Both start from the same particles. After one step every particle must agree to float32
    rounding. Their sums run in different orders, so they part at the level of float rounding and a
    dam break amplifies that: after ``CHECK_STEPS`` steps the tolerance of each aggregate is 3x the
    largest difference between the project's run (seed 0, ``threads``) and runs of the project
    perturbed as little: ``CHECK_SEEDS`` other seeds (the initial jitter of 1% of r) and one thread
    (another summation order). Two perturbations were too few a sample of the chaos: on 2026-12-01
    the Taichi run (the same code as on 2026-11-25, rounding differently on that day's host) missed
    the fluid's top by 1.4x a tolerance drawn from two. A Taichi run with a parameter changed
    (``--check-control``) must fail.
    """
    steps = CHECK_STEPS
    p = dam_break.params(args.particles, threads)
    init_warp((K,), "cpu")
    summaries = {}
    runs = [("project", 0, threads)] + [(f"project seed {k}", k, threads) for k in range(1, CHECK_SEEDS + 1)]
    for name, seed, n_threads in [*runs, ("project 1 thread", 0, 1)]:
        solver = project_solver(args.particles, n_threads, "cpu", seed)
        solver.step()
        if name == "project":
            first_step = id_ordered_state(solver)
        for _ in range(steps - 1):
            solver.step()
        x, v = solver.state()
        summaries[name] = flow_summary(x, v, solver.particle_rho.numpy()[:solver.n], p.rest_density)
        solver.close()
    variants = {"Taichi": [], f"Taichi {args.check_control}": ["--set", args.check_control]}
    first_diff = {}
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state.npz"
        for name, extra in variants.items():
            run_peer("taichi", args.particles, 1, threads, warmup=0, extra=["--state", str(state), *extra])
            s = np.load(state)
            first_diff[name] = [float(np.abs(s[k] - first_step[k]).max()) for k in ("x", "v", "rho")]
            run_peer("taichi", args.particles, steps, threads, warmup=0, extra=["--state", str(state), *extra])
            s = np.load(state)
            summaries[name] = flow_summary(s["x"], s["v"], s["rho"], p.rest_density)
    print(f"{len(first_step['x'])} particles from the same initial block, {threads} threads")
    # after one step the same algorithm differs from the project only by float32 rounding
    first_tol = [1e-3 * p.particle_radius, 1e-3 * p.particle_radius * 120, 1e-5 * p.rest_density]
    print(f"after 1 step, largest difference of any particle from the project's: position (m), velocity (m/s), "
          f"density (kg/m^3); tolerance {', '.join(f'{t:.2g}' for t in first_tol)} (float32 rounding is ~1e-7 m)")
    for name, diff in first_diff.items():
        print(f"  {name:24s}" + "".join(f"{d:12.3g}" for d in diff))
    for summary in summaries.values():
        summary["x histogram L1 to project"] = float(np.abs(summary["_histogram"]
                                                           - summaries["project"]["_histogram"]).sum())
    names = list(summaries)
    references = [n for n in names if n.startswith("project ")]
    base, peers = summaries["project"], [n for n in names if not n.startswith("project")]
    print(f"after {steps} steps ({steps / 120:.2f} s of flow; a dam break is chaotic, so per-particle states part):")
    print(f"{'':27s}" + "".join(f"{n:>21s}" for n in names) + f"{'tolerance':>11s}")
    floors = {"(m)": 0.25 * p.particle_radius, "(J/kg)": 0.01, "rest": 0.002, "project": 0.01}
    verdict = {n: all(d <= t for d, t in zip(first_diff[n], first_tol, strict=True)) for n in peers}
    for key in [k for k in base if not k.startswith("_")]:
        floor = next(f for unit, f in floors.items() if key.endswith(unit))
        tol = max(3.0 * max(abs(summaries[n][key] - base[key]) for n in references), floor)
        print(f"{key:27s}" + "".join(f"{summaries[n][key]:21.5f}" for n in names) + f"{tol:11.5f}")
        for n in peers:
            verdict[n] &= abs(summaries[n][key] - base[key]) <= tol
    print(f"tolerance: 3x the largest difference of the {len(references)} perturbed project runs from the project's "
          "run, at "
          f"least r/4 = {floors['(m)'] * 1000:.2f} mm, 0.01 J/kg, 0.002 of rest density, 0.01 of the histogram")
    for n, ok in verdict.items():
        print(f"{n}: {'agrees with' if ok else 'DIFFERS from'} the project's solver")
    if not verdict["Taichi"] or verdict[peers[1]]:
        sys.exit(1)


def gang_mode(args: argparse.Namespace, threads: int) -> None:
    """The gang launch against phase-by-phase launches of the same solver, interleaved in one process."""
    init_warp((K,), "cpu")
    solvers = {"gang (one launch per thread)": project_solver(args.particles, threads, "cpu"),
               "phase by phase (a hand-off per phase)": project_solver(args.particles, threads, "cpu", gang=False)}
    for solver in solvers.values():
        for _ in range(args.warmup):
            solver.step()
    seconds = {name: [] for name in solvers}
    block = 8
    for r in range(max(args.repeat, 4)):
        for name in list(solvers)[:: 1 if r % 2 == 0 else -1]:
            start = time.perf_counter()
            for _ in range(block):
                solvers[name].step()
            seconds[name].append((time.perf_counter() - start) / block)
    states = [solver.state() for solver in solvers.values()]
    same = all(np.array_equal(a, b) for a, b in zip(states[0], states[1], strict=True))
    n = next(iter(solvers.values())).n
    print(f"{n:,} particles, CPU, {threads} threads; blocks of {block} steps alternating, {max(args.repeat, 4)} each")
    gang, phases = (np.array(v) for v in seconds.values())
    for name, v in seconds.items():
        print(f"  {name:40s} {1000 * statistics.median(v):6.2f} ms/step (median of blocks)")
    print(f"  gang / phase by phase, median of paired blocks: {float(np.median(gang / phases)):.3f}")
    print(f"  the same state after {solvers[next(iter(solvers))].step_index} steps: {same}")
    for solver in solvers.values():
        solver.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--warmup", type=int, default=dam_break.WARMUP_STEPS, help="untimed steps first")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0: one per core)")
    parser.add_argument("--profile", action="store_true", help="time each kernel (adds a sync per launch)")
    parser.add_argument("--pair-passes", choices=("auto", "scatter", "gather"), default="auto",
                        help="simulate.pair_passes (auto: gather on CUDA, scatter on the CPU)")
    parser.add_argument("--peers", action="store_true", help="also run Taichi and SPlisHSPlasH, print ratios")
    parser.add_argument("--repeat", type=int, default=1, help="--peers: alternate the round this many times")
    parser.add_argument("--scaling", action="store_true", help="10k-1M particles, the project and its peers")
    parser.add_argument("--sizes", type=lambda s: [int(float(x)) for x in s.split(",")], default=list(SCALING_SIZES))
    parser.add_argument("--plot", help="--scaling: write the log-log plot here (PNG)")
    parser.add_argument("--json-out", help="--scaling: write the measurements here (JSON)")
    parser.add_argument("--check", action="store_true", help="the Taichi peer against the project's solver")
    parser.add_argument("--check-control", default="iterations=2",
                        help="--check: a Taichi run with this parameter changed, which the check must tell apart")
    parser.add_argument("--json", action="store_true", help="print the project's measurement as one JSON line")
    parser.add_argument("--gang", action="store_true", help="the gang launch against phase-by-phase launches")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"),
                        help="where the project's solver runs (default: auto; cpu with --peers, whose --device cuda "
                             "runs Taichi on the same GPU)")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING  # no greeting or module-load lines
    threads = args.threads or os.cpu_count() or 1
    if args.peers:
        peers_mode(args, threads)
    elif args.scaling:
        scaling_mode(args, threads)
    elif args.check:
        check_mode(args, threads)
    elif args.gang:
        gang_mode(args, threads)
    else:
        device = warp_device(choose_device(args.device or "auto")) if not args.json else "cpu"
        result, kernels = measure_project(args.particles, args.steps, threads, device, args.warmup, args.profile,
                                          args.pair_passes)
        if args.json:
            print(result.to_json())
        else:
            print_project(result, kernels)


if __name__ == "__main__":
    main()
