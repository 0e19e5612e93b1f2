"""``make export``: PLY or legacy VTK copies of each cached particle sequence, for other tools.

Writes ``data/simulate/<scene>-<key>/export/<format>/frame_0001.<format> ...``.
"""

from __future__ import annotations

import logging

from tqdm import tqdm

from pipeline import cache
from pipeline.frames import frame_name, load_frame
from pipeline.particles import ParticleFrame, write_particles
from stages import simulate
from stages.common import StageOptions, make_run

log = logging.getLogger("deep_ssfr")


def main(opts: StageOptions, fmt: str = "ply") -> None:
    """``deep-ssfr export``."""
    run = make_run(opts)
    simulate.ahead(run, list(run.loaded.scenes.values()))
    for scene in run.loaded.scenes.values():
        entry = simulate.ensure(run, scene)
        out = entry.dir / "export" / fmt
        n = len(entry.manifest()["files"])
        for i in tqdm(range(1, n + 1), desc=f"export {scene.name}", unit="frame"):
            x, v = load_frame(entry.path(frame_name(i)))
            with cache.atomic_path(out / frame_name(i, fmt)) as tmp:
                write_particles(tmp, ParticleFrame(x, v), fmt)
        log.info("export %s: %d %s files in %s", scene.name, n, fmt, out)
