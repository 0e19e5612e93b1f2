"""Fast against exact screen-space filters: angular error against the mesh target and time per frame.

On the evaluation's held-out sequences (``stages.evaluate.sequences``: the held-out scenes, the
validation camera of the others, the imported SPlisHSPlasH frames), a few frames each, at several
resolutions: the normals of the bilateral and narrow-range filters in ``exact`` mode (2D bilateral
window, every pixel of the narrow-range radius) and ``fast`` mode (separable bilateral, strided
taps), and the shipped refiner on each mode's bilateral input, all against the ray-cast
anisotropic mesh. Errors are pooled over pixels where the method and the mesh both show fluid.

    .venv/bin/python benchmarks/bench_filters.py [--sizes 256 512 1024] [--frames 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import warp as wp

from pipeline.camera import camera_for_frame
from pipeline.exr import stack
from pipeline.frames import frame_name, load_frame, spread
from pipeline.methods import refine
from pipeline.metrics import angular_errors
from pipeline.model import SHIPPED_WEIGHTS
from pipeline.model.inference import load_refiner
from pipeline.parallel import Launcher
from pipeline.screen import ScreenSpace
from pipeline.surface import reconstruct
from pipeline.views import screen_space_inputs, target_channels
from stages import evaluate
from stages.common import StageOptions, make_run

ROOT = Path(__file__).resolve().parents[1]
MODES = ("exact", "fast")
METHODS = ("bilateral", "nrf", "refined")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--frames", type=int, default=4, help="frames per held-out sequence")
    args = parser.parse_args()
    wp.config.quiet = True
    run = make_run(StageOptions(config=args.config))
    base = run.config.dataset
    refiner = load_refiner(SHIPPED_WEIGHTS)
    ss, launch = ScreenSpace("cpu"), Launcher("cpu")
    errors = {(s, m, mode): [] for s in args.sizes for m in METHODS for mode in MODES}
    times = {(s, m, mode): [] for s in args.sizes for m in ("bilateral", "nrf") for mode in MODES}
    radii = {s: [] for s in args.sizes}
    seqs = evaluate.sequences(run)
    for seq in seqs:
        scene, path, r = seq.scene, seq.camera, seq.particle_radius
        frames = [rec["frame"] for rec in seq.records]
        picks = spread(list(range(len(frames))), args.frames)
        for index in picks:
            x, _ = load_frame(seq.sim_dir / frame_name(frames[index]))
            mesh = reconstruct(x, r, base, launch)
            for size in args.sizes:
                cam = camera_for_frame(scene.cameras, path, int(index), len(frames), size, size)
                tc = target_channels(mesh, cam, launch)
                target, t_mask = stack(tc, "target.N."), tc["target.A"] > 0
                for mode in MODES:
                    p = dataclasses.replace(base, filter_mode=mode, width=size, height=size)
                    ch = screen_space_inputs(x, r, cam, p, ss, filters=("bilateral", "nrf"))
                    fluid = ch["A"] > 0
                    for m in ("bilateral", "nrf"):
                        start = time.perf_counter()
                        ss.bilateral(ch["Z"], cam, r, p) if m == "bilateral" else ss.narrow_range(ch["Z"], cam, r, p)
                        times[(size, m, mode)].append(time.perf_counter() - start)
                        errors[(size, m, mode)].append(angular_errors(stack(ch, f"{m}.N."), target, fluid & t_mask))
                    n, mask, _ = refine(refiner, ch, run.config.render.normal_threshold, cam.focal_px, r)
                    errors[(size, "refined", mode)].append(angular_errors(n, target, mask & t_mask))
                    if mode == "fast" and fluid.any():
                        radii[size].append(float(np.median(cam.focal_px * r / ch["Z"][fluid])))
        print(f"  {scene.name}/{path}: {len(picks)} frames", flush=True)
    print(f"\n{len(seqs)} held-out sequences, {args.frames} frames each; angular error against the mesh (deg)")
    print(f"{'size':>5s} {'r_px':>5s} {'method':9s} {'exact mean':>10s} {'median':>7s} {'fast mean':>10s} "
          f"{'median':>7s} {'mean x':>7s} {'median x':>8s} {'exact ms':>9s} {'fast ms':>8s}")
    for size in args.sizes:
        for m in METHODS:
            e = {mode: np.concatenate(errors[(size, m, mode)]) for mode in MODES}
            mean = {mode: float(e[mode].mean()) for mode in MODES}
            med = {mode: float(np.median(e[mode])) for mode in MODES}
            ms = {mode: 1000 * float(np.mean(times[(size, m, mode)])) if m != "refined" else float("nan")
                  for mode in MODES}
            print(f"{size:5d} {np.median(radii[size]):5.1f} {m:9s} {mean['exact']:10.2f} {med['exact']:7.2f} "
                  f"{mean['fast']:10.2f} {med['fast']:7.2f} {mean['fast'] / mean['exact']:7.3f} "
                  f"{med['fast'] / med['exact']:8.3f} {ms['exact']:9.1f} {ms['fast']:8.1f}")
    ss.close()
    launch.close()


if __name__ == "__main__":
    main()
