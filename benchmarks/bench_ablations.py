"""The refiner ablations of Choi et al. and the input ablation, on the shipped recipe, as one table.

Each row is a config of ``configs/ablations/`` based on ``recipe.yaml`` (the shipped weights'
recipe, ``configs/generalize.yaml``): ``deep-ssfr evaluate`` with ``render.weights: trained`` trains
the variant if its checkpoint is missing and scores it on the held-out sequences at 512 px. Every
stage caches and resumes, so a run stopped half way (Ctrl-C, the end of a session) goes on where it
stopped when started again; ``--table`` only prints what has finished. The first row is the recipe
trained as every variant is (bfloat16 autocast on a CPU with native bf16,
``train.mixed_precision``), whose checkpoint the shipped weights were trained further from.

    .venv/bin/python benchmarks/bench_ablations.py [--only l2_content scenes_1] [--table]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages import cli  # noqa: E402

ROWS = {
    "retrained": "the recipe (ellipsoid input, normal + raw and blurred depth, L1 + normal constraint, "
                 "10 scenes, bfloat16 autocast): the shipped weights before 2026-12-07",
    "no_auxiliary": "no auxiliary depth features",
    "no_normal_loss": "no normal-constraint loss",
    "l2_content": "L2 content loss instead of L1",
    "scenes_1": "1 training scene",
    "scenes_3": "3 training scenes",
    "scenes_6": "6 training scenes (PBF only)",
    "sphere_input": "sphere-splat input instead of ellipsoids",
}
CONFIGS = ROOT / "configs" / "ablations"


def finished(name: str) -> dict | None:
    """The 512 px overall figures of the newest finished evaluation of ``name``'s config, if any."""
    entries = sorted((ROOT / "data" / "evaluate").glob(f"{name}-*/metrics.json"), key=lambda p: p.stat().st_mtime)
    if not entries:
        return None
    metrics = json.loads(entries[-1].read_text())
    return metrics.get("sizes", {}).get("512", metrics)["overall"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=list(ROWS), help="these rows (default: all)")
    parser.add_argument("--table", action="store_true", help="print the finished rows; run nothing")
    args = parser.parse_args()
    names = args.only or list(ROWS)
    if not args.table:
        for name in names:
            if cli.main(["evaluate", "--config", str(CONFIGS / f"{name}.yaml")]) != 0:
                sys.exit(f"{name}: evaluate failed")
    print("| variant | mean (deg) | median (deg) | < 10 deg | IoU | temporal (deg) | mean / narrow-range |")
    print("|---|---|---|---|---|---|---|")
    for name in names:
        o = finished(name)
        if o is None:
            print(f"| {ROWS[name]} | not run | | | | | |")
            continue
        r = o["refined"]
        print(f"| {ROWS[name]} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} | {100 * r['under_10']:.1f}% | "
              f"{r['iou']:.3f} | {r.get('temporal_deg', float('nan')):.2f} | "
              f"{r['mean_deg'] / o['nrf']['mean_deg']:.3f} |")


if __name__ == "__main__":
    main()
