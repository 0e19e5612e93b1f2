"""The deep-ssfr command line: --help everywhere, and a user's own sequence rendered in one command."""

from __future__ import annotations

import json
import os
import subprocess
import sys

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


def test_the_runtime_environment_reaches_the_libraries_as_they_load():
    """The console script's environment (``stages.cli.RUNTIME_ENV``) is set before numpy loads:
    numpy then asks for no huge pages. A user's own setting wins."""
    probe = ("import stages.cli, os; from numpy._core.multiarray import _get_madvise_hugepage as g; "
             "print(g(), os.environ['OMP_WAIT_POLICY'])")
    env = {k: v for k, v in os.environ.items() if k not in cli.RUNTIME_ENV}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "PASSIVE"]
    out = subprocess.run([sys.executable, "-c", probe], env={**env, "NUMPY_MADVISE_HUGEPAGE": "1"},
                         capture_output=True, text=True, check=True)
    assert out.stdout.split()[0] == "True"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_every_command_serves_frame_sized_arrays_from_the_heap():
    """The console script tunes malloc as it loads (``keep_freed_memory``): a 24 MB array, a 1080p
    vec3 map, then comes from the heap, not from a mapping of its own that page-faults afresh every
    frame."""
    probe = ("import ctypes, sys, numpy as np\n"
             "class Info(ctypes.Structure): _fields_ = [(n, ctypes.c_size_t) for n in 'arena ordblks smblks hblks "
             "hblkhd usmblks fsmblks uordblks fordblks keepcost'.split()]\n"
             "info = ctypes.CDLL('libc.so.6').mallinfo2; info.restype = Info\n"
             "if sys.argv[1] == 'cli':\n"
             "    import stages.cli\n"
             "before = info().hblkhd; a = np.ones(3 << 20); print(info().hblkhd - before)")
    mapped = {how: int(subprocess.run([sys.executable, "-c", probe, how], capture_output=True, text=True,
                                      check=True).stdout) for how in ("plain", "cli")}
    assert mapped["plain"] >= 3 << 23 and mapped["cli"] == 0


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
def test_render_a_users_sequence_in_one_command(tmp_path, capsys, monkeypatch):
    _drop(tmp_path, frames=[1, 2, 3, 4, 5, 10, 11])  # 10 and 11 sort before 2 by name
    out = tmp_path / "out"
    argv = ["render", str(tmp_path / "drop_{}.ply"), "--radius", "0.01", "--out", str(out), "--size", "64x64",
            "--frames", ":5", "--fps", "24", "--compare"]
    assert cli.main(argv) == 0
    exrs = sorted(p.name for p in out.glob("frame_*.exr"))
    assert exrs == [f"frame_{i:04d}.exr" for i in range(1, 6)]
    assert count_video_frames(out / "drop_refined.mp4") == 5
    assert count_video_frames(out / "drop_comparison.mp4") == 5
    # frames in number order: the block's centre moves +x from frame to frame
    centres = []
    for name in exrs:
        ch = read_exr(out / name)
        cols = np.nonzero(ch["ViewLayer.Fluid.A"] > 0)[1]
        assert cols.size > 20
        centres.append(cols.mean())
    assert np.all(np.diff(centres) > 0), centres
    cameras = json.loads((out / "camera.json").read_text())
    assert [f["frame"] for f in cameras["frames"]] == [1, 2, 3, 4, 5]

    # the exported camera gives the same frames back, at the size it records
    again = tmp_path / "again"
    assert cli.main([*argv[:5], str(again), "--frames", ":5", "--camera", str(out / "camera.json")]) == 0
    assert json.loads((again / "camera.json").read_text())["width"] == 64
    for name in exrs:
        alpha = "ViewLayer.Fluid.A"
        # camera.json rounds the focal length to 1e-6 mm, so a refined pixel whose normal length sits
        # on the mask's threshold may flip (1 of 4096 with the weights of 2026-12-06); no more
        assert np.mean(read_exr(again / name)[alpha] != read_exr(out / name)[alpha]) <= 0.002, name

    # fluid over transparent black: premultiplied colour is 0 wherever alpha is; without --compare
    # the metaball network, which only the comparison draws, is not even loaded
    from stages import render

    clear = tmp_path / "clear"
    with monkeypatch.context() as patch:
        patch.setattr(render, "load_metaball", lambda run: pytest.fail("the metaball network was loaded"))
        assert cli.main([*argv[:5], str(clear), "--size", "64x64", "--frames", "3", "--background", "none"]) == 0
    ch = read_exr(clear / "frame_0003.exr")
    alpha, rgb = ch["ViewLayer.Combined.A"], np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"])
    assert 0 < (alpha > 0).mean() < 1 and np.all(rgb[:, alpha == 0] == 0)
    # without --compare only the refined method runs: no comparison frames or video
    assert not list(clear.glob("*comparison*"))
    (entry,) = (clear / ".cache" / "render").iterdir()
    assert not (entry / "compare").exists() and (entry / "preview").exists()

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
        (["render", pattern, "--radius", "0.01", "--out", o, "--size", "100000x100000"], 2,
         "--size: 100000x100000 is larger than 16384 pixels a side"),
    ]
    good = {"frame": 1, "camera_to_world": np.eye(4).tolist(), "focal_length_mm": 50.0}
    for name, body, words in [
        ("list", [good], "must be a JSON object with a 'frames' list"),
        ("flat", {"frames": [{**good, "camera_to_world": np.diag([1.0, 1.0, 0.0, 1.0]).tolist()}]},
         "rotation is singular"),
        ("lens", {"frames": [{**good, "focal_length_mm": -35}]}, "focal_length_mm must be > 0, got -35"),
    ]:
        (tmp_path / f"{name}.json").write_text(json.dumps(body))
        cases.append((["render", pattern, "--radius", "0.01", "--out", o, "--camera", str(tmp_path / f"{name}.json")],
                      1, words))
    assert cli.main(["render", pattern, "--radius", "0.01", "--out", o, "--up", "x"]) == 2  # a usage error
    assert "'x' is not one of 'y', 'z'" in capsys.readouterr().err
    for argv, code, words in cases:
        capsys.readouterr()
        assert cli.main(argv) == code, argv
        line = _one_line(capsys.readouterr().err)
        assert words in line, line
    zeros = tmp_path / "zeros_1.ply"
    write_particles(zeros, ParticleFrame(np.zeros((4, 3), np.float32), None, np.zeros(4, np.float32)))
    assert cli.main(["render", str(zeros), "--out", o]) == 2
    assert "--radius: is required: the median pscale or radius of zeros_1.ply is 0" in \
        _one_line(capsys.readouterr().err)
    (tmp_path / "drop_3.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\n")
    assert cli.main(["render", pattern, "--radius", "0.01", "--out", str(tmp_path / "o")]) == 1
    assert "drop_3.ply" in _one_line(capsys.readouterr().err)


