"""A scene's particle sequence into a cache folder: a PBF simulation, or an imported file sequence.

Either way the folder gets ``frame_0001.npz ...`` (positions, velocities) and ``sequence.json``;
both resume after the last whole frame when a run was killed.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from pipeline import resources
from pipeline.config import SceneConfig, SimulateConfig
from pipeline.frames import (
    SequenceInfo,
    completed_frames,
    frame_bounds,
    frame_name,
    load_frame,
    save_frame,
    union_bounds,
    write_sequence_info,
)
from pipeline.particles import read_particles
from pipeline.particles.sequence import find_sequence
from pipeline.sph import IMPORT_PADDING_RADII, NEIGHBOUR_PAIRS_LIMIT, WATER_DENSITY, neighbour_count
from pipeline.timing import Timings
from pipeline.vectors import bounds
from pipeline.writer import BackgroundWriter

log = logging.getLogger("deep_ssfr")


class SimulationFailed(RuntimeError):
    """The solver blew up; the message says which scene and what to change."""


def source_files(scene: SceneConfig) -> list[Path]:
    """The frame files of an imported scene, in frame-number order (``f_2`` before ``f_10``)."""
    return list(find_sequence(scene.source.pattern).paths)


def import_sequence(folder: Path, name: str, files: list[Path], radius: float, fps: float, up: str = "y",
                    source: str = "", *, support: float, stray: float | None = None) -> dict:
    """Copy particle files (in this order) into the folder as frames 1, 2, ...; returns the
    manifest's extra fields. ``up="z"`` turns Z-up data to the pipeline's Y-up. ``support``: the
    anisotropy's neighbour radius; a frame whose neighbour search would not finish is refused.
    With ``stray``, the extra fields hold the sequence's ``sequence_bounds`` (``bounds``: lo, hi)
    taken from the files as they are read, so nothing reads the copies again for them."""
    folder = Path(folder)
    timings, n_max, boxes, first = Timings(), 0, [], None
    # a frame's copy is written while the next is read (a million particles: 94 -> 75 ms a frame)
    with BackgroundWriter() as writer:
        for i, f in enumerate(tqdm(files, desc=f"import {name}", unit="frame"), start=1):
            target = folder / frame_name(i)
            if target.exists():  # copied by a run that was stopped: only its boxes are wanted
                if stray is not None or i == 1:
                    positions = load_frame(target)[0]
                    if stray is not None:
                        boxes.append(frame_bounds(positions, stray))
                    if i == 1:
                        first = bounds(positions)
                continue
            with timings("read"):
                frame = read_particles(f, up=up)
            check_crowding(f, frame.positions, radius, support)
            if stray is not None:
                boxes.append(frame_bounds(frame.positions, stray))
            first = bounds(frame.positions) if i == 1 else first  # the domain, from the first frame
            writer.submit(save_frame, target, frame.positions, frame.velocities)
            n_max = max(n_max, len(frame.positions))
    pad = IMPORT_PADDING_RADII * radius
    write_sequence_info(folder, SequenceInfo(name, len(files), radius, WATER_DENSITY, fps,
                                             tuple(float(v - pad) for v in first[0]),
                                             tuple(float(v + pad) for v in first[1]), source))
    log.info("import %s: %d frames from %s", name, len(files), source)
    extra = {"files": [frame_name(i) for i in range(1, len(files) + 1)], "timings": timings.as_dict(),
             "particles_max": n_max}
    if stray is not None:
        extra["bounds"] = [v.tolist() for v in union_bounds(boxes)]
    return extra


def check_crowding(path: Path, positions: np.ndarray, radius: float, support: float) -> None:
    """Refuse a frame whose particles crowd so densely that its neighbour search would not finish."""
    neighbours = neighbour_count(positions, support)
    if len(positions) * neighbours > NEIGHBOUR_PAIRS_LIMIT:
        raise ValueError(f"{path}: each particle has about {neighbours:,.0f} neighbours within the anisotropy's "
                         f"radius {support:.4g} (a fluid at rest: about 520), {len(positions) * neighbours:.1e} "
                         f"pairs for its {len(positions):,} particles, over the {NEIGHBOUR_PAIRS_LIMIT:.0e} a frame "
                         f"can search: at radius {radius:.4g} they overlap far more than a fluid's; check --radius "
                         f"against the files' units")


FRAME_BYTES_PER_PARTICLE = 24
"""A cached frame's bytes per particle: float32 positions and velocities (plus a small header)."""


