"""The render stage's own frame loop: frames per second with the files written and without.

Renders a PBF dam break of about 49k particles (half a second into the collapse, as
``bench_render.py``) as a sequence through ``pipeline.renderer.SequenceRenderer``, the code
``make render`` runs for each frame: the background, the refined method on the ellipsoid input, the
shading, motion vectors, and the EXR and preview written on the writer thread. Prints the loop's
frames per second with the files written and with the writing left out (issue 13 asks for 30
frames/s at 1024 x 1024 on an H100 with EXR writing excluded), and the per-step means of the stage's
log from the run without files. On a GPU the steps overlap the device's work, so a third run without
files takes the breakdown with every step waiting for the GPU (``DEEP_SSFR_SYNC_TIMINGS``), each
step then holding its own work. ``--trace DIR`` records a last run without files with torch's
profiler (``pipeline.profiling``): its summary (the device's busy share and idle gaps, the host's
waits, the copies, device time by step, the costliest kernels) is printed and saved with the trace.

    .venv/bin/python benchmarks/bench_render_stage.py [--size 1024] [--frames 8] [--device auto]
                                                      [--background none|scene] [--no-motion] [--orbit-deg 1]
                                                      [--trace DIR] [--trace-frames 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dataset import _camera_for, _pbf_state  # noqa: E402

from pipeline.camera import Camera, look_at  # noqa: E402
from pipeline.config_files import load  # noqa: E402
from pipeline.device import choose_device  # noqa: E402
from pipeline.model import SHIPPED_WEIGHTS  # noqa: E402
from pipeline.model.inference import load_refiner  # noqa: E402
from pipeline.profiling import Trace, profiled  # noqa: E402
from pipeline.renderer import SequenceRenderer  # noqa: E402
from pipeline.shading.background import Surroundings  # noqa: E402
from pipeline.timing import SYNC_ENV, Timings  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _orbit(camera: Camera, centre: np.ndarray, degrees: float) -> Camera:
    """``camera`` turned by ``degrees`` about the vertical axis through ``centre``."""
    a = np.radians(degrees)
    turn = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    return Camera(look_at(centre + turn @ (camera.eye - centre), centre), camera.fov_y_deg, camera.width,
                  camera.height)


def loop(folder: Path, config, device: str, refiner, x: np.ndarray, v: np.ndarray, radius: float, frames: int,
         write: bool, orbit_deg: float = 0.0, record: bool = False) -> tuple[float, dict[str, float], Trace]:
    """Frames per second of the render loop over ``frames`` frames after one warm-up frame (the
    writer drained at the end), and its per-step means (ms); the camera turns ``orbit_deg`` a frame
    about the fluid (0: it stays); and, with ``record``, the profiler's trace of the frames after
    the warm-up (``pipeline.profiling``; empty without)."""
    p = config.render
    start_camera, centre = _camera_for(x, p.width), (x.min(0) + x.max(0)) / 2
    camera_at = lambda i: _orbit(start_camera, centre, orbit_deg * i)  # noqa: E731
    lo, hi = x.min(0), x.max(0)
    around = Surroundings(tuple(map(float, lo - 0.05)), tuple(map(float, hi + 0.05)))
    with SequenceRenderer(folder, "bench", around, config, device, refiner) as renderer:
        if not write:
            renderer.write = lambda *args, **kwargs: None
        load_frame = lambda f: (x, v)  # noqa: E731
        renderer.render([0], load_frame, radius, camera_at, videos=False)  # kernels built, caches warm
        renderer.timings = Timings()
        with profiled("render_stage", frames, enabled=record) as trace:
            start = time.perf_counter()
            renderer.render(list(range(1, frames + 1)), load_frame, radius, camera_at, videos=False)
            rate = frames / (time.perf_counter() - start)
        return rate, renderer.timings.per_call_ms(), trace


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--particles", type=int, default=50_000)
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    parser.add_argument("--background", choices=("none", "scene"), default="none",
                        help="'scene' rasterises the floor and walls with pyrender (EGL on a headless GPU)")
    parser.add_argument("--no-motion", action="store_true", help="leave out the motion-vector pass")
    parser.add_argument("--orbit-deg", type=float, default=0.0,
                        help="degrees the camera turns a frame about the fluid (the camera's motion pass)")
    parser.add_argument("--trace", type=Path, help="record a last run without files with torch's profiler; its "
                                                   "trace and summary go into this folder as render_stage.*")
    parser.add_argument("--trace-frames", type=int, default=5, help="frames the recorded run renders")
    args = parser.parse_args()
    device = choose_device(args.device)
    wp.config.quiet = True
    overrides = {"render": {"width": args.size, "height": args.size, "method": "refined", "comparison": False,
                            "background": args.background, "motion_vectors": not args.no_motion}}
    config = load(ROOT / "configs" / "default.yaml", overrides).config
    refiner = load_refiner(SHIPPED_WEIGHTS, device)
    x, v, r = _pbf_state(args.particles)
    where = "CUDA" if device == "cuda" else f"CPU, {torch.get_num_threads()} torch threads"
    print(f"device: {where}; {len(x):,} particles, {args.size} x {args.size}, refined ({refiner.splat} input), "
          f"background {args.background}, motion vectors {'off' if args.no_motion else 'on'}, camera "
          f"{f'turning {args.orbit_deg:g} degrees a frame' if args.orbit_deg else 'at rest'}; {args.frames} frames")
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for write in (False, True):
            rate, steps, _ = loop(Path(tmp) / str(write), config, device, refiner, x, v, r, args.frames, write,
                                  args.orbit_deg)
            results[write] = (rate, steps)
            label = "with EXR + preview written" if write else "without writing files"
            print(f"{label:28s} {rate:6.2f} frames/s ({1000 / rate:7.1f} ms a frame)", flush=True)
    steps = results[False][1]
    print("steps without files (ms a frame): " + ", ".join(f"{k} {v:.1f}" for k, v in steps.items()))
    if device == "cuda":
        os.environ[SYNC_ENV] = "1"
        with tempfile.TemporaryDirectory() as tmp:
            rate, steps, _ = loop(Path(tmp), config, device, refiner, x, v, r, args.frames, False, args.orbit_deg)
        print(f"steps waiting for the GPU ({rate:.2f} frames/s so): "
              + ", ".join(f"{k} {v:.1f}" for k, v in steps.items()))
        os.environ.pop(SYNC_ENV)
    if args.trace:
        with tempfile.TemporaryDirectory() as tmp:
            rate, _, trace = loop(Path(tmp), config, device, refiner, x, v, r, args.trace_frames, False,
                                  args.orbit_deg, record=True)
        print(trace.report(args.trace, f"{rate:.2f} frames/s so, its own cost included"))


if __name__ == "__main__":
    main()
