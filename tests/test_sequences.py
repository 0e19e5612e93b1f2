"""Particle sequences: every readable format written as a short sequence with unpadded numbers and
varying particle counts, read back in frame order; patterns, gaps, frame ranges and clear errors."""

from __future__ import annotations

import gzip
import logging
import struct
from pathlib import Path

import meshio
import numpy as np
import pytest

from pipeline.particles import ParticleFormatError, ParticleFrame, read_particles, write_particles
from pipeline.particles.sequence import ParticleSequenceError, find_sequence, parse_frame_range

NUMBERS = (8, 9, 10, 11)  # unpadded: by name f_10 and f_11 would sort before f_8


def _frames(numbers=NUMBERS) -> dict[int, ParticleFrame]:
    """One frame per number, each with its own particle count, velocities and radii."""
    rng = np.random.default_rng(7)
    frames = {}
    for k, number in enumerate(numbers):
        n = 5 + 3 * k
        frames[number] = ParticleFrame(rng.normal(size=(n, 3)).astype(np.float32),
                                       rng.normal(size=(n, 3)).astype(np.float32),
                                       rng.uniform(0.01, 0.05, n).astype(np.float32))
    return frames


def _mesh(frame: ParticleFrame, velocity: str = "velocity", radius: str = "pscale"):
    """A meshio point cloud (vertex cells) with named velocity and radius point data."""
    n = len(frame.positions)
    return meshio.Mesh(frame.positions, [("vertex", np.arange(n)[:, None])],
                       point_data={velocity: frame.velocities, radius: frame.radii})


def _ply_ascii(path: Path, frame: ParticleFrame, newline: str = "\n") -> None:
    """ASCII PLY with x y z vx vy vz pscale, lines ending in ``newline``."""
    names = ["x", "y", "z", "vx", "vy", "vz", "pscale"]
    header = ["ply", "format ascii 1.0", "comment written by a test", f"element vertex {len(frame.positions)}"]
    header += [f"property float {c}" for c in names] + ["end_header"]
    table = np.concatenate([frame.positions, frame.velocities, frame.radii[:, None]], axis=1)
    rows = [" ".join(repr(float(v)) for v in row) for row in table]
    path.write_bytes(newline.join(header + rows + [""]).encode())


def _ply_binary_crlf(path: Path, frame: ParticleFrame) -> None:
    """The binary PLY that ``write_particles`` writes, with CRLF header lines."""
    write_particles(path, frame, "ply")
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    path.write_bytes(raw[:end].replace(b"\n", b"\r\n") + raw[end:])


def bgeo_bytes(frame: ParticleFrame, compress: bool) -> bytes:
    """A BGEO v5 point file as Partio writes it, with a ``v`` vector and a ``pscale`` float attribute."""
    attributes = [("v", 3, 5), ("pscale", 1, 0)]  # name, components, Houdini type (5 vector, 0 float)
    n = len(frame.positions)
    out = b"BgeoV" + struct.pack(">9i", 5, n, 0, 0, 0, len(attributes), 0, 0, 0)
    for name, size, htype in attributes:
        out += struct.pack(">H", len(name)) + name.encode() + struct.pack(">Hi", size, htype) + bytes(4 * size)
    rows = np.concatenate([frame.positions, np.ones((n, 1)), frame.velocities, frame.radii[:, None]], axis=1)
    out += rows.astype(">f4").tobytes() + b"\x00\xff"
    return gzip.compress(out) if compress else out


# name: (extension, writer(path, frame), carries velocities, carries radii)
WRITERS = {
    "vtk-4.2-ascii": (".vtk", lambda p, f: meshio.vtk.write(p, _mesh(f), fmt_version="4.2", binary=False), 1, 1),
    "vtk-4.2-binary": (".vtk", lambda p, f: meshio.vtk.write(p, _mesh(f), fmt_version="4.2", binary=True), 1, 1),
    "vtk-5.1-ascii": (".vtk", lambda p, f: meshio.vtk.write(p, _mesh(f), fmt_version="5.1", binary=False), 1, 1),
    "vtk-5.1-binary": (".vtk", lambda p, f: meshio.vtk.write(p, _mesh(f), fmt_version="5.1", binary=True), 1, 1),
    "vtk-own": (".vtk", lambda p, f: write_particles(p, f), 1, 1),
    "vtu-ascii": (".vtu", lambda p, f: meshio.vtu.write(p, _mesh(f, radius="radius"), binary=False), 1, 1),
    "vtu-binary-zlib": (".vtu", lambda p, f: meshio.vtu.write(p, _mesh(f, radius="radius")), 1, 1),
    "ply-binary": (".ply", lambda p, f: write_particles(p, f), 1, 1),
    "ply-binary-crlf": (".ply", _ply_binary_crlf, 1, 1),
    "ply-ascii": (".ply", _ply_ascii, 1, 1),
    "ply-ascii-crlf": (".ply", lambda p, f: _ply_ascii(p, f, "\r\n"), 1, 1),
    "bgeo-plain": (".bgeo", lambda p, f: p.write_bytes(bgeo_bytes(f, compress=False)), 1, 1),
    "bgeo-gzip": (".bgeo", lambda p, f: p.write_bytes(bgeo_bytes(f, compress=True)), 1, 1),
    "bgeo.gz": (".bgeo.gz", lambda p, f: p.write_bytes(bgeo_bytes(f, compress=True)), 1, 1),
    "xyz": (".xyz", lambda p, f: write_particles(p, f), 0, 0),
}


