"""Particle import: other simulators' real frames, round trips, clear errors on damaged files."""

from __future__ import annotations

import gzip

import meshio
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


@pytest.mark.parametrize("ext", ["ply", "vtk"])
def test_radii_round_trip(tmp_path, ext):
    rng = np.random.default_rng(2)
    x = rng.normal(size=(50, 3)).astype(np.float32)
    r = rng.uniform(0.01, 0.1, 50).astype(np.float32)
    write_particles(tmp_path / f"f.{ext}", ParticleFrame(x, radii=r))
    back = read_particles(tmp_path / f"f.{ext}")
    np.testing.assert_array_equal(back.radii, r)
    assert back.velocities is None


@pytest.mark.parametrize("velocity", ["velocity", "v", "vel", "velocities", "Velocity"])
@pytest.mark.parametrize("radius", ["pscale", "radius", "radii"])
@pytest.mark.parametrize("ext", ["vtu", "vtk"])
def test_point_attributes_are_picked_by_name(tmp_path, velocity, radius, ext):
    rng = np.random.default_rng(3)
    x, v = rng.normal(size=(20, 3)), rng.normal(size=(20, 3))
    r = rng.uniform(0.01, 0.1, 20)
    mesh = meshio.Mesh(x, [("vertex", np.arange(20)[:, None])],
                       point_data={"id": np.arange(20), "density": r * 1000, velocity: v, radius: r})
    meshio.write(tmp_path / f"f.{ext}", mesh)
    frame = read_particles(tmp_path / f"f.{ext}")
    assert frame.velocities.dtype == np.float32 and frame.radii.dtype == np.float32
    np.testing.assert_allclose(frame.velocities, v, atol=1e-6)
    np.testing.assert_allclose(frame.radii, r, atol=1e-7)


def test_attributes_of_the_wrong_shape_are_not_picked(tmp_path):
    x = np.random.default_rng(4).normal(size=(20, 3))
    mesh = meshio.Mesh(x, [("vertex", np.arange(20)[:, None])], point_data={"v": np.ones(20), "radius": x})
    meshio.write(tmp_path / "f.vtu", mesh)
    frame = read_particles(tmp_path / "f.vtu")
    assert frame.velocities is None and frame.radii is None


def test_bgeo_plain_and_gzip_and_bgeo_gz_name_read_the_same(tmp_path):
    src = PARTICLES / "dam_break_frame_9_6859_particles.bgeo"
    (tmp_path / "plain.bgeo").write_bytes(gzip.decompress(src.read_bytes()))
    (tmp_path / "named.bgeo.gz").write_bytes(src.read_bytes())
    reference = read_particles(src)
    assert reference.velocities.shape == (6859, 3)
    for name in ("plain.bgeo", "named.bgeo.gz"):
        frame = read_particles(tmp_path / name)
        np.testing.assert_array_equal(frame.positions, reference.positions)
        np.testing.assert_array_equal(frame.velocities, reference.velocities)


def test_ply_with_crlf_header(tmp_path):
    x = np.random.default_rng(5).normal(size=(30, 3)).astype(np.float32)
    write_particles(tmp_path / "lf.ply", ParticleFrame(x))
    raw = (tmp_path / "lf.ply").read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    (tmp_path / "crlf.ply").write_bytes(raw[:end].replace(b"\n", b"\r\n") + raw[end:])
    np.testing.assert_array_equal(read_particles(tmp_path / "crlf.ply").positions, x)


@pytest.mark.parametrize("body", [b"ply\nformat ascii 1.0\nelement vertex 2\n", b"ply\r\nformat ascii 1.0\r\n"])
def test_ply_cut_in_its_header_is_reported(tmp_path, body):
    (tmp_path / "cut.ply").write_bytes(body)
    with pytest.raises(ParticleFormatError, match=r"cut\.ply: not a PLY file or header incomplete"):
        read_particles(tmp_path / "cut.ply")


@pytest.mark.parametrize("count", [b"-3", b"many", b"2 7"])
def test_ply_with_a_vertex_count_that_is_no_count_is_reported(tmp_path, count):
    body = b"ply\nformat binary_little_endian 1.0\nelement vertex " + count + \
        b"\nproperty float x\nproperty float y\nproperty float z\nend_header\n" + bytes(36)
    (tmp_path / "odd.ply").write_bytes(body)
    with pytest.raises(ParticleFormatError, match=r"odd\.ply: element line needs a name and a count of 0 or more"):
        read_particles(tmp_path / "odd.ply")


def test_vtu_cut_or_garbled_is_reported(tmp_path):
    x = np.random.default_rng(6).normal(size=(20, 3))
    meshio.write(tmp_path / "f.vtu", meshio.Mesh(x, [("vertex", np.arange(20)[:, None])]))
    raw = (tmp_path / "f.vtu").read_bytes()
    (tmp_path / "cut.vtu").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ParticleFormatError, match=r"cut\.vtu: truncated"):
        read_particles(tmp_path / "cut.vtu")
    (tmp_path / "garbled.vtu").write_bytes(b"<VTKFile type='PolyData'>\n</VTKFile>\n")
    with pytest.raises(ParticleFormatError, match=r"garbled\.vtu: not a readable VTU file"):
        read_particles(tmp_path / "garbled.vtu")


def test_z_up_becomes_y_up_by_a_rotation(tmp_path):
    rng = np.random.default_rng(8)
    x = rng.normal(size=(40, 3)).astype(np.float32)
    v = rng.normal(size=(40, 3)).astype(np.float32)
    r = rng.uniform(0.01, 0.1, 40).astype(np.float32)
    x[0], v[0] = (0, 0, 1), (0, 1, 0)  # Z-up "up" becomes +y; +y ("forward") becomes -z
    write_particles(tmp_path / "f.ply", ParticleFrame(x, v, r))
    frame = read_particles(tmp_path / "f.ply", up="z")
    np.testing.assert_array_equal(frame.positions, np.stack([x[:, 0], x[:, 2], -x[:, 1]], axis=1))
    np.testing.assert_array_equal(frame.velocities, np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1))
    np.testing.assert_array_equal(frame.positions[0], (0, 1, 0))
    np.testing.assert_array_equal(frame.velocities[0], (0, 0, -1))
    np.testing.assert_array_equal(frame.radii, r)
    assert frame.positions.dtype == np.float32
    # a rotation: lengths and handedness kept (the triple product of three particles keeps its sign)
    np.testing.assert_allclose(np.linalg.norm(frame.positions, axis=1), np.linalg.norm(x, axis=1), rtol=1e-6)
    assert np.sign(np.linalg.det(frame.positions[1:4])) == np.sign(np.linalg.det(x[1:4]))
    np.testing.assert_array_equal(read_particles(tmp_path / "f.ply", up="y").positions, x)
    with pytest.raises(ValueError, match=r"up must be one of y, z, got 'x'"):
        read_particles(tmp_path / "f.ply", up="x")


@pytest.mark.parametrize("name, count", SHARED[:2])
def test_shared_vtk_frames_carry_velocities(name, count):
    frame = read_particles(PARTICLES / name)
    assert frame.velocities.shape == (count, 3) and np.abs(frame.velocities).max() > 0