def check_disk(folder: Path, name: str, frames: int, particles: int) -> None:
    """Refuse, before the first frame, a run whose frames would not fit on the cache's disk
    (``particles``: the scene's initial count, so emitters' particles are not foreseen)."""
    resources.check_disk(folder, frames * (particles * FRAME_BYTES_PER_PARTICLE + 1024),
                         f"simulate.frames: {frames:,} more frames of scene {name!r} ({particles:,} particles)",
                         "lower simulate.frames or free some space")


def simulate_sequence(folder: Path, scene: SceneConfig, params: SimulateConfig, device: str, seed: int) -> dict:
    """Run PBF for ``params.frames`` frames (resuming after the last whole one on disk); returns the
    manifest's extra fields. ``device`` is a Warp device."""
    from pipeline.sim.pbf import PBFSolver, PendingFrame, SimulationError
    from pipeline.sim.seeding import MAX_INITIAL_PARTICLES, initial_particle_estimate

    folder = Path(folder)
    write_sequence_info(folder, SequenceInfo(scene.name, params.frames, params.particle_radius, params.rest_density,
                                             params.fps, scene.domain_lo, scene.domain_hi, "pbf"))
    done = completed_frames(folder, params.frames)
    # before the solver, whose arrays an absurd frame count with emitters would size too
    estimate = initial_particle_estimate(scene, params.particle_radius)
    if estimate <= MAX_INITIAL_PARTICLES:  # beyond, the seeding names the particle radius
        check_disk(folder, scene.name, params.frames - done, max(1, round(estimate)))
    solver = PBFSolver(scene, params, device, seed=seed)
    if done:
        x, v = load_frame(folder / frame_name(done))
        solver.set_state(x, v, done * params.substeps)
        log.info("simulate %s: resuming after frame %d", scene.name, done)
    log.info("simulate %s: %d particles (capacity %d), %d frames x %d substeps x %d iterations on %s",
             scene.name, solver.n, solver.capacity, params.frames, params.substeps, params.iterations, device)
    timings = Timings()
    start, steps0, particle_steps = time.perf_counter(), solver.step_index, 0
    bar = tqdm(range(done + 1, params.frames + 1), desc=f"simulate {scene.name}", unit="frame",
               initial=done, total=params.frames)
    try:
        # Pipelined: frame k + 1 is queued before frame k is waited for, checked and handed to the
        # writer, so a GPU never waits for the host between frames (on the CPU the same order costs
        # nothing), and a frame's file is written while later ones are solved.
        with BackgroundWriter() as writer:

            def finish(pending: PendingFrame) -> int:
                with timings("state"):
                    stats, x, v = solver.finish_frame(pending)
                    writer.submit(save_frame, folder / frame_name(pending.frame), x, v)
                bar.set_postfix(particles=stats.particles, rho_max=f"{stats.max_density_ratio:.2f}")
                return stats.particles * params.substeps

            pending = None
            for frame in bar:
                with timings("solve"):
                    begun = solver.begin_frame(frame)
                if pending is not None:
                    particle_steps += finish(pending)
                pending = begun
            if pending is not None:
                particle_steps += finish(pending)
    except SimulationError as exc:
        raise SimulationFailed(f"simulate {scene.name}: {exc}; lower the time step (substeps) or "
                               "artificial_pressure_k") from None
    finally:
        solver.close()
    wall = max(time.perf_counter() - start, 1e-9)
    log.info("simulate %s: %d frames, %d particles, %.1f s wall, %.1f steps/s, %.3g particle-steps/s", scene.name,
             params.frames - done, solver.n, wall, (solver.step_index - steps0) / wall, particle_steps / wall)
    return {"files": [frame_name(i) for i in range(1, params.frames + 1)], "timings": timings.as_dict(),
            "particles": solver.n, "wall_seconds": round(wall, 3),
            "particle_steps_per_second": round(particle_steps / wall, 1)}
