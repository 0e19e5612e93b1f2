"""Shared fixtures: small configs written into a temporary folder, using the real scene files."""

from __future__ import annotations

import fnmatch
import os
import signal
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PARTICLES = ROOT.parent / "shared" / "data" / "particles"
if not PARTICLES.exists():  # CI clones sit elsewhere; the frames also ship in tests/data
    PARTICLES = ROOT / "tests" / "data"

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("DEEP_SSFR_DEVICE", "cpu")  # every test on the CPU, except those marked cuda

LONGEST_FIRST = ("test_multinode.py", "test_executor.py", "test_ddp.py", "test_concurrency.py", "test_faults.py")
"""The test files that take longest, collected first: ``make test``'s two workers take files in
collection order, and one that starts last would finish alone."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    rank = {name: k for k, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONGEST_FIRST)))  # stable: in-file order kept


@pytest.fixture(autouse=True)
def _cuda_marked_tests_use_the_gpu(request, monkeypatch):
    """``@pytest.mark.cuda`` tests run the stages on the GPU, and skip cleanly without one."""
    if request.node.get_closest_marker("cuda") is None:
        return
    from pipeline.device import cuda_available

    if not cuda_available():
        pytest.skip("needs a CUDA GPU that Warp and torch both see")
    monkeypatch.setenv("DEEP_SSFR_DEVICE", "cuda")


@pytest.fixture(scope="session")
def ss():
    """Screen-space kernel runner on the CPU, shared by the tests that splat and filter."""
    from pipeline.screen import ScreenSpace

    runner = ScreenSpace("cpu")
    yield runner
    runner.close()


@pytest.fixture(scope="session")
def launch():
    """Chunked Warp launcher on the CPU, shared by the tests that run surface kernels."""
    from pipeline.parallel import Launcher

    runner = Launcher("cpu")
    yield runner
    runner.close()


def on_writes(cmd: list[str], pattern: str, count: int, then, env: dict | None = None) -> subprocess.Popen:
    """Run a stage in a subprocess and call ``then(proc)`` right after its ``count``-th finished file
    whose path matches ``pattern`` (at once when ``count`` is 0; the cache logs each rename at DEBUG
    level: an event, not a poll); the rest of its log is drained until it ends. Returns the ended
    process, with ``proc.seen`` the number of matching files it had finished and ``proc.log`` its
    stderr lines."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), **(env or {}), "DEEP_SSFR_LOG": "DEBUG"}
    # Ctrl-C reaches the stage even when the suite runs as a background job, whose children inherit
    # an ignored SIGINT (and Python then never installs its KeyboardInterrupt handler)
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    proc.seen, proc.log, called = 0, [], False
    if count == 0:
        then(proc)
        called = True
    for line in proc.stderr:
        proc.log.append(line)
        _, marker, path = line.strip().partition(" wrote ")
        if marker and fnmatch.fnmatch(path, pattern):
            proc.seen += 1
            if not called and proc.seen >= count:
                then(proc)
                called = True
    proc.wait()
    proc.stderr.close()
    return proc


def kill_after_writes(cmd: list[str], pattern: str, count: int = 1, env: dict | None = None) -> int:
    """Run a stage in a subprocess and SIGKILL it right after its ``count``-th finished file whose
    path matches ``pattern``. Returns how many matching files it had finished (fewer when it ended
    first)."""
    return min(on_writes(cmd, pattern, count, lambda p: p.send_signal(signal.SIGKILL), env).seen, count)


def write_config(folder: Path, body: dict, scenes: dict[str, dict] | None = None) -> Path:
    """Write a pipeline config (and optional scene files) into ``folder``; returns its path."""
    folder.mkdir(parents=True, exist_ok=True)
    scene_dir = folder / "scenes"
    scene_dir.mkdir(exist_ok=True)
    for name, scene in (scenes or {}).items():
        (scene_dir / f"{name}.yaml").write_text(yaml.safe_dump(scene))
    body = {"scene_dir": "scenes", "data_dir": "data", **body}
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(body))
    return path


def copy_paper_scene(name: str) -> dict:
    """A scene file of the repository as a dict (to shrink or modify)."""
    return yaml.safe_load((ROOT / "configs" / "scenes" / f"{name}.yaml").read_text())


CAMERAS = {
    "static": {"eye": [0.2, 0.3, 1.5], "target": [0.2, 0.15, 0.2], "fov_deg": 40.0},
    "orbit": {"target": [0.2, 0.15, 0.2], "distance": 1.3, "height": 0.3, "sweep_deg": 30.0},
}


@pytest.fixture
def tiny_dam(tmp_path) -> Path:
    """A small dam break (about 1,500 particles) and its config."""
    scene = {"name": "tiny_dam", "domain_lo": [0, 0, 0], "domain_hi": [0.6, 0.5, 0.3],
             "fluid": [{"shape": "box", "lo": [0, 0, 0], "hi": [0.2, 0.3, 0.3]}],
             "obstacles": [{"shape": "sphere", "center": [0.42, 0.05, 0.15], "radius": 0.06}],
             "cameras": CAMERAS}
    return write_config(tmp_path, {"scenes": ["tiny_dam"], "seed": 3,
                                   "simulate": {"particle_radius": 0.0125, "frames": 6}},
                        {"tiny_dam": scene})
