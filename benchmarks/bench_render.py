"""Render costs per frame on this machine: each stage of the refined method at 256 to 2048 pixels,
for small and large projected particles, the refiner against a plain forward pass of the same
weights, a pipelined frame loop (EXR writing overlapped with the next frame), and optionally the
wall time of ``make demo`` from a clean cache.

Frames: the SPlisHSPlasH dam break (6,859 particles, r = 25 mm: large on screen) and a PBF dam
break of 49,140 particles (r = 7.4 mm: small on screen), each framed whole by the camera.

    .venv/bin/python benchmarks/bench_render.py [--sizes 256 512 1024 2048] [--plot docs/render_costs.png]
                                                [--splat sphere|ellipsoid] [--demo] [--exact]

The refiner's input is what the shipped weights read: since 2026-11-25 the particles' anisotropic
ellipsoids (the per-frame anisotropy of the particles the camera sees joins the inputs), since
2026-12-07 with their density map, which the sphere splat lacks. ``--splat sphere`` times the sphere
splat's stages with weights that read no density.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_dataset import _camera_for, _pbf_frame  # noqa: E402

from pipeline.config import DatasetConfig, RenderConfig  # noqa: E402
from pipeline.device import choose_device, warp_device  # noqa: E402
from pipeline.methods import normal_source, shade_frame  # noqa: E402
from pipeline.model import SHIPPED_WEIGHTS  # noqa: E402
from pipeline.model.data import InputSpec, prepare  # noqa: E402
from pipeline.model.inference import Refiner  # noqa: E402
from pipeline.model.trainer import load_generator, predict  # noqa: E402
from pipeline.parallel import Launcher  # noqa: E402
from pipeline.particles import read_particles  # noqa: E402
from pipeline.screen import ScreenSpace  # noqa: E402
from pipeline.shading import Shader  # noqa: E402
from pipeline.surface import particle_ellipsoids  # noqa: E402
from pipeline.timing import Timings  # noqa: E402
from pipeline.views import screen_space_inputs  # noqa: E402
from pipeline.writer import BackgroundWriter  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("splat", "bilateral", "normals", "refiner", "shading", "exr")


def _best_ms(fn, repeat: int) -> float:
    """Median of ``repeat`` timed calls after one warm-up (ms)."""
    fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000 * float(np.median(times))


def measure(x: np.ndarray, r: float, size: int, p: DatasetConfig, ss: ScreenSpace, launch: Launcher,
            shader: Shader, refiner: Refiner, generator, repeat: int, tmp: Path) -> dict[str, float]:
    """Per-stage medians (ms) of one frame at one size, plus the plain forward pass and a pipelined loop."""
    cam = _camera_for(x, size)
    rp = RenderConfig(width=size, height=size)
    bg = np.full((size, size, 3), 0.5, np.float32)
    bg_depth = np.full((size, size), 10.0, np.float32)
    t = Timings()
    src = {}

    def frame(write: BackgroundWriter | None = None) -> None:
        src.update(normal_source("refined", x, r, cam, p, ss, launch, refiner, timings=t))
        out = shade_frame(src, bg, bg_depth, cam, rp, shader, t)
        if write is not None:
            write.submit(out.write, tmp / "frame.exr", rp, cam, rp.video_fps, 1)
        else:
            with t("exr"):
                out.write(tmp / "frame.exr", rp, cam, rp.video_fps, 1)

    frame()
    t = Timings()
    for _ in range(repeat):
        frame()
    row = {k: t.mean_ms(k) for k in ("anisotropy", "splat", "bilateral", "normals", "refiner", "shading", "exr",
                                     "inputs", "prepare", "network", "post")}
    row["inputs"] += row["anisotropy"]
    ellipsoids = (particle_ellipsoids(x, r, p, launch, density=refiner.spec.density) if refiner.splat == "ellipsoid"
                  else None)
    channels = screen_space_inputs(x, r, cam, p, ss, filters=("bilateral",), ellipsoids=ellipsoids,
                                   aniso_filters=("bilateral",))
    inputs = prepare(channels, refiner.spec, cam.focal_px, r).inputs
    row["plain_refiner"] = _best_ms(lambda: predict(generator, inputs, refiner.device), max(1, repeat // 2))
    row["fast_refiner_nocrop"] = _best_ms(lambda: refiner(inputs), max(1, repeat // 2))
    # the render loop as the stage runs it: EXR writing on a background thread
    n = max(3, repeat)
    with BackgroundWriter() as writer:
        frame(writer)
        start = time.perf_counter()
        for _ in range(n):
            frame(writer)
        writer.drain()
        row["pipelined_frame"] = 1000 * (time.perf_counter() - start) / n
    row["rp_px"] = float(np.median(cam.focal_px * r / src["depth"][src["depth"] > 0])) if src["mask"].any() else 0.0
    return row


def plot(results: dict, path: Path) -> None:
    """Log-log ms per stage against pixel count, one panel per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4.5), squeeze=False)
    for ax, (name, rows) in zip(axes[0], results.items(), strict=True):
        sizes = sorted(int(s) for s in rows)
        px = [s * s for s in sizes]
        for key in (*STAGES, "plain_refiner"):
            style = "--" if key == "plain_refiner" else "-"
            ax.loglog(px, [rows[str(s)][key] for s in sizes], style, marker="o", label=key.replace("_", " "))
        linear = [rows[str(sizes[0])]["inputs"] * n / px[0] for n in px]
        ax.loglog(px, linear, ":", color="gray", label="inputs, if linear in pixels")
        ax.set_title(f"{name}")
        ax.set_xlabel("pixels per frame")
        ax.set_ylabel("ms per frame")
        ax.set_xticks(px, [f"{s}^2" for s in sizes])
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.suptitle(f"render stages per frame, {torch.get_num_threads()} CPU threads")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def shipped_refiner(device: str, splat: str | None = None) -> tuple[Refiner, torch.nn.Module]:
    """The shipped weights as the render runs them and as the training-time module, reading
    ``splat`` (default: the splat they were trained on)."""
    generator, meta = load_generator(SHIPPED_WEIGHTS)
    shipped = InputSpec.of(meta["config"])
    generator = generator.to(device)
    splat = splat or shipped.splat
    if splat == "sphere" and shipped.density:
        raise SystemExit("bench_render: the shipped weights read the ellipsoid splat's density map, which the "
                         "sphere splat has not: use --splat ellipsoid")
    return Refiner(generator, device=device, spec=dataclasses.replace(shipped, splat=splat)), generator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--exact", action="store_true", help="the exact (pre-2026-11) filters instead of the fast")
    parser.add_argument("--splat", choices=("sphere", "ellipsoid"),
                        help="what the refiner's input is made of (default: what the shipped weights read; the "
                             "network's cost is the same)")
    parser.add_argument("--plot", type=Path, help="write a log-log plot of the stage costs here")
    parser.add_argument("--json", type=Path, help="write the figures as JSON here")
    parser.add_argument("--demo", action="store_true", help="also time `make demo` in a fresh cache")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="where Warp and torch run (auto: CUDA when both see a GPU; run cpu and cuda for both)")
    args = parser.parse_args()
    device = choose_device(args.device)
    wdev = warp_device(device)
    wp.config.quiet = True
    p = DatasetConfig(filter_mode="exact" if args.exact else "fast")
    refiner, generator = shipped_refiner(device, args.splat)
    splat = refiner.spec.splat
    ss, launch, shader = ScreenSpace(wdev), Launcher(wdev), Shader(wdev)
    bgeo = ROOT / "tests" / "data" / "dam_break_frame_9_6859_particles.bgeo"
    x_pbf, r_pbf = _pbf_frame(50_000)
    frames = {"SPlisHSPlasH dam break, 6,859 particles (large)": (read_particles(bgeo).positions, 0.025),
              f"PBF dam break, {len(x_pbf):,} particles (small)": (x_pbf, r_pbf)}
    results: dict[str, dict[str, dict[str, float]]] = {}
    where = "CUDA" if device == "cuda" else f"CPU, {torch.get_num_threads()} torch threads"
    print(f"device: {where}; filters: {p.filter_mode}; refiner input: {splat} splat; ms per frame (medians)")
    head = (f"{'size':>5s} {'r_px':>5s} {'aniso':>6s} {'splat':>6s} {'bilat':>6s} {'normal':>6s} {'inputs':>7s} "
            f"{'shade':>6s} {'exr':>6s} {'in+sh+exr':>9s} {'pipelined':>9s} {'refiner':>8s} {'prep':>6s} "
            f"{'net':>6s} {'post':>6s} {'nocrop':>7s} {'plain':>7s} {'speed-up':>8s}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, (x, r) in frames.items():
            print(f"\n{name}\n{head}")
            results[name] = {}
            for size in args.sizes:
                repeat = args.repeat if size <= 1024 else max(2, args.repeat // 2)
                row = measure(x, r, size, p, ss, launch, shader, refiner, generator, repeat, Path(tmp))
                results[name][str(size)] = row
                print(f"{size:5d} {row['rp_px']:5.1f} {row['anisotropy']:6.1f} {row['splat']:6.1f} "
                      f"{row['bilateral']:6.1f} {row['normals']:6.1f} {row['inputs']:7.1f} {row['shading']:6.1f} "
                      f"{row['exr']:6.1f} {row['inputs'] + row['shading'] + row['exr']:9.1f} "
                      f"{row['pipelined_frame']:9.1f} {row['refiner']:8.1f} {row['prepare']:6.1f} "
                      f"{row['network']:6.1f} {row['post']:6.1f} {row['fast_refiner_nocrop']:7.1f} "
                      f"{row['plain_refiner']:7.1f} {row['plain_refiner'] / row['refiner']:7.2f}x", flush=True)
    print("\ninputs = anisotropy (ellipsoid input only) + splat + filter + normals + copies; refiner = folded, "
          "channels-last, cropped to the fluid (nocrop: whole image): prep (the input at the working scale: "
          "numpy on a CPU, torch on the refiner's GPU) + net (the generator) + post (back to the view's size, "
          "mask and depth; on the refiner's device, the reach's distance transform and depth spread too on a GPU); "
          "plain = the training-time module's forward pass; pipelined = a frame of the render loop, inputs + "
          "refiner + shading with the EXR written on a background thread")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    if args.plot:
        plot(results, args.plot)
        print(f"plot: {args.plot}")
    ss.close()
    launch.close()
    shader.close()
    if args.demo:
        with tempfile.TemporaryDirectory() as tmp:
            config = Path(tmp) / "demo.yaml"
            config.write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\ndata_dir: {Path(tmp) / 'data'}\n")
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "stages.cli", "demo", "--config", str(config)], cwd=ROOT, check=True,
                           env={**os.environ, "PYTHONPATH": str(ROOT), "DEEP_SSFR_DEVICE": device},
                           stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL)
            print(f"make demo on {device} (fresh cache, warm kernel cache): {time.perf_counter() - start:.0f} s")
            shutil.rmtree(Path(tmp) / "data", ignore_errors=True)


if __name__ == "__main__":
    main()
