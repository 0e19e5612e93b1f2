"""The dataset stage's throughput in views per second at one size (issue 13 asks for 20 or more at
512 x 512 on a GPU).

Simulates a scene into an empty cache, then times ``deep-ssfr dataset`` on it: every view of the
scene's cameras at ``--size`` (no random views, which come at random sizes). A view is one EXR of
the stage: the sphere and ellipsoid inputs with their filters and the mesh target (built once per
frame, cast per view). The stage runs twice, on the first half of the ``--frames`` frames and on all
of them (two cache entries of the one simulation), and prints each run's views per second and the
second half's views over the extra wall time: what the stage keeps up once running, without its
fixed costs (loading the kernels, the first frame's warm-up, the manifest), which on a GPU are
much of a short run (the later frames of a dam break are more spread out, so on the CPU, where
the fixed costs are small, the second half runs a little slower than the whole); before them,
the per-step costs of the whole run. ``--trace DIR`` records a third run, on the first
``--trace-frames`` frames, with torch's profiler (``pipeline.profiling``, its figures per view; the
run's kernel loads and first frame included) and prints and saves its summary with the trace.

    .venv/bin/python benchmarks/bench_dataset_stage.py [--config configs/default.yaml] [--scene dam_break]
                                                       [--size 512] [--frames 16] [--trace DIR] [--trace-frames 2]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import warp as wp
import yaml
from stage_runs import logged_summary, scratch_config

from pipeline.device import choose_device
from pipeline.profiling import Trace, profiled
from stages import cli

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    parser.add_argument("--scene", default="dam_break")
    parser.add_argument("--size", type=int, default=512, help="width and height of every view (px)")
    parser.add_argument("--frames", type=int, default=16, help="frames of the simulation made into views")
    parser.add_argument("--trace", type=Path, help="record a run with torch's profiler; its trace and summary go "
                                                   "into this folder as dataset_stage.*")
    parser.add_argument("--trace-frames", type=int, default=2, help="frames of the recorded run")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    with tempfile.TemporaryDirectory() as tmp:
        config = scratch_config(args.config, Path(tmp), simulate={"frames": args.frames},
                                dataset={"width": args.size, "height": args.size, "frame_stride": 1,
                                         "random_views": 0})
        assert cli.main(["simulate", "--config", str(config), "--scene", args.scene]) == 0
        runs = [_run(config, args.scene, max_frames) for max_frames in (args.frames // 2, 0)]
        traced = _run(config, args.scene, args.trace_frames, record=True)[3] if args.trace else None
    (half_views, half_wall, _, _), (views, wall, steps, _) = runs
    print(f"{args.scene}: views at {args.size}x{args.size} on {choose_device()}")
    print(f"  per call (all)    {steps}")
    print(f"  dataset stage     {half_views / half_wall:8.2f} views/s  ({half_views} views, {half_wall:.1f} s)")
    print(f"  dataset stage     {views / wall:8.2f} views/s  ({views} views, {wall:.1f} s)")
    if views > half_views and wall > half_wall:
        print(f"  second half       {(views - half_views) / (wall - half_wall):8.2f} views/s  (frames "
              f"{args.frames // 2 + 1}-{args.frames}: their views over the extra wall time, the fixed costs cancel)")
    if traced is not None:
        print(traced.report(args.trace, f"{args.trace_frames} frames, the run's fixed costs and the profiler's own "
                                        "included"))


def _run(config: Path, scene: str, max_frames: int, record: bool = False) -> tuple[int, float, str, Trace]:
    """The dataset stage on the first ``max_frames`` frames (0: all): its views, wall seconds and
    steps, and with ``record`` the profiler's trace of it (empty without)."""
    body = yaml.safe_load(config.read_text())
    body["dataset"]["max_frames"] = max_frames
    config.write_text(yaml.safe_dump(body))
    with profiled("dataset_stage", unit="view", enabled=record) as trace:
        # the recorded run builds its views again, even when a timed run already made those frames
        found = logged_summary("dataset", config, scene, r"dataset \S+: (\d+) EXR files in ([\d.]+) s \(([^)]*)\)",
                               force=record)
    trace.units = int(found.group(1))
    return int(found.group(1)), float(found.group(2)), found.group(3), trace

if __name__ == "__main__":
    main()
