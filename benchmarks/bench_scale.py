"""Cost per frame at the particle counts users bring: the refined method against the mesh it imitates.

Frames: the SPlisHSPlasH double dam break (4,732 particles, r = 25 mm, ``tests/data``) with each
particle split into k^3 of radius r / k on a jittered lattice: about 38k, 303k and 1.02M particles of
the same fluid. Each is rendered at 1920 x 1080 (and the 1M frame once at 3840 x 2160) with the
methods refined, aniso_nrf, nrf and mesh, each in a process of its own: one frame to warm up
(kernel compilation, the GL context), then a sequence of one frame and one of ``--frames`` frames
through the renderer's own loop (EXR written on its thread while the next frame computes), a still
camera. A frame's time is the difference of the two over ``--frames`` - 1: a frame of a long
sequence, without the last frame's EXR, which is written once per sequence after every frame is
computed (as the user's command is timed below). Printed: wall ms per frame, ms per step, the
process's peak memory, the ratios refined / mesh and refined / nrf, and
pysplashsurf's reconstruction of the same particles (the mesh alone, not rendered) as the outside
anchor. Right after each refined measurement comes the command a user runs (``deep-ssfr render
PATTERN``) on ``--sequence`` frames and on the first alone, then the refined frame again: the time to
the first frame, and each further frame against the mean of the renderer's own two.

    .venv/bin/python benchmarks/bench_scale.py [--counts 38k 303k 1022k] [--methods ...] [--frames 3]
                                               [--no-4k] [--json out.json]

pysplashsurf comes with the bench extra (``pip install -e '.[bench]'``); without it that column is
empty.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "tests" / "data" / "double_dam_break_frame_01_4732_particles.vtk"
SOURCE_RADIUS = 0.025
SPLITS = {"38k": 2, "303k": 4, "1022k": 6}
METHODS = ("refined", "aniso_nrf", "nrf", "mesh")
STEPS = ("background", "anisotropy", "inputs", "refiner", "mesh", "nrf", "shading", "motion", "exr_write")


def split_frame(k: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """The source frame with each particle split into k^3 of radius r / k (lattice offsets of 2r / k,
    jittered by 5% of that): positions, velocities and the new radius."""
    from pipeline.particles import read_particles

    frame = read_particles(SOURCE)
    g = (np.arange(k) - (k - 1) / 2) * (2 * SOURCE_RADIUS / k)
    offsets = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x = (frame.positions[:, None, :] + offsets[None]).reshape(-1, 3)
    x += np.random.default_rng(seed).normal(0.0, 0.05 * SOURCE_RADIUS / k, x.shape)
    v = np.repeat(frame.velocities, len(offsets), axis=0)
    return x.astype(np.float32), v.astype(np.float32), SOURCE_RADIUS / k


def measure_one(count: str, method: str, width: int, height: int, frames: int) -> dict:
    """Render one split frame ``frames`` times (after a warm-up frame) with one method: wall ms per
    frame, ms per step and the peak resident memory of this process."""
    from pipeline.camera import framing_cameras
    from pipeline.config import Config
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_weights
    from pipeline.renderer import SequenceRenderer
    from pipeline.shading.background import Surroundings
    from pipeline.timing import Timings
    from stages.cli import keep_freed_memory

    keep_freed_memory()  # as every deep-ssfr command does
    x, v, r = split_frame(SPLITS[count])
    config = Config(scenes=())
    config = dataclasses.replace(config, render=dataclasses.replace(
        config.render, width=width, height=height, method=method, comparison=False))
    camera = framing_cameras(x.min(0) - r, x.max(0) + r, width, height, 1)[0]
    refiner = load_weights(SHIPPED_WEIGHTS)[0] if method == "refined" else None
    around = Surroundings(tuple(x.min(0) - 4 * r), tuple(x.max(0) + 4 * r), walls=False)
    with tempfile.TemporaryDirectory() as tmp, \
            SequenceRenderer(Path(tmp), "bench", around, config, "cpu", refiner) as renderer:
        renderer.render([0], lambda i: (x, v), r, lambda i: camera, videos=False)  # warm-up
        renderer.timings = Timings()
        walls = []
        for numbers in ([1], list(range(2, frames + 2))):  # one frame, then ``frames``, each to its last write
            start = time.perf_counter()
            renderer.render(numbers, lambda i: (x, v), r, lambda i: camera, videos=False)
            walls.append(time.perf_counter() - start)
        steps = renderer.timings.as_dict()
    return {"count": count, "particles": len(x), "method": method, "size": f"{width}x{height}",
            "ms_per_frame": 1000 * (walls[1] - walls[0]) / (frames - 1),
            "steps_ms": {k: 1000 * t["seconds"] / (frames + 1) for k, t in steps.items()},
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def splashsurf_ms(count: str) -> float | None:
    """pysplashsurf's reconstruction of a split frame (ms, after a warm-up run), on the grid our mesh
    method uses (its cell size, capped at ``dataset.max_grid_cells`` a side); None without it."""
    try:
        import pysplashsurf
    except ImportError:
        return None
    from pipeline.config import DatasetConfig

    x, _, r = split_frame(SPLITS[count])
    p = DatasetConfig()
    span = float((x.max(0) - x.min(0)).max() + 4 * r)
    cube = max(r / p.grid_cells_per_radius, span / (p.max_grid_cells - 5))
    kw = dict(particle_radius=r, smoothing_length=2.0 * r, cube_size=cube, iso_surface_threshold=0.6)
    x64 = x.astype(np.float64)
    pysplashsurf.reconstruct_surface(x64, **kw)
    start = time.perf_counter()
    pysplashsurf.reconstruct_surface(x64, **kw)
    return 1000 * (time.perf_counter() - start)


def sequence_overhead(count: str, frames: int, width: int, height: int) -> dict:
    """The command a user runs, ``deep-ssfr render PATTERN``, on a sequence of ``frames`` split frames
    (each jittered anew) and on its first frame alone, from a clean output folder each: seconds from
    process start to the end (import, camera, video and publishing included)."""
    from pipeline.particles import ParticleFrame, write_particles

    timings = {}
    with tempfile.TemporaryDirectory() as tmp:
        for f in range(1, frames + 1):
            x, v, r = split_frame(SPLITS[count], seed=f)
            write_particles(Path(tmp) / f"fluid_{f}.ply", ParticleFrame(x, v))
        for label, last in (("first", 1), ("all", frames)):
            cmd = [str(Path(sys.executable).parent / "deep-ssfr"), "render", str(Path(tmp) / "fluid_{}.ply"),
                   "--radius", str(r), "--out", str(Path(tmp) / f"out_{label}"), "--size", f"{width}x{height}",
                   "--frames", f"1:{last}"]
            start = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True, cwd=ROOT,
                           env={**os.environ, "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")})
            timings[label] = time.perf_counter() - start
    return {"count": count, "frames": frames, "first_s": timings["first"], "all_s": timings["all"],
            "per_frame_s": (timings["all"] - timings["first"]) / (frames - 1)}


def _child(args: list[str]) -> dict:
    """Run one measurement in a fresh process (its own peak memory) and read its JSON line, in the
    environment ``deep-ssfr`` sets (``stages.cli.RUNTIME_ENV``)."""
    from stages.cli import RUNTIME_ENV

    env = {**RUNTIME_ENV, **os.environ,
           "PYOPENGL_PLATFORM": os.environ.get("PYOPENGL_PLATFORM", "egl")}
    out = subprocess.run([sys.executable, __file__, "--one", *args], capture_output=True, text=True, cwd=ROOT,
                         env=env)
    if out.returncode != 0:
        raise SystemExit(f"bench_scale: {' '.join(args)} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _ratio(rows: dict[str, dict], a: str, b: str) -> str:
    """Method a's time per frame over method b's, or '-' when either was not measured."""
    return f"{rows[a]['ms_per_frame'] / rows[b]['ms_per_frame']:.2f}" if a in rows and b in rows else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--counts", nargs="+", default=list(SPLITS), choices=list(SPLITS))
    ap.add_argument("--methods", nargs="+", default=list(METHODS))
    ap.add_argument("--frames", type=int, default=4, help="frames of the longer timed sequence (at least 2)")
    ap.add_argument("--no-4k", action="store_true", help="skip the 3840 x 2160 frame")
    ap.add_argument("--sequence", type=int, default=11,
                    help="frames of the deep-ssfr render run timed against the renderer's own frames (<2: none)")
    ap.add_argument("--json", type=Path, help="also write every figure here")
    ap.add_argument("--one", nargs=4, metavar=("COUNT", "METHOD", "WIDTH", "HEIGHT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.frames < 2:
        ap.error("--frames must be at least 2")
    if args.one:
        count, method, width, height = args.one
        print(json.dumps(measure_one(count, method, int(width), int(height), args.frames)))
        return

    cases = [(c, m, 1920, 1080) for c in args.counts for m in args.methods]
    if not args.no_4k and "1022k" in args.counts:
        cases.append(("1022k", "refined", 3840, 2160))
    rows, runs = [], []
    for count, method, w, h in cases:
        print(f"  {count} {method} {w}x{h} ...", file=sys.stderr, flush=True)
        rows.append(_child([count, method, str(w), str(h), "--frames", str(args.frames)]))
        if method == "refined" and (w, h) == (1920, 1080) and args.sequence > 1:
            # the command between two of the renderer's own measurements: this machine's speed
            # drifts by more than the overhead sought within minutes
            print(f"  {count} deep-ssfr render, {args.sequence} frames ...", file=sys.stderr, flush=True)
            run = sequence_overhead(count, args.sequence, w, h)
            after = _child([count, method, str(w), str(h), "--frames", str(args.frames)])
            run["own_s"] = (rows[-1]["ms_per_frame"] + after["ms_per_frame"]) / 2000
            runs.append(run)
    splash = {c: splashsurf_ms(c) for c in args.counts}

    print(f"# bench_scale: {date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"device cpu, sequences of 1 and {args.frames} frames a measurement\n")
    print("## ms per frame of a long sequence at 1920x1080 (wall, EXR written alongside) and peak memory\n")
    print("| particles | " + " | ".join(args.methods) + " | refined / mesh | refined / nrf | splashsurf (mesh only) |")
    print("|---" * (len(args.methods) + 4) + "|")
    for c in args.counts:
        got = {r["method"]: r for r in rows if r["count"] == c and r["size"] == "1920x1080"}
        cells = [f"{got[m]['ms_per_frame']:.0f} ms, {got[m]['peak_mb'] / 1024:.2f} GB" for m in args.methods]
        s = f"{splash[c]:.0f} ms" if splash[c] is not None else "not installed"
        print(f"| {got[args.methods[0]]['particles']:,} | " + " | ".join(cells) +
              f" | {_ratio(got, 'refined', 'mesh')} | {_ratio(got, 'refined', 'nrf')} | {s} |")
    print("\n## ms per step (each step's own time; the EXR's overlaps the next frame)\n")
    print("| particles | method | size | " + " | ".join(STEPS) + " | wall |")
    print("|---" * (len(STEPS) + 4) + "|")
    for r in rows:
        cells = [f"{r['steps_ms'][k]:.0f}" if k in r["steps_ms"] else "" for k in STEPS]
        print(f"| {r['particles']:,} | {r['method']} | {r['size']} | " + " | ".join(cells) +
              f" | {r['ms_per_frame']:.0f} |")
    if runs:
        print(f"\n## `deep-ssfr render PATTERN` (refined, 1920x1080): {args.sequence} frames against the first alone\n")
        print("| particles | first frame, process start to end (s) | each further frame (s) | renderer's own frame "
              "(s, the mean of one measurement just before and one just after) | overhead |")
        print("|---|---|---|---|---|")
        for run in runs:
            own = run["own_s"]
            print(f"| {SPLITS[run['count']] ** 3 * 4732:,} | {run['first_s']:.1f} | {run['per_frame_s']:.2f} | "
                  f"{own:.2f} | {100 * (run['per_frame_s'] / own - 1):+.0f}% |")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "splashsurf_ms": splash, "sequence": runs}, indent=1))


if __name__ == "__main__":
    main()
