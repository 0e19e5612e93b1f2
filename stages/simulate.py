"""``make simulate``: run PBF for each configured scene (or import its particle files) into the cache.

Writes ``data/simulate/<scene>-<key>/frame_0001.npz ...`` (positions, velocities), ``sequence.json``
and ``manifest.json`` (``pipeline.sim.runner``). A killed run resumes from its last whole frame.
"""

from __future__ import annotations

import logging
import os
import sys

from pipeline import cache
from pipeline.config import SceneConfig, to_dict
from pipeline.device import warp_device
from pipeline.sim.runner import import_sequence, simulate_sequence, source_files
from stages.common import Run

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
        extra = import_sequence(entry.dir, scene.name, source_files(scene), src.particle_radius, src.fps, src.up,
                                src.pattern)
    else:
        extra = simulate_sequence(entry.dir, scene, run.config.simulate, warp_device(run.device), run.config.seed)
    entry.finish(extra.pop("files"), extra.pop("timings"), **extra)
    log.info("simulate %s: -> %s", scene.name, entry.dir)
    return entry


if __name__ == "__main__":
    from stages.cli import main as cli

    sys.exit(cli(["simulate", *sys.argv[1:]]))