def test_refine_your_own_exrs(tmp_path, ss, launch, capsys):
    from pipeline.camera import Camera, look_at
    from pipeline.config import DatasetConfig
    from pipeline.exr import stack, write_exr
    from pipeline.methods import refine
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner
    from pipeline.surface import particle_ellipsoids
    from pipeline.views import screen_space_inputs

    r, p = 0.01, DatasetConfig(width=64, height=64)
    ax = np.arange(-0.08, 0.08 + 1e-9, 2 * r)
    ball = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    ball = ball[np.linalg.norm(ball, axis=1) <= 0.08].astype(np.float32)
    for f in (1, 2, 10):  # written out of name order
        cam = Camera(look_at((0.05 * f, 0.1, 0.5), (0, 0, 0)), 40.0, 64, 64)
        ch = screen_space_inputs(ball, r, cam, p, ss, filters=None,
                                 ellipsoids=particle_ellipsoids(ball, r, p, launch, density=True),
                                 aniso_filters=("bilateral",))
        write_exr(tmp_path / f"view_{f}.exr", ch)
    refiner = load_refiner(SHIPPED_WEIGHTS)
    if refiner.spec.features == "radius":  # no camera or radius in these headers: the command asks for them
        capsys.readouterr()
        assert cli.main(["refine", str(tmp_path / "view_{}.exr"), "--out", str(tmp_path / "out")]) == 1
        assert "--radius" in _one_line(capsys.readouterr().err)
    assert cli.main(["refine", str(tmp_path / "view_{}.exr"), "--out", str(tmp_path / "out"), "--radius", str(r),
                     "--fov", "40"]) == 0
    from pipeline.exr import read_exr

    for f in (1, 2, 10):
        got = read_exr(tmp_path / "out" / f"view_{f}.exr")
        focal_px = Camera(np.eye(4), 40.0, 64, 64).focal_px
        n, mask, _ = refine(refiner, read_exr(tmp_path / f"view_{f}.exr"), 0.5, focal_px, r)
        np.testing.assert_allclose(stack(got, "N."), n, atol=1e-6)
        assert np.array_equal(got["mask"] > 0, mask) and mask.sum() > 40
        np.testing.assert_allclose(np.linalg.norm(n[mask], axis=-1), 1.0, atol=1e-5)
    write_exr(tmp_path / "bad" / "view_1.exr", {"Z": np.ones((8, 8), np.float32)})
    capsys.readouterr()
    assert cli.main(["refine", str(tmp_path / "bad" / "view_{}.exr"), "--out", str(tmp_path / "o2")]) == 1
    line = _one_line(capsys.readouterr().err)
    assert "view_1.exr" in line and "aniso_bilateral.N.X" in line, line
