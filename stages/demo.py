"""``make demo``: the main job on the embedded default, end to end.

Simulates the default scene (dam break), builds its screen-space inputs, refines the normal maps
with the shipped generator, shades, and writes the EXR frames, a preview MP4 and the comparison
(bilateral | narrow-range | refined | metaballs | mesh) as video and contact sheet. Prints where they are.
"""

from __future__ import annotations

import dataclasses
import logging
import time

from stages import render
from stages.common import StageOptions, make_run

log = logging.getLogger("deep_ssfr")
DEFAULT_SCENE = "dam_break"


def main(opts: StageOptions) -> None:
    """``deep-ssfr demo``."""
    opts = dataclasses.replace(opts, scene=opts.scene or DEFAULT_SCENE)
    run = make_run(opts, overrides={"render": {"method": "refined", "comparison": True}})
    start = time.perf_counter()
    scene = run.loaded.scene(opts.scene)
    entry = render.ensure(run, scene, force=run.force)
    p = run.config.render
    wall = time.perf_counter() - start
    print(f"\ndeep-ssfr demo: {scene.name}, {p.width}x{p.height}, refined normals, done in {wall:.0f} s")
    print(f"  EXR frames        {entry.dir / 'frames'}/frame_0001.exr ...")
    print(f"  previews          {entry.dir / 'preview'}/frame_0001.png ...")
    print(f"  video             {entry.dir / f'{scene.name}_{p.method}.mp4'}")
    print(f"  comparison video  {entry.dir / f'{scene.name}_comparison.mp4'}")
    print(f"  comparison sheet  {entry.dir / f'{scene.name}_comparison_sheet.png'}")
