"""The simulate stage against its solver alone: how much of the solver's speed the stage keeps.

Steps a scene's PBF solver with nothing else (the benchmark's view, after three warm-up frames),
then runs the simulate stage on the same scene from an empty cache (frame checks, state copies,
frame files, manifest) for half the frames and for all of them, and prints each in steps/s with its
ratio to the solver's, and the second half's steps over the extra wall time: the stage's fixed
costs (its solver's set-up and first frame, the last frame's write) cancel there, as the solver's
warm-up is left out of its own figure. On a GPU the per-frame work is what costs (issue 13 asks for
at least 80%). ``--trace DIR`` records a third stage run of ``--trace-frames`` frames with torch's
profiler (``pipeline.profiling``, its figures per solver step; the stage's set-up included: its
idle gaps show where the device waited) and prints and saves its summary with the trace.

    .venv/bin/python benchmarks/bench_sim_stage.py [--config configs/default.yaml] [--scene dam_break]
                                                   [--frames 100] [--particle-radius 0.00888]
                                                   [--trace DIR] [--trace-frames 20]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import warp as wp
from stage_runs import logged_summary, scratch_config

from pipeline.config_files import load
from pipeline.device import choose_device, warp_device
from pipeline.profiling import Trace, profiled
from pipeline.sim.pbf import PBFSolver

ROOT = Path(__file__).resolve().parents[1]


def solver_alone(config: str, scene: str, frames: int, radius: float | None) -> tuple[float, int]:
    """Steps per second of the bare solver (after three warm-up frames) and its particle count."""
    loaded = load(config, only_scene=scene)
    params = dataclasses.replace(loaded.config.simulate, frames=frames)
    if radius:
        params = dataclasses.replace(params, particle_radius=radius)
    solver = PBFSolver(loaded.scenes[scene], params, warp_device(choose_device(loaded.config.device)), seed=0)
    for f in range(1, 4):
        solver.advance_frame(f)
    start, steps0 = time.perf_counter(), solver.step_index
    for _ in range(frames * params.substeps):
        solver.step()
    wp.synchronize()
    rate = (solver.step_index - steps0) / (time.perf_counter() - start)
    n = solver.n
    solver.close()
    return rate, n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    parser.add_argument("--scene", default="dam_break")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--particle-radius", type=float,
                        help="simulate.particle_radius (m); 0.00888 gives the dam break 50k particles (issue 13)")
    parser.add_argument("--trace", type=Path, help="record a stage run with torch's profiler; its trace and summary "
                                                   "go into this folder as sim_stage.*")
    parser.add_argument("--trace-frames", type=int, default=20, help="frames of the recorded run")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    alone, n = solver_alone(args.config, args.scene, args.frames, args.particle_radius)
    with tempfile.TemporaryDirectory() as tmp:
        runs = [_stage(Path(tmp) / str(frames), args, frames) for frames in (args.frames // 2, args.frames)]
        traced = _stage(Path(tmp) / "traced", args, args.trace_frames, record=True)[2] if args.trace else None
    (half_steps, half_wall, _), (steps, wall, _) = runs
    print(f"{args.scene}: {n} particles on {choose_device()}")
    print(f"  solver alone      {alone:8.1f} steps/s")
    for label, rate in ((f"stage, {args.frames // 2} frames", half_steps / half_wall),
                        (f"stage, {args.frames} frames", steps / wall)):
        print(f"  {label:17s} {rate:8.1f} steps/s  ({100 * rate / alone:.0f}% of the solver alone)")
    if steps > half_steps and wall > half_wall:
        rate = (steps - half_steps) / (wall - half_wall)
        print(f"  second half       {rate:8.1f} steps/s  ({100 * rate / alone:.0f}% of the solver alone: frames "
              f"{args.frames // 2 + 1}-{args.frames}, the stage's fixed costs cancel)")
    if traced is not None:
        print(traced.report(args.trace, f"{args.trace_frames} frames, the stage's set-up and the profiler's own "
                                        "cost included"))


def _stage(data_dir: Path, args: argparse.Namespace, frames: int, record: bool = False) -> tuple[int, float, Trace]:
    """The simulate stage for ``frames`` frames into an empty cache: its steps and wall seconds, and
    with ``record`` the profiler's trace of it (empty without)."""
    keys = {"frames": frames, **({"particle_radius": args.particle_radius} if args.particle_radius else {})}
    config = scratch_config(args.config, data_dir, simulate=keys)
    steps = frames * load(config, only_scene=args.scene).config.simulate.substeps
    with profiled("sim_stage", steps, "step", enabled=record) as trace:
        rate = float(logged_summary("simulate", config, args.scene, r"s wall, ([\d.]+) steps/s").group(1))
    return steps, steps / rate, trace  # the logged rate has more digits than the wall

if __name__ == "__main__":
    main()
