"""The refined method's inference settings, chosen on the validation scene only.

The refined mask may reach ``REFINED_REACH_PX`` working pixels past the splat (the mesh is wider
than the particles' splat), at render time views whose particles are smaller than
``UPSCALE_BELOW_PX`` are interpolated up to the working radius, small inputs also run mirrored
(``FLIP_MAX_PIXELS``), and the network may run in
bfloat16 (``render.refiner_precision``); refined pixels whose normal is shorter than
``render.normal_threshold`` are dropped. All of them change what the evaluation scores, so they are
chosen here on the scene that chooses the trainer's best checkpoint (``train.validation_scenes``),
never on the reported held-out sequences. This prints, for each value of one setting (the others at
their defaults), the refined normals' mean and median error over the
mesh's pixels (a missed pixel scores 90 degrees, as in the report), the missed share and IoU, at
each size, for both cameras of the validation scene (``--scenes``: of training scenes instead).

    .venv/bin/python benchmarks/tune_inference.py [--config configs/generalize.yaml] [--sizes 256 512 1024]
    .venv/bin/python benchmarks/tune_inference.py --sizes 128 160 192 256 512 1024 --reaches 2 3 4 \
        --below 0 1.6 inf --precisions float32 bfloat16    # the table in docs/evaluation.md
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pipeline.methods as methods  # noqa: E402
import pipeline.model.inference as inference  # noqa: E402
from pipeline.camera import Camera, camera_for_frame  # noqa: E402
from pipeline.dataset import CAMERAS  # noqa: E402
from pipeline.exr import read_exr, stack  # noqa: E402
from pipeline.frames import read_sequence_info, spread  # noqa: E402
from pipeline.metrics import errors_over_reference, iou  # noqa: E402
from pipeline.model.scale import median_radius_px  # noqa: E402
from stages import dataset, render, simulate  # noqa: E402
from stages.common import StageOptions, make_run  # noqa: E402


@dataclass(frozen=True)
class View:
    """One dataset view of a scene's camera path: its channels, camera, the mesh's normals and mask."""

    scene: str
    radius: float
    sim_dir: Path
    record: dict
    channels: dict[str, np.ndarray]
    camera: Camera
    target: np.ndarray
    target_mask: np.ndarray


def scene_views(run, names: list[str], frames: int, size: int) -> Iterator[View]:
    """``frames`` views of each camera path of the scenes ``names`` at ``size`` px, from the
    dataset (built where missing), evenly spread over the path."""
    for name in names:
        scene = run.loaded.scenes[name]
        entry, sim = dataset.ensure(run, scene), simulate.ensure(run, scene)
        radius = read_sequence_info(sim.dir).particle_radius
        for camera in CAMERAS:
            records = [r for r in entry.manifest()["frames"] if r["camera"] == camera]
            for r in spread(records, frames):
                ch = read_exr(entry.dir / r["file"])
                cam = camera_for_frame(scene.cameras, camera, r["index"], len(records), size, size)
                yield View(name, radius, sim.dir, r, ch, cam, stack(ch, "target.N."), ch["target.A"] > 0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "generalize.yaml"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--frames", type=int, default=8, help="views per camera")
    parser.add_argument("--reaches", type=int, nargs="+", default=[0, 1, 2, 3, 4, 6])
    parser.add_argument("--below", type=float, nargs="+", default=[0.0, 0.8, 1.0, 1.25, 1.5, float("inf")],
                        help="UPSCALE_BELOW_PX values (0: never upscale, inf: always)")
    parser.add_argument("--precisions", nargs="+", default=["float32", "bfloat16"], choices=["float32", "bfloat16"])
    parser.add_argument("--flips", type=float, nargs="+", default=[],
                        help="FLIP_MAX_PIXELS values (0: one pass, inf: every input also mirrored)")
    parser.add_argument("--thresholds", type=float, nargs="+", default=[],
                        help="render.normal_threshold values (the refined normal's shortest kept length)")
    parser.add_argument("--scenes", nargs="+", default=None,
                        help="scenes whose camera paths score (default: the validation scenes; never held-out ones)")
    args = parser.parse_args()
    wp.config.quiet = True
    defaults = {"reach": methods.REFINED_REACH_PX, "below": methods.UPSCALE_BELOW_PX,
                "flip": inference.FLIP_MAX_PIXELS}
    settings = ([("reach", v) for v in args.reaches] + [("below", v) for v in args.below]
                + [("precision", v) for v in args.precisions] + [("threshold", v) for v in args.thresholds]
                + [("flip", v) for v in args.flips])
    config = make_run(StageOptions(config=args.config), {}).config
    names = args.scenes or list(config.train.validation_scenes)
    reported = set(names) & (set(config.dataset.holdout_scenes) - set(config.train.validation_scenes))
    if reported:
        raise SystemExit(f"tune_inference: {', '.join(sorted(reported))} are reported held-out scenes; settings "
                         "are chosen on the validation and training scenes only")
    scores: dict = {}
    radii: dict[int, list[float]] = {}
    for size in args.sizes:
        run = make_run(StageOptions(config=args.config), {"dataset": {"width": size, "height": size}})
        refiners = {p: render.networks(make_run(StageOptions(config=args.config), {
            "dataset": {"width": size, "height": size}, "render": {"refiner_precision": p}}), ("refined",))[0]
            for p in ("auto", *args.precisions)}
        threshold = run.config.render.normal_threshold
        for view in scene_views(run, names, args.frames, size):
            ch, cam, radius = view.channels, view.camera, view.radius
            target, t_mask = view.target, view.target_mask
            radii.setdefault(size, []).append(median_radius_px(ch["Z"], cam.focal_px, radius))
            for key, value in settings:
                methods.REFINED_REACH_PX = value if key == "reach" else defaults["reach"]
                methods.UPSCALE_BELOW_PX = value if key == "below" else defaults["below"]
                inference.FLIP_MAX_PIXELS = value if key == "flip" else defaults["flip"]
                refiner = refiners[value if key == "precision" else "auto"]
                n, mask, _ = methods.refine(refiner, ch, value if key == "threshold" else threshold,
                                            cam.focal_px, radius)
                e, _, missed = errors_over_reference(n, target, mask, t_mask)
                got = scores.setdefault((size, key, value), {"errors": [], "missed": 0, "iou": []})
                got["errors"].append(e)
                got["missed"] += missed
                got["iou"].append(iou(mask, t_mask))
        print(f"  {size} px done", flush=True)
    methods.REFINED_REACH_PX, methods.UPSCALE_BELOW_PX = defaults["reach"], defaults["below"]
    inference.FLIP_MAX_PIXELS = defaults["flip"]
    scored = ", ".join(args.scenes) if args.scenes else "validation scenes"
    print(f"\n{scored} of {Path(args.config).name}; refined over the mesh's pixels: mean / median (deg), "
          f"missed, IoU; defaults: reach {defaults['reach']} px, upscale below {defaults['below']:g} px, "
          f"precision {str(refiners['auto'].dtype).removeprefix('torch.')}")
    print(f"{'setting':>18s}" + "".join(f" {f'{s} px (particles {np.median(radii[s]):.1f} px)':>30s}"
                                        for s in args.sizes) + f" {'avg mean':>9s}")
    for key, value in settings:
        cells, means = "", []
        for size in args.sizes:
            got = scores[(size, key, value)]
            e = np.concatenate(got["errors"])
            means.append(float(e.mean()))
            cells += (f" {e.mean():6.2f} / {np.median(e):5.2f} {100 * got['missed'] / e.size:5.2f}% "
                      f"{np.mean(got['iou']):.3f}")
        label = f"{key} {value}" if isinstance(value, str) else f"{key} {value:g}"
        print(f"{label:>18s}{cells} {np.mean(means):9.2f}")


if __name__ == "__main__":
    main()