def write_sequence(folder: Path, kind: str, numbers=NUMBERS, name: str = "f_{}") -> dict[int, ParticleFrame]:
    """Write one frame per number as ``folder/name`` (``{}`` -> number) in the format ``kind``."""
    ext, writer, _, _ = WRITERS[kind]
    folder.mkdir(parents=True, exist_ok=True)
    frames = _frames(numbers)
    for number in numbers:
        writer(folder / (name.format(number) + ext), frames[number])
    return frames


@pytest.mark.parametrize("kind", list(WRITERS))
def test_each_format_reads_back_in_frame_order(tmp_path, kind):
    ext, _, has_velocities, has_radii = WRITERS[kind]
    frames = write_sequence(tmp_path, kind)
    for pattern in (f"f_{{}}{ext}", f"f_*{ext}"):
        seq = find_sequence(tmp_path / pattern)
        assert seq.numbers == NUMBERS and seq.missing == () and seq.step == 1
        assert [p.name for p in seq.paths] == [f"f_{n}{ext}" for n in NUMBERS]
    for number, written in frames.items():
        frame = seq.read(number)
        assert frame.positions.dtype == np.float32 and frame.positions.shape == written.positions.shape
        np.testing.assert_allclose(frame.positions, written.positions, rtol=0, atol=1e-6)
        if has_velocities:
            np.testing.assert_allclose(frame.velocities, written.velocities, rtol=0, atol=1e-6)
        if has_radii:
            np.testing.assert_allclose(frame.radii, written.radii, rtol=0, atol=1e-7)


def test_placeholder_matches_zero_padded_and_ignores_other_names(tmp_path):
    write_sequence(tmp_path, "xyz", name="fluid_{:04d}")
    (tmp_path / "fluid_0009_backup.xyz").write_bytes(bytes(12))
    (tmp_path / "fluid_.xyz").write_bytes(bytes(12))
    seq = find_sequence(str(tmp_path / "fluid_{}.xyz"))
    assert seq.numbers == NUMBERS and seq.paths[0].name == "fluid_0008.xyz"


def test_same_number_twice_is_an_error(tmp_path):
    write_sequence(tmp_path, "xyz", numbers=(1, 2))
    write_particles(tmp_path / "f_01.xyz", ParticleFrame(np.zeros((1, 3), np.float32)))
    with pytest.raises(ParticleSequenceError, match=r"frame 1 matches two files"):
        find_sequence(tmp_path / "f_{}.xyz")


def test_glob_number_is_the_whole_digit_run_around_the_wildcard(tmp_path):
    write_sequence(tmp_path, "xyz", name="run2_f_{}")
    assert find_sequence(tmp_path / "run2_f_1*.xyz").numbers == (10, 11)
    assert find_sequence(tmp_path / "run2_f_??.xyz").numbers == (10, 11)
    assert find_sequence(tmp_path / "run2_f_[89].xyz").numbers == (8, 9)
    write_sequence(tmp_path / "other", "xyz", numbers=(8,), name="run_f_{}")
    with pytest.raises(ParticleSequenceError, match=r"run_f_8\.xyz: the file name's wildcards match no digits"):
        find_sequence(tmp_path / "other" / "*_f_8.xyz")


def test_plain_path_is_frame_one_whatever_digits_its_name_holds(tmp_path):
    """A file's name may hold a particle count or a version (octo_880k.vtk): only a pattern's {} or
    wildcards say where a frame number stands."""
    write_sequence(tmp_path, "xyz", numbers=(9,))
    (tmp_path / "f_9.xyz").rename(tmp_path / "octo_880k.xyz")
    seq = find_sequence(tmp_path / "octo_880k.xyz")
    assert seq.numbers == (1,) and len(seq) == 1 and seq.missing == ()


