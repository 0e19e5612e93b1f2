"""The deep-ssfr command line: --help everywhere, and a user's own sequence rendered in one command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pipeline.exr import read_exr
from pipeline.media import count_video_frames
from pipeline.particles import ParticleFrame, write_particles
from stages import cli
from tests.test_faults import _one_line

COMMANDS = ["simulate", "dataset", "train", "ship", "render", "evaluate", "export", "demo", "cache"]


@pytest.mark.parametrize("command", [[], *[[c] for c in COMMANDS]])
def test_every_command_has_help(command, capsys):
    assert cli.main([*command, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("Usage: deep-ssfr") and (not command or "--help" in out)


def _drop(folder, fmt: str = "ply", frames=range(1, 6)) -> None:
    """A 1,000-particle block flying in +x at 0.6 m/s, written as unpadded frames drop_1, drop_2, ..."""
    ax = np.arange(-0.1, 0.1, 0.02)
    block = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    for f in frames:
        x = block + (0.02 * f, 0.1, 0.0) + rng.normal(scale=0.002, size=block.shape)
        v = np.tile((0.6, 0.0, 0.0), (len(x), 1))
        write_particles(folder / f"drop_{f}.{fmt}", ParticleFrame(x.astype(np.float32), v.astype(np.float32)))


@pytest.mark.slow
def test_render_a_users_sequence_in_one_command(tmp_path, capsys):
    _drop(tmp_path, frames=[1, 2, 3, 4, 5, 10, 11])  # 10 and 11 sort before 2 by name
    out = tmp_path / "out"
    argv = ["render", str(tmp_path / "drop_{}.ply"), "--radius", "0.01", "--out", str(out), "--size", "64x64",
            "--frames", ":5", "--fps", "24"]
    assert cli.main(argv) == 0
    exrs = sorted(p.name for p in out.glob("frame_*.exr"))
    assert exrs == [f"frame_{i:04d}.exr" for i in range(1, 6)]
    assert count_video_frames(out / "drop_refined.mp4") == 5
    assert count_video_frames(out / "drop_comparison.mp4") == 5
    # frames in number order: the block's centre moves +x from frame to frame
    centres = []
    for name in exrs:
        ch = read_exr(out / name)
        cols = np.nonzero(ch["A"] > 0)[1]
        assert cols.size > 20
        centres.append(cols.mean())
    assert np.all(np.diff(centres) > 0), centres
    cameras = json.loads((out / "camera.json").read_text())
    assert [f["frame"] for f in cameras["frames"]] == [1, 2, 3, 4, 5]

    # the exported camera gives the same frames back
    again = tmp_path / "again"
    assert cli.main([*argv[:5], str(again), "--size", "64x64", "--frames", ":5", "--camera",
                     str(out / "camera.json")]) == 0
    for name in exrs:
        np.testing.assert_allclose(read_exr(again / name)["A"], read_exr(out / name)["A"])

    # a second run finds everything cached: nothing rendered again
    before = {p: p.stat().st_mtime_ns for p in (out / ".cache" / "render").rglob("*.exr")}
    assert cli.main(argv) == 0
    assert before == {p: p.stat().st_mtime_ns for p in (out / ".cache" / "render").rglob("*.exr")}


def test_bad_requests_are_one_line_each(tmp_path, capsys):
    _drop(tmp_path, frames=[1, 2])
    pattern, o = str(tmp_path / "drop_{}.ply"), str(tmp_path / "o")
    cases = [
        (["render", str(tmp_path / "none_{}.ply"), "--radius", "0.01", "--out", o], 1, "no file matches"),
        (["render", pattern, "--radius", "0.01"], 2, "--out: is required"),
        (["render", pattern, "--radius", "0.01", "--out", o, "--size", "64"], 2, "--size: must be WIDTHxHEIGHT"),
        (["render", pattern, "--out", o], 2, "--radius: is required: drop_1.ply has no pscale or radius"),
        (["render", pattern, "--radius", "0.01", "--out", o, "--fps", "0"], 2, "--fps: must be > 0"),
        (["render", pattern, "--radius", "0.01", "--out", o, "--camera", "nope.json"], 2, "nope.json does not"),
    ]
    assert cli.main(["render", pattern, "--radius", "0.01", "--out", o, "--up", "x"]) == 2  # a usage error
    assert "'x' is not one of 'y', 'z'" in capsys.readouterr().err
    for argv, code, words in cases:
        capsys.readouterr()
        assert cli.main(argv) == code, argv
        line = _one_line(capsys.readouterr().err)
        assert words in line, line
    (tmp_path / "drop_3.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\n")
    assert cli.main(["render", pattern, "--radius", "0.01", "--out", str(tmp_path / "o")]) == 1
    assert "drop_3.ply" in _one_line(capsys.readouterr().err)
