"""The simulate stage against its solver alone: how much of the solver's speed the stage keeps.

Steps a scene's PBF solver with nothing else (the benchmark's view), then runs the simulate stage
on the same scene from an empty cache (frame checks, state copies, frame files, manifest), and
prints both in steps/s and their ratio. On a GPU the per-frame work is what costs (issue 13 asks for
at least 80%).

    .venv/bin/python benchmarks/bench_sim_stage.py [--config configs/default.yaml] [--scene dam_break]
                                                   [--frames 100] [--particle-radius 0.00888]
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import logging
import re
import tempfile
import time
from pathlib import Path

import warp as wp
import yaml

from pipeline.config import load
from pipeline.device import choose_device, warp_device
from pipeline.sim.pbf import PBFSolver
from stages import cli

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
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    alone, n = solver_alone(args.config, args.scene, args.frames, args.particle_radius)
    with tempfile.TemporaryDirectory() as tmp:
        body = yaml.safe_load(Path(args.config).read_text())
        body.update(data_dir=tmp, scene_dir=str(Path(args.config).resolve().parent / body.get("scene_dir", "scenes")))
        body.setdefault("simulate", {})["frames"] = args.frames
        if args.particle_radius:
            body["simulate"]["particle_radius"] = args.particle_radius
        config = Path(tmp) / "config.yaml"
        config.write_text(yaml.safe_dump(body))
        stream = io.StringIO()
        handler = logging.StreamHandler(stream)
        logging.getLogger("deep_ssfr").addHandler(handler)
        assert cli.main(["simulate", "--config", str(config), "--scene", args.scene]) == 0
        logging.getLogger("deep_ssfr").removeHandler(handler)
    stage = float(re.search(r"([\d.]+) steps/s", stream.getvalue()).group(1))
    print(f"{args.scene}: {n} particles on {choose_device()}")
    print(f"  solver alone      {alone:8.1f} steps/s")
    print(f"  simulate stage    {stage:8.1f} steps/s  ({100 * stage / alone:.0f}% of the solver alone)")


if __name__ == "__main__":
    main()