def test_a_folder_as_the_pattern_says_how_to_name_its_files(tmp_path):
    with pytest.raises(ParticleSequenceError, match=r"is a folder: give its files, e\.g\. .*\*\.vtk"):
        find_sequence(tmp_path)


def test_gaps_are_reported_and_logged_compactly(tmp_path, caplog):
    write_sequence(tmp_path, "xyz", numbers=(1, 2, 5, 6, 7, 10, 14))
    with caplog.at_level(logging.WARNING, logger="pipeline.particles.sequence"):
        seq = find_sequence(tmp_path / "f_{}.xyz")
    assert seq.missing == (3, 4, 8, 9, 11, 12, 13)
    assert "7 frame(s) missing between 1 and 14: 3-4, 8-9, 11-13" in caplog.text
    assert find_sequence(tmp_path / "f_{}.xyz", start=5, end=7).missing == ()


def test_a_constant_step_is_not_a_gap(tmp_path, caplog):
    write_sequence(tmp_path, "xyz", numbers=(0, 10, 20, 40))
    with caplog.at_level(logging.WARNING, logger="pipeline.particles.sequence"):
        seq = find_sequence(tmp_path / "f_*.xyz")
    assert seq.step == 10 and seq.missing == (30,) and "missing between 0 and 40: 30" in caplog.text


def test_frame_range_selects_by_number_inclusive(tmp_path):
    write_sequence(tmp_path, "xyz")
    seq = find_sequence(tmp_path / "f_{}.xyz")
    assert seq.select(9, 10).numbers == (9, 10)
    assert seq.select(None, 9).numbers == (8, 9) and seq.select(10).numbers == (10, 11)
    assert seq.select().numbers == NUMBERS
    assert find_sequence(tmp_path / "f_{}.xyz", start=0, end=8).numbers == (8,)
    with pytest.raises(ParticleSequenceError, match=r"f_\{\}\.xyz: frame range 20:30 selects no frame"):
        seq.select(20, 30)
    with pytest.raises(ParticleSequenceError, match=r"no frame 3"):
        seq.read(3)


@pytest.mark.parametrize("text, expected", [("10:20", (10, 20)), ("10:", (10, None)), (":20", (None, 20)),
                                            ("7", (7, 7)), (" 3 : 4 ", (3, 4)), ("", (None, None)),
                                            (None, (None, None)), (":", (None, None))])
def test_parse_frame_range(text, expected):
    assert parse_frame_range(text) == expected


@pytest.mark.parametrize("text", ["a:b", "5:2", "1:2:3"])
def test_parse_frame_range_rejects_nonsense(text):
    with pytest.raises(ValueError, match="frame range"):
        parse_frame_range(text)


def test_no_match_names_the_pattern(tmp_path):
    with pytest.raises(ParticleSequenceError, match=r"fluid_\{\}\.vtk: no file matches the pattern$"):
        find_sequence(tmp_path / "fluid_{}.vtk")
    with pytest.raises(ParticleSequenceError, match=r"folder .*nowhere does not exist"):
        find_sequence(tmp_path / "nowhere" / "fluid_*.vtk")


def test_mixed_formats_are_an_error(tmp_path):
    write_sequence(tmp_path, "xyz", numbers=(8, 9))
    write_sequence(tmp_path, "ply-binary", numbers=(9, 10))  # frame 9 in both formats
    with pytest.raises(ParticleSequenceError, match=r"several formats: 2 \.ply \(e\.g\. f_9\.ply\), 2 \.xyz"):
        find_sequence(tmp_path / "f_*")


def test_unsupported_format_and_misplaced_placeholder(tmp_path):
    (tmp_path / "f_1.txt").write_text("0 0 0")
    with pytest.raises(ParticleSequenceError, match=r"matches \.txt files, not a particle format"):
        find_sequence(tmp_path / "f_{}.txt")
    with pytest.raises(ParticleSequenceError, match=r"one \{\} for the frame number, in the file name"):
        find_sequence(tmp_path / "f_{}_{}.vtk")
    with pytest.raises(ParticleSequenceError, match=r"one \{\}"):
        find_sequence(tmp_path / "run_{}" / "f_1.vtk")


