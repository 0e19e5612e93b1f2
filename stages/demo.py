"""``make demo``: the main job on the embedded default, end to end.

Simulates the default scene (dam break), builds its screen-space inputs, refines the normal maps
with the shipped generator, shades, and writes the EXR frames, a preview MP4 and the comparison
(bilateral | narrow-range | refined | mesh) as video and contact sheet. Prints where they are.
"""

from __future__ import annotations

import logging
import sys
import time

from stages import render
from stages.common import make_run, parse_args, stage_main

log = logging.getLogger("deep_ssfr")
DEFAULT_SCENE = "dam_break"


def main(argv: list[str] | None = None) -> None:
    """Entry point of ``make demo``."""
    args = parse_args("demo", argv)
    args.scene = args.scene or DEFAULT_SCENE
    run = make_run(args, overrides={"render": {"method": "refined", "comparison": True}})
    start = time.perf_counter()
    scene = run.loaded.scene(args.scene)
    entry = render.ensure(run, scene, force=run.force)
    p = run.config.render
    wall = time.perf_counter() - start
    print(f"\ndeep-ssfr demo: {scene.name}, {p.width}x{p.height}, refined normals, done in {wall:.0f} s")
    print(f"  EXR frames        {entry.dir / 'frames'}/frame_0001.exr ...")
    print(f"  previews          {entry.dir / 'preview'}/frame_0001.png ...")
    print(f"  video             {entry.dir / f'{scene.name}_{p.method}.mp4'}")
    print(f"  comparison video  {entry.dir / f'{scene.name}_comparison.mp4'}")
    print(f"  comparison sheet  {entry.dir / f'{scene.name}_comparison_sheet.png'}")


if __name__ == "__main__":
    sys.exit(stage_main("demo", main))
