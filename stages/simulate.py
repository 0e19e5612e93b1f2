"""``make simulate``: run PBF for each configured scene (or import its particle files) into the cache.

Writes ``data/simulate/<scene>-<key>/frame_0001.npz ...`` (positions, velocities), ``sequence.json``
and ``manifest.json``. A killed run resumes from its last whole frame.
"""

from __future__ import annotations

import glob
import logging
import os
import time
from pathlib import Path

from tqdm import tqdm

from pipeline import cache
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.frames import SequenceInfo, completed_frames, frame_name, load_frame, save_frame, write_sequence_info
from pipeline.particles import read_particles
from pipeline.timing import Timings
from stages.common import Run, StageError, make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")


def source_files(scene: SceneConfig) -> list[str]:
    """The sorted frame files of an imported scene."""
    files = sorted(glob.glob(scene.source.pattern))
    if not files:
        raise StageError(f"scene {scene.name}: no files match {scene.source.pattern}")
    return files


def sim_entry(run: Run, scene: SceneConfig) -> cache.CacheEntry:
    """Cache entry of a scene's particle sequence (keyed on the scene, solver config and seed)."""
    physics = to_dict(scene)
    physics.pop("cameras")  # cameras matter downstream only
    if scene.source is not None:
        files = [(f, os.path.getsize(f), os.path.getmtime(f)) for f in source_files(scene)]
        config = {"scene": physics, "files": files}
    else:
        config = {"scene": physics, "simulate": to_dict(run.config.simulate), "seed": run.config.seed}
    return cache.entry(run.data_dir, "simulate", scene.name, config, {}, run.device)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """The complete entry of a scene, simulating (or importing) what is missing."""
    entry = sim_entry(run, scene)
    if entry.is_complete() and not force:
        log.info("simulate %s: cached (%s)", scene.name, entry.dir)
        return entry
    entry.begin(force=force)
    if scene.source is not None:
        _import(entry, scene)
    else:
        _simulate(run, entry, scene)
    return entry


def _import(entry: cache.CacheEntry, scene: SceneConfig) -> None:
    files = source_files(scene)
    src = scene.source
    timings = Timings()
    n_max = 0
    for i, f in enumerate(tqdm(files, desc=f"import {scene.name}", unit="frame"), start=1):
        target = entry.path(frame_name(i))
        if target.exists():
            continue
        with timings("read"):
            frame = read_particles(f)
        save_frame(target, frame.positions, frame.velocities)
        n_max = max(n_max, len(frame.positions))
    first = read_particles(files[0]).positions
    lo, hi = first.min(0), first.max(0)
    pad = 4 * src.particle_radius
    info = SequenceInfo(scene.name, len(files), src.particle_radius, 1000.0, src.fps,
                        tuple(float(v - pad) for v in lo), tuple(float(v + pad) for v in hi), src.pattern)
    write_sequence_info(entry.dir, info)
    entry.finish([frame_name(i) for i in range(1, len(files) + 1)], timings.as_dict(),
                 particles_max=n_max)
    log.info("import %s: %d frames from %s", scene.name, len(files), src.pattern)


def _simulate(run: Run, entry: cache.CacheEntry, scene: SceneConfig) -> None:
    from pipeline.sim.pbf import PBFSolver

    params = run.config.simulate
    info = SequenceInfo(scene.name, params.frames, params.particle_radius, params.rest_density, params.fps,
                        scene.domain_lo, scene.domain_hi, "pbf")
    write_sequence_info(entry.dir, info)
    solver = PBFSolver(scene, params, warp_device(run.device), seed=run.config.seed)
    done = completed_frames(entry.dir, params.frames)
    if done:
        x, v = load_frame(entry.path(frame_name(done)))
        solver.set_state(x, v, done * params.substeps)
        log.info("simulate %s: resuming after frame %d", scene.name, done)
    log.info("simulate %s: %d particles (capacity %d), %d frames x %d substeps x %d iterations on %s",
             scene.name, solver.n, solver.capacity, params.frames, params.substeps, params.iterations,
             run.device)
    timings = Timings()
    start, steps0, particle_steps = time.perf_counter(), solver.step_index, 0
    bar = tqdm(range(done + 1, params.frames + 1), desc=f"simulate {scene.name}", unit="frame",
               initial=done, total=params.frames)
    try:
        for frame in bar:
            with timings("solve"):
                stats = solver.advance_frame(frame)
            particle_steps += stats.particles * params.substeps
            with timings("write"):
                x, v = solver.state()
                save_frame(entry.path(frame_name(frame)), x, v)
            bar.set_postfix(particles=stats.particles, rho_max=f"{stats.max_density_ratio:.2f}")
    except Exception as exc:
        if exc.__class__.__name__ == "SimulationError":
            raise StageError(f"simulate {scene.name}: {exc}; lower the time step (substeps) or "
                             f"artificial_pressure_k") from None
        raise
    finally:
        solver.close()
    wall = time.perf_counter() - start
    steps = solver.step_index - steps0
    entry.finish([frame_name(i) for i in range(1, params.frames + 1)], timings.as_dict(),
                 particles=solver.n, wall_seconds=round(wall, 3),
                 particle_steps_per_second=round(particle_steps / max(wall, 1e-9), 1))
    log.info("simulate %s: %d frames, %d particles, %.1f s wall, %.1f steps/s, %.3g particle-steps/s -> %s",
             scene.name, params.frames - done, solver.n, wall, steps / max(wall, 1e-9),
             particle_steps / max(wall, 1e-9), entry.dir)


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make simulate``."""
    run = make_run(parse_args("simulate", argv))
    for scene in run.loaded.scenes.values():
        ensure(run, scene, force=run.force)


def export_main(argv: list[str] | None = None) -> None:
    """Entry point of ``make export``: PLY or legacy VTK copies of each cached sequence."""
    from pipeline.particles import ParticleFrame, write_particles

    args = parse_args("export", argv, lambda p: p.add_argument("--format", choices=["ply", "vtk"],
                                                               default="ply"))
    run = make_run(args)
    for scene in run.loaded.scenes.values():
        entry = ensure(run, scene)
        out = Path(entry.dir) / "export" / args.format
        out.mkdir(parents=True, exist_ok=True)
        n = len(entry.manifest()["files"])
        for i in tqdm(range(1, n + 1), desc=f"export {scene.name}", unit="frame"):
            x, v = load_frame(entry.path(frame_name(i)))
            with cache.atomic_path(out / frame_name(i, args.format)) as tmp:
                write_particles(tmp, ParticleFrame(x, v), args.format)
        log.info("export %s: %d %s files in %s", scene.name, n, args.format, out)


if __name__ == "__main__":
    import sys

    if len(sys.argv) > 1 and sys.argv[1] == "export":
        sys.exit(stage_main("export", export_main, sys.argv[2:]))
    sys.exit(stage_main("simulate", main))