def test_corrupt_frame_names_its_file(tmp_path):
    write_sequence(tmp_path, "vtk-own")
    bad = tmp_path / "f_10.vtk"
    bad.write_bytes(bad.read_bytes()[:200])
    seq = find_sequence(tmp_path / "f_{}.vtk")  # finding reads no frame
    seq.read(9)
    with pytest.raises(ParticleFormatError, match=r"f_10\.vtk: truncated"):
        seq.read(10)


@pytest.mark.parametrize("kind", ["vtk-own", "vtu-binary-zlib", "ply-ascii", "bgeo-plain", "xyz"])
def test_empty_frame_is_an_error(tmp_path, kind):
    ext, writer, _, _ = WRITERS[kind]
    write_sequence(tmp_path, kind, numbers=(8,))
    (tmp_path / f"f_9{ext}").write_bytes(b"")
    empty = np.zeros((0, 3), np.float32)
    writer(tmp_path / f"f_10{ext}", ParticleFrame(empty, empty, np.zeros(0, np.float32)))  # a header, no points
    seq = find_sequence(tmp_path / f"f_{{}}{ext}")
    assert seq.read(8).positions.shape == (5, 3)
    for number in (9, 10):
        with pytest.raises(ParticleFormatError, match=rf"f_{number}{ext}: the file holds no particles"):
            seq.read(number)


def test_read_converts_z_up(tmp_path):
    frames = write_sequence(tmp_path, "bgeo-gzip")
    frame = find_sequence(tmp_path / "f_{}.bgeo").read(8, up="z")
    x, y, z = frames[8].positions.T
    np.testing.assert_array_equal(frame.positions, np.stack([x, z, -y], axis=1))
    np.testing.assert_array_equal(frame.radii, frames[8].radii)


def test_the_automatic_cameras_box_is_the_fluids_bulk_not_its_stray_droplets(tmp_path):
    """A few droplets flung far from the fluid would shrink it to a corner of an automatic camera's
    picture; the bulk box leaves up to 0.2% of a frame's particles out on each side of each axis."""
    from pipeline.frames import frame_name, save_frame, sequence_bounds
    from stages.sequence import STRAY_SHARE

    ax = np.arange(0.0, 0.5, 0.02)
    block = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)  # 15,625 particles
    for i, shift in enumerate((0.0, 0.1), start=1):
        droplets = np.array([[30.0, 2.0, 0.0], [-9.0, 0.0, 4.0], [0.2, 40.0, 0.2]]) * (i if shift else 1)
        save_frame(tmp_path / frame_name(i), np.concatenate([block + shift, droplets]).astype(np.float32), None)
    lo, hi = sequence_bounds(tmp_path, 2, stray=STRAY_SHARE)
    np.testing.assert_allclose(lo, 0.0, atol=1e-6)
    np.testing.assert_allclose(hi, 0.48 + 0.1, atol=1e-6)  # both frames' blocks, no droplet
    lo, hi = sequence_bounds(tmp_path, 2)
    assert hi[0] == 60.0 and lo[0] == -18.0 and hi[1] == 80.0  # every particle


def test_an_import_takes_the_sequences_box_as_it_reads_resumed_or_not(tmp_path):
    """The box the automatic camera frames comes from the files as they are imported, equal to
    ``sequence_bounds`` over the cached copies, also when a stopped import left some copies."""
    from pipeline.frames import frame_name, read_sequence_info, sequence_bounds
    from pipeline.sim.runner import import_sequence
    from pipeline.sph import IMPORT_PADDING_RADII
    from stages.sequence import STRAY_SHARE

    rng = np.random.default_rng(1)
    files = []
    for i in range(1, 4):
        x = rng.normal(0.1 * i, 0.2, (3000, 3)).astype(np.float32)
        files.append(tmp_path / f"f_{i}.ply")
        write_particles(files[-1], ParticleFrame(x, None))
    cache = tmp_path / "cache"
    for stopped in (False, True):
        if stopped:  # the second frame's copy is gone, the others kept
            (cache / frame_name(2)).unlink()
        extra = import_sequence(cache, "f", files, 0.01, 30.0, support=0.04, stray=STRAY_SHARE)
        lo, hi = sequence_bounds(cache, 3, stray=STRAY_SHARE)
        np.testing.assert_array_equal(extra["bounds"], [lo, hi])
        # the domain: the first frame's box grown by the import's padding, read once
        info, first = read_sequence_info(cache), read_particles(files[0]).positions
        pad = IMPORT_PADDING_RADII * 0.01
        assert info.domain_lo == tuple(float(v - pad) for v in first.min(0))
        assert info.domain_hi == tuple(float(v + pad) for v in first.max(0))
