"""Shared fixtures: small configs written into a temporary folder, using the real scene files."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PARTICLES = ROOT.parent / "shared" / "data" / "particles"
if not PARTICLES.exists():  # CI clones sit elsewhere; the frames also ship in tests/data
    PARTICLES = ROOT / "tests" / "data"

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("DEEP_SSFR_DEVICE", "cpu")


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
