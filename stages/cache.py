"""``deep-ssfr cache ls|clean`` (``make cache-ls`` / ``make clean-cache``): list or delete cache entries."""

from __future__ import annotations

import shutil

from pipeline.cache import list_entries
from pipeline.config_files import load
from stages.common import StageOptions


def _human(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def main(opts: StageOptions, action: str) -> None:
    """List (``ls``) or delete (``clean``) the cache entries under the config's ``data_dir``."""
    root = load(opts.config).data_dir
    rows = list_entries(root)
    if action == "ls":
        total = 0
        for r in rows:
            state = "complete" if r["complete"] else "partial"
            print(f"{r['stage']:10s} {r['entry']:40s} {_human(r['bytes']):>10s} {r['files']:6d} files  {state}")
            total += r["bytes"]
        print(f"{len(rows)} entries, {_human(total)} in {root}")
        return
    for stage in {r["stage"] for r in rows}:
        shutil.rmtree(root / stage)
    shutil.rmtree(root / ".staging", ignore_errors=True)  # temporaries of writes cut short, if any
    print(f"removed {len(rows)} entries from {root}")
