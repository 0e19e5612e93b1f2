"""``make cache-ls`` / ``make clean-cache``: list or delete stage cache entries."""

from __future__ import annotations

import argparse
import shutil
import sys

from pipeline.cache import list_entries
from pipeline.config import load
from stages.common import stage_main


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def main(argv: list[str] | None = None) -> None:
    """List or clean the cache named by the config's ``data_dir``."""
    parser = argparse.ArgumentParser(prog="make cache-ls|clean-cache")
    parser.add_argument("action", choices=["ls", "clean"])
    parser.add_argument("--config", default="configs/default.yaml")
    args = parser.parse_args(argv)
    root = load(args.config).data_dir
    rows = list_entries(root)
    if args.action == "ls":
        total = 0
        for r in rows:
            state = "complete" if r["complete"] else "partial"
            print(f"{r['stage']:10s} {r['entry']:40s} {_human(r['bytes']):>10s} {r['files']:6d} files  {state}")
            total += r["bytes"]
        print(f"{len(rows)} entries, {_human(total)} in {root}")
        return
    for stage in {r["stage"] for r in rows}:
        shutil.rmtree(root / stage)
    print(f"removed {len(rows)} entries from {root}")


if __name__ == "__main__":
    sys.exit(stage_main("cache", main))
