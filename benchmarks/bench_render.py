"""Render costs per frame: screen-space inputs, refiner, shading and EXR write at 512^2 and 1024^2,
and the wall time of ``make demo`` from a clean cache.

    .venv/bin/python benchmarks/bench_render.py [--demo]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import warp as wp

from pipeline.camera import Camera, look_at
from pipeline.config import RenderConfig, load
from pipeline.exr import write_exr
from pipeline.model.trainer import load_generator
from pipeline.parallel import Launcher
from pipeline.particles import read_particles
from pipeline.render import normal_source, shade_frame
from pipeline.screen import ScreenSpace
from pipeline.shading import Shader
from pipeline.shading.background import BackgroundRenderer
from pipeline.timing import Timings

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo", action="store_true", help="also time `make demo` in a fresh cache")
    args = parser.parse_args()
    wp.config.quiet = True
    loaded = load(ROOT / "configs" / "default.yaml")
    x = read_particles(ROOT / "tests" / "data" / "dam_break_frame_9_6859_particles.bgeo").positions
    r = 0.025
    generator, _ = load_generator(ROOT / "pipeline" / "weights" / "refiner.pt")
    ss, launch, shader = ScreenSpace("cpu"), Launcher("cpu"), Shader("cpu")
    centre = (x.min(0) + x.max(0)) / 2
    print(f"{'size':>6s} {'inputs':>8s} {'refiner':>8s} {'shading':>8s} {'exr':>8s} {'total':>8s}  (ms per frame)")
    for size in (512, 1024):
        cam = Camera(look_at(centre + np.array([0.0, 0.8, 2.6]), centre), 40.0, size, size)
        p = RenderConfig(width=size, height=size)
        bg = BackgroundRenderer(loaded.imported["splishsplash_dam_break"], p, size, size)
        colour, depth = bg.render(cam)
        t = Timings()
        for _ in range(3):
            src = normal_source("refined", x, r, cam, loaded.config.dataset, ss, launch, generator, timings=t)
            frame = shade_frame(src, colour, depth, cam, p, shader, t)
            with tempfile.TemporaryDirectory() as tmp, t("exr"):
                write_exr(Path(tmp) / "frame_0001.exr", frame.channels())
        bg.close()
        parts = [t.mean_ms("inputs"), t.mean_ms("refiner"), t.mean_ms("shading"), t.mean_ms("exr")]
        print(f"{size:6d} {parts[0]:8.1f} {parts[1]:8.1f} {parts[2]:8.1f} {parts[3]:8.1f} {sum(parts):8.1f}")
    if args.demo:
        with tempfile.TemporaryDirectory() as tmp:
            config = Path(tmp) / "demo.yaml"
            config.write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\ndata_dir: {Path(tmp) / 'data'}\n")
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "stages.demo", "--config", str(config)], cwd=ROOT, check=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
            print(f"make demo (fresh cache, warm kernel cache): {time.perf_counter() - start:.0f} s")
            shutil.rmtree(Path(tmp) / "data", ignore_errors=True)


if __name__ == "__main__":
    main()
