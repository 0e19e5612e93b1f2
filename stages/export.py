"""``make export``: PLY or legacy VTK copies of each cached particle sequence, for other tools.

Writes ``data/simulate/<scene>-<key>/export/<format>/frame_0001.<format> ...``.
"""

from __future__ import annotations

import logging
import sys

from tqdm import tqdm

from pipeline import cache
from pipeline.frames import frame_name, load_frame
from pipeline.particles import ParticleFrame, write_particles
from stages import simulate
from stages.common import make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make export``."""
    args = parse_args("export", argv, lambda p: p.add_argument("--format", choices=["ply", "vtk"], default="ply"))
    run = make_run(args)
    for scene in run.loaded.scenes.values():
        entry = simulate.ensure(run, scene)
        out = entry.dir / "export" / args.format
        n = len(entry.manifest()["files"])
        for i in tqdm(range(1, n + 1), desc=f"export {scene.name}", unit="frame"):
            x, v = load_frame(entry.path(frame_name(i)))
            with cache.atomic_path(out / frame_name(i, args.format)) as tmp:
                write_particles(tmp, ParticleFrame(x, v), args.format)
        log.info("export %s: %d %s files in %s", scene.name, n, args.format, out)


if __name__ == "__main__":
    sys.exit(stage_main("export", main))
