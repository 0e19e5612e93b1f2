"""``make simulate``: run PBF for each configured scene (or import its particle files) into the cache.

Writes ``data/simulate/<scene>-<key>/frame_0001.npz ...`` (positions, velocities), ``sequence.json``
and ``manifest.json`` (``pipeline.sim.runner``). A killed run resumes from its last whole frame.
On a Ray executor the scenes are simulated at once, one Ray task a scene (:func:`ensure_all`).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import traceback
from collections.abc import Sequence
from pathlib import Path

from pipeline import cache
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.executor import run_tasks
from pipeline.sim.runner import import_sequence, simulate_sequence, source_files
from pipeline.sph import anisotropy_support
from stages.common import Run, StageOptions, make_run

log = logging.getLogger("deep_ssfr")


def sim_entry(run: Run, scene: SceneConfig) -> cache.CacheEntry:
    """Cache entry of a scene's particle sequence (keyed on the scene, solver config and seed)."""
    physics = to_dict(scene)
    physics.pop("cameras")  # cameras matter downstream only
    if scene.source is not None:
        files = [(str(f), os.path.getsize(f), os.path.getmtime(f)) for f in source_files(scene)]
        config = {"scene": physics, "files": files}
    else:
        config = {"scene": physics, "simulate": to_dict(run.config.simulate), "seed": run.config.seed}
    return cache.entry(run.data_dir, "simulate", scene.name, config, {}, run.device)


def ensure(run: Run, scene: SceneConfig, force: bool = False) -> cache.CacheEntry:
    """The complete entry of a scene, simulating (or importing) what is missing."""
    entry = sim_entry(run, scene)
    if not entry.begin(force=force):
        log.info("simulate %s: cached (%s)", scene.name, entry.dir)
        return entry
    if scene.source is not None:
        src = scene.source
        support = anisotropy_support(src.particle_radius, run.config.dataset.aniso_kernel_radius)
        extra = import_sequence(entry.dir, scene.name, source_files(scene), src.particle_radius, src.fps, src.up,
                                src.pattern, support=support)
    else:
        extra = simulate_sequence(entry.dir, scene, run.config.simulate, warp_device(run.device), run.config.seed)
    entry.finish(extra.pop("files"), extra.pop("timings"), **extra)
    log.info("simulate %s: -> %s", scene.name, entry.dir)
    return entry


def ensure_all(run: Run, scenes: Sequence[SceneConfig], force: bool = False) -> None:
    """The complete entries of ``scenes``. Locally one scene after another; on a Ray executor the
    simulated scenes missing from the cache run at once, one Ray task a scene (imported ones are
    read here). A task asks for as many CPUs as it runs solver threads (the config's ``threads``,
    else the driver's cores, as a serial run here would use: the CPU solver's sums follow the
    thread count, so the frames are a serial run's to the bit), or for a GPU on a CUDA run, and gets
    no backup copy (a scene's time says nothing of another's). A task lost with its node runs
    again and resumes after its last whole frame. Each scene's entry is finished as its task returns,
    so a driver killed later keeps it. A scene that fails (a blow-up) does not keep the others
    unfinished: theirs are finished, then its error is raised (the first to fail, by time)."""
    if run.config.executor != "ray":
        for scene in scenes:
            ensure(run, scene, force)
        return
    for scene in scenes:
        if scene.source is not None:
            ensure(run, scene, force)
    # claimed in one order (by folder) in every run, so two runs that share entries never wait on each other
    entries = sorted(((sim_entry(run, s), s) for s in scenes if s.source is None), key=lambda e: str(e[0].final_dir))
    begun = []
    for entry, scene in entries:
        if entry.begin(force=force):
            begun.append((entry, scene))
        else:
            log.info("simulate %s: cached (%s)", scene.name, entry.dir)
    if not begun:
        return
    params, seed, device = run.config.simulate, run.config.seed, warp_device(run.device)
    threads = params.threads or os.cpu_count() or 1
    solver = dataclasses.replace(params, threads=threads)  # the key keeps the config's own

    def one(task: tuple[Path, SceneConfig]) -> dict | Exception:
        try:
            return simulate_sequence(task[0], task[1], solver, device, seed)
        except Exception as exc:  # returned, not raised: Ray would end the run before the others finish
            exc.add_note(traceback.format_exc())  # shown with DEEP_SSFR_DEBUG=1
            return exc

    failed = []

    def finished(k: int, extra: dict | Exception) -> None:  # as each scene returns, not once all have
        entry, scene = begun[k]
        if isinstance(extra, Exception):
            failed.append((scene, extra))
            return
        files = extra.pop("files")
        entry.finish(files, extra.pop("timings"), **extra)
        log.info("simulate %s: %d frames, %.3g particle-steps/s on the cluster -> %s", scene.name, len(files),
                 extra["particle_steps_per_second"], entry.dir)

    run_tasks(one, [(entry.dir, scene) for entry, scene in begun], "ray", run.config.ray_address, run.device,
              cpus=threads, backups=False, on_result=finished)
    for scene, exc in failed[1:]:  # the first is the stage's error
        log.error("simulate %s: failed too: %s", scene.name, exc)
    if failed:
        raise failed[0][1]


def ahead(run: Run, scenes: Sequence[SceneConfig]) -> None:
    """Before a stage's loop over ``scenes``: on a Ray executor their missing sequences simulated at
    once over the cluster (:func:`ensure_all`); locally nothing, each is simulated when reached."""
    if run.config.executor == "ray":
        ensure_all(run, scenes)


def main(opts: StageOptions) -> None:
    """``deep-ssfr simulate``: every configured scene."""
    run = make_run(opts)
    ensure_all(run, list(run.loaded.scenes.values()), force=run.force)
