"""Runs of one config at the same time: both succeed, neither breaks the other's files, and a forced
rebuild leaves the old entry whole until it is swapped in."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from pipeline.cache import CacheEntry, read_json
from pipeline.exr import read_exr
from pipeline.fencing import staging
from tests.conftest import ROOT, on_writes


def _render_config(tiny_dam):
    body = yaml.safe_load(tiny_dam.read_text())
    body["simulate"]["frames"] = 30  # long enough for the two runs to overlap
    body["render"] = {"width": 64, "height": 64, "method": "nrf", "comparison": True}
    tiny_dam.write_text(yaml.safe_dump(body))
    return [sys.executable, "-m", "stages.cli", "render", "--config", str(tiny_dam)]


def _whole(folder) -> None:
    """A complete entry: its manifest's files all there with their recorded sizes, no temporaries."""
    manifest = read_json(folder / "manifest.json")
    for name, check in manifest["checks"].items():
        assert (folder / name).stat().st_size == check["size"], name
    staged = staging(folder.resolve())
    assert not [p for p in [*folder.rglob("*"), *staged.rglob("*")] if ".tmp-" in p.name]


@pytest.mark.slow
@pytest.mark.parametrize("offset, force", [(0, False), (3, False), (3, True)])
def test_two_renders_of_one_config_at_once_both_succeed(tiny_dam, offset, force):
    """The second run starts with the first (offset 0) or after it wrote ``offset`` files; with
    ``force`` it rebuilds the entry the first is still writing."""
    cmd = _render_config(tiny_dam)
    second: list[subprocess.Popen] = []

    def start_second(_):
        second.append(subprocess.Popen([*cmd, *(["--force"] if force else [])], cwd=ROOT, text=True,
                                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                       env={**os.environ, "PYTHONPATH": str(ROOT)}))

    first = on_writes(cmd, "*/frame_*", offset, start_second)
    _, err = second[0].communicate(timeout=300)
    assert first.returncode == 0
    assert second[0].returncode == 0, err
    for stage in ("simulate", "render"):
        (entry,) = (tiny_dam.parent / "data" / stage).iterdir()
        _whole(entry)
    (entry,) = (tiny_dam.parent / "data" / "render").iterdir()
    exrs = sorted((entry / "frames").glob("*.exr"))
    assert len(exrs) == 30 and not any(np.isnan(a).any() for exr in exrs for a in read_exr(exr).values())


@pytest.mark.slow
def test_force_builds_beside_the_old_entry_and_swaps_it_in(tiny_dam):
    cmd = [sys.executable, "-m", "stages.cli", "simulate", "--config", str(tiny_dam)]
    assert subprocess.run(cmd, cwd=ROOT, capture_output=True).returncode == 0
    (entry,) = (tiny_dam.parent / "data" / "simulate").iterdir()
    before = {p.name: p.read_bytes() for p in entry.glob("frame_*.npz")}
    seen = {}

    def look(_):  # the forced run has written its first frame: the old entry is still whole
        _whole(entry)
        seen["rebuilds"] = [p.name for p in entry.parent.iterdir() if ".new-" in p.name]

    forced = on_writes([*cmd, "--force"], "*/frame_0001.npz", 1, look)
    assert forced.returncode == 0 and forced.seen >= 1
    assert seen["rebuilds"] == [next(p for p in seen["rebuilds"])] and seen["rebuilds"][0].startswith(entry.name)
    assert [p.name for p in entry.parent.iterdir()] == [entry.name], "the rebuild swapped in, nothing left beside"
    _whole(entry)
    assert {p.name: p.read_bytes() for p in entry.glob("frame_*.npz")} == before  # same seed, same frames


def test_a_second_claim_waits_for_the_first_to_finish(tmp_path):
    import threading

    a = CacheEntry(tmp_path, "render", "scene", "k", {})
    b = CacheEntry(tmp_path, "render", "scene", "k", {})
    assert a.begin()
    (a.dir / "out.txt").write_text("done")
    result = {}
    # another process would block on the lock; in one process a second lock object blocks alike
    waiter = threading.Thread(target=lambda: result.setdefault("claimed", b.begin()))
    waiter.start()
    waiter.join(0.5)
    assert waiter.is_alive(), "the second claim must wait while the first holds the entry"
    a.finish(["out.txt"])
    waiter.join(10)
    assert result == {"claimed": False}, "after the first finished, the entry is complete: nothing to do"
