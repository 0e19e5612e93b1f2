"""Particle import: other simulators' real frames, round trips, clear errors on damaged files."""

from __future__ import annotations

import gzip

import numpy as np
import pytest

from pipeline.particles import ParticleFormatError, ParticleFrame, read_particles, write_particles
from tests.conftest import PARTICLES

SHARED = [
    ("bunny_frame_14_7705_particles.vtk", 7706),
    ("double_dam_break_frame_01_4732_particles.vtk", 4732),
    ("dam_break_frame_9_6859_particles.bgeo", 6859),
]


@pytest.mark.parametrize("name, count", SHARED)
def test_shared_frames_load_with_sane_bounds(name, count):
    frame = read_particles(PARTICLES / name)
    x = frame.positions
    assert x.shape == (count, 3) and x.dtype == np.float32
    extent = x.max(0) - x.min(0)
    # SPlisHSPlasH scenes are metres-sized: every axis spans more than 10 particle radii
    # (r = 0.025) and less than 10 m, and particles are not stacked on each other.
    assert np.all(extent > 0.25) and np.all(extent < 10.0)
    assert np.unique(np.round(x, 4), axis=0).shape[0] > 0.99 * count
    if frame.velocities is not None:
        assert frame.velocities.shape == (count, 3) and np.isfinite(frame.velocities).all()


@pytest.mark.parametrize("name, count", SHARED)
def test_truncated_copy_names_the_file(tmp_path, name, count):
    src = PARTICLES / name
    raw = src.read_bytes()
    if name.endswith(".bgeo"):
        cut = gzip.compress(gzip.decompress(raw)[: 41 + 200 + 32 * (count // 2)])
    else:
        cut = raw[: len(raw) // 3]
    bad = tmp_path / name
    bad.write_bytes(cut)
    with pytest.raises(ParticleFormatError) as err:
        read_particles(bad)
    assert str(bad) in str(err.value) and "truncated" in str(err.value)


def test_bgeo_cut_gzip_stream_is_reported(tmp_path):
    raw = (PARTICLES / "dam_break_frame_9_6859_particles.bgeo").read_bytes()
    bad = tmp_path / "cut.bgeo"
    bad.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ParticleFormatError, match="cut.bgeo"):
        read_particles(bad)


@pytest.mark.parametrize("ext", ["ply", "vtk", "xyz"])
def test_write_read_round_trip(tmp_path, ext):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(500, 3)).astype(np.float32)
    v = rng.normal(size=(500, 3)).astype(np.float32)
    write_particles(tmp_path / f"f.{ext}", ParticleFrame(x, v))
    back = read_particles(tmp_path / f"f.{ext}")
    np.testing.assert_array_equal(back.positions, x)
    if ext != "xyz":
        np.testing.assert_array_equal(back.velocities, v)


def test_unknown_extension_is_rejected(tmp_path):
    (tmp_path / "a.obj").write_text("v 0 0 0")
    with pytest.raises(ParticleFormatError, match="unsupported particle format"):
        read_particles(tmp_path / "a.obj")
