"""The dataset stage's throughput in views per second at one size (issue 13 asks for 20 or more at
512 x 512 on a GPU).

Simulates a scene into an empty cache, then times ``deep-ssfr dataset`` on it: every view of the
scene's cameras at ``--size`` (no random views, which come at random sizes), for ``--frames``
frames. A view is one EXR of the stage: the sphere and ellipsoid inputs with their filters and the
mesh target (built once per frame, cast per view). Prints the stage's own wall time and its
per-step costs.

    .venv/bin/python benchmarks/bench_dataset_stage.py [--config configs/default.yaml] [--scene dam_break]
                                                       [--size 512] [--frames 16]
"""

from __future__ import annotations

import argparse
import io
import logging
import re
import tempfile
from pathlib import Path

import warp as wp
import yaml

from pipeline.device import choose_device
from stages import cli

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    parser.add_argument("--scene", default="dam_break")
    parser.add_argument("--size", type=int, default=512, help="width and height of every view (px)")
    parser.add_argument("--frames", type=int, default=16, help="frames of the simulation made into views")
    args = parser.parse_args()
    wp.config.log_level = wp.LOG_WARNING
    with tempfile.TemporaryDirectory() as tmp:
        body = yaml.safe_load(Path(args.config).read_text())
        body.update(data_dir=tmp, scene_dir=str(Path(args.config).resolve().parent / body.get("scene_dir", "scenes")))
        body.setdefault("simulate", {})["frames"] = args.frames
        body.setdefault("dataset", {}).update(width=args.size, height=args.size, frame_stride=1, max_frames=0,
                                              random_views=0)
        config = Path(tmp) / "config.yaml"
        config.write_text(yaml.safe_dump(body))
        assert cli.main(["simulate", "--config", str(config), "--scene", args.scene]) == 0
        stream = io.StringIO()
        handler = logging.StreamHandler(stream)
        logging.getLogger("deep_ssfr").addHandler(handler)
        try:
            assert cli.main(["dataset", "--config", str(config), "--scene", args.scene]) == 0
        finally:
            logging.getLogger("deep_ssfr").removeHandler(handler)
    found = re.search(r"dataset \S+: (\d+) EXR files in ([\d.]+) s \(([^)]*)\)", stream.getvalue())
    if found is None:
        raise SystemExit(f"bench_dataset_stage: the dataset stage logged no summary:\n{stream.getvalue()}")
    views, wall, steps = int(found.group(1)), float(found.group(2)), found.group(3)
    print(f"{args.scene}: {views} views at {args.size}x{args.size} ({args.frames} frames) on {choose_device()}")
    print(f"  dataset stage     {views / wall:8.2f} views/s  ({wall:.1f} s)")
    print(f"  per call          {steps}")


if __name__ == "__main__":
    main()
