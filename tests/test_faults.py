"""Faults and hostile inputs end in one clear line, and nothing half-written is taken as done."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest
import yaml

from stages import cli
from tests.conftest import ROOT, kill_after_writes


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def _full_at_call(k: int, writer):
    """``writer`` that fails with ENOSPC on its k-th call (the disk fills half way through a run)."""
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == k:
            _enospc()
        return writer(*args, **kwargs)

    return flaky


def _one_line(err: str) -> str:
    """The error line of a stage's stderr (progress bars aside): exactly one, and no traceback."""
    lines = [line for line in err.replace("\r", "\n").splitlines() if "error:" in line or "Traceback" in line]
    assert len(lines) == 1, err
    return lines[0]


def test_disk_full_while_simulating_is_one_line_and_resumes(tiny_dam, capsys, monkeypatch):
    """The frame writer fails with ENOSPC half way: one line naming the stage, the file and the
    cause; no manifest (the entry is not complete); a later run resumes and completes."""
    real = np.savez
    monkeypatch.setattr(np, "savez", _full_at_call(4, real))
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("simulate: error: No space left on device") and "frame_0004.npz" in line
    (entry,) = (tiny_dam.parent / "data" / "simulate").iterdir()
    assert not (entry / "manifest.json").exists() and not list(entry.glob(".*tmp*"))
    monkeypatch.setattr(np, "savez", real)
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    assert (entry / "manifest.json").exists() and len(list(entry.glob("frame_*.npz"))) == 6


def test_disk_full_while_writing_an_exr_is_one_line(tiny_dam, capsys, monkeypatch):
    """The EXR is written on the background writer thread; its failure still reaches the stage
    boundary as one line naming the EXR, and the render is not marked complete."""
    import OpenEXR

    body = yaml.safe_load(tiny_dam.read_text())
    body["render"] = {"width": 48, "height": 48, "method": "nrf", "comparison": False}
    tiny_dam.write_text(yaml.safe_dump(body))
    monkeypatch.setattr(OpenEXR.File, "write", _enospc)
    assert cli.main(["render", "--config", str(tiny_dam)]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("render: error: No space left on device") and ".exr" in line
    (entry,) = (tiny_dam.parent / "data" / "render").iterdir()
    assert not (entry / "manifest.json").exists()
    data = tiny_dam.parent / "data"
    assert not [p for p in data.rglob("*") if ".mp4" in p.name], "the video being encoded goes with the error"


def test_a_duplicated_yaml_key_is_rejected(tmp_path, capsys):
    path = tmp_path / "dup.yaml"
    path.write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\nsimulate:\n  frames: 4\n  frames: 8\n")
    assert cli.main(["simulate", "--config", str(path)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "dup.yaml" in line and "duplicate key 'frames'" in line and "line 3" in line


@pytest.mark.parametrize("key, value, words", [
    ("fps", ".inf", "simulate.fps: must be a finite number"),
    ("particle_radius", ".nan", "simulate.particle_radius: must be a finite number"),
    ("particle_radius", "1.0e-9", "simulate.particle_radius 1e-09 would fill the fluid of scene"),
])
def test_non_finite_and_absurd_numbers_are_named(tiny_dam, capsys, key, value, words):
    text = tiny_dam.read_text().replace("simulate:\n", f"simulate:\n  {key}: {value}\n", 1)
    if key == "particle_radius":
        text = text.replace("  particle_radius: 0.0125\n", "")
    tiny_dam.write_text(text)
    code = cli.main(["simulate", "--config", str(tiny_dam)])
    line = _one_line(capsys.readouterr().err)
    assert code in (1, 2) and words in line, line


def test_dataset_workers_never_load_warp_modules_at_once(tiny_dam, monkeypatch):
    """Two frame workers used to initialise Warp together (about 1 run in 30 failed inside Warp):
    Warp is initialised before they start and module loads are serialised."""
    import threading

    import warp as wp


    real = wp.load_module
    state = {"inside": 0, "most": 0, "calls": 0}
    lock = threading.Lock()

    def watched(*args, **kwargs):
        with lock:
            state["inside"] += 1
            state["calls"] += 1
            state["most"] = max(state["most"], state["inside"])
        try:
            threading.Event().wait(0.01)  # widen the window a race would need
            return real(*args, **kwargs)
        finally:
            with lock:
                state["inside"] -= 1

    monkeypatch.setattr(wp, "load_module", watched)
    body = yaml.safe_load(tiny_dam.read_text())
    body["dataset"] = {"width": 32, "height": 32, "frame_stride": 1, "workers": 2}
    tiny_dam.write_text(yaml.safe_dump(body))
    assert cli.main(["dataset", "--config", str(tiny_dam)]) == 0
    assert state["calls"] > 2 and state["most"] == 1, state


def test_a_corrupt_upstream_file_names_the_command_that_rebuilds_it(tiny_dam, capsys):
    """A finished simulation with a damaged frame: the dataset stage names the file and the exact
    command, and running that command does fix it."""

    body = yaml.safe_load(tiny_dam.read_text())
    body["dataset"] = {"width": 32, "height": 32, "frame_stride": 1}
    tiny_dam.write_text(yaml.safe_dump(body))
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    (entry,) = (tiny_dam.parent / "data" / "simulate").iterdir()
    stat = (entry / "frame_0003.npz").stat()
    (entry / "frame_0003.npz").write_bytes(b"g" * stat.st_size)  # same size and time: only a hash would tell
    os.utime(entry / "frame_0003.npz", ns=(stat.st_atime_ns, stat.st_mtime_ns))
    capsys.readouterr()
    assert cli.main(["dataset", "--config", str(tiny_dam)]) == 1
    line = _one_line(capsys.readouterr().err)
    assert "frame_0003.npz" in line and "`make simulate FORCE=1 SCENE=tiny_dam`" in line, line
    assert cli.main(["simulate", "--config", str(tiny_dam), "--scene", "tiny_dam", "--force"]) == 0
    assert cli.main(["dataset", "--config", str(tiny_dam)]) == 0


@pytest.mark.parametrize("binary", [False, True])
def test_vtk_5_1_files_as_meshio_writes_them(tmp_path, binary):
    """VTK 5.1 (CELLS as OFFSETS and CONNECTIVITY arrays) used to fail with raw bytes in the message."""
    meshio = pytest.importorskip("meshio")
    from pipeline.particles import read_particles

    rng = np.random.default_rng(0)
    points, velocity = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    mesh = meshio.Mesh(points, [("vertex", np.arange(50)[:, None])], point_data={"velocity": velocity})
    path = tmp_path / "frame.vtk"
    meshio.vtk.write(str(path), mesh, fmt_version="5.1", binary=binary)
    assert "Version 5.1" in path.read_bytes()[:40].decode()
    frame = read_particles(path)
    np.testing.assert_allclose(frame.positions, points, atol=1e-6)
    np.testing.assert_allclose(frame.velocities, velocity, atol=1e-6)


def test_an_empty_particle_file_is_named(tmp_path):
    from pipeline.particles import ParticleFormatError, read_particles

    path = tmp_path / "frame_1.xyz"
    path.write_bytes(b"")
    with pytest.raises(ParticleFormatError, match=r"frame_1\.xyz: the file holds no particles"):
        read_particles(path)


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MB tmpfs (needs root and mount rights; skipped elsewhere, where the patched-writer tests
    above stand in)."""
    import os
    import subprocess

    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3M", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a small tmpfs here")
    yield mount
    subprocess.run(["umount", str(mount)], capture_output=True)


@pytest.mark.slow
@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_real_full_disk_at_every_point_of_a_render_is_one_line(small_disk, capsys):
    """Fill the disk so that space runs out at successively later points of a render (before it, by
    the estimate; frames, previews, comparison tiles, videos, the contact sheet): every failure is
    one line naming a file and the cause, never a traceback, nothing is marked complete, and once
    space is freed the same render completes."""
    import shutil
    from pathlib import Path

    body = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    body.update({"scenes": ["dam_break"], "scene_dir": str(ROOT / "configs" / "scenes"),
                 "data_dir": str(small_disk / "data")})
    body["simulate"].update({"particle_radius": 0.03, "frames": 6})
    body["dataset"] = {"holdout_scenes": []}
    body["render"] = {"width": 128, "height": 128, "method": "nrf", "comparison": True}
    config = small_disk.parent / "config.yaml"
    config.write_text(yaml.safe_dump(body))
    assert cli.main(["simulate", "--config", str(config)]) == 0
    fill = small_disk / "fill"
    failures = set()
    for budget in range(150_000, 1_200_000, 70_000):
        shutil.rmtree(small_disk / "data" / "render", ignore_errors=True)
        fill.unlink(missing_ok=True)
        fill.write_bytes(b"0" * max(shutil.disk_usage(small_disk).free - budget, 0))
        capsys.readouterr()
        code = cli.main(["render", "--config", str(config)])
        err = capsys.readouterr().err
        assert "Traceback" not in err
        if code:
            line = _one_line(err)
            assert code == 1 and str(small_disk) in line, line
            assert not list((small_disk / "data" / "render").glob("*/manifest.json"))
            if "GB free" in line:  # refused up front: the frames' estimate does not fit
                assert "render.width, render.height: 6 frames of 128x128 need about" in line, line
                failures.add("estimate")
            else:
                assert "No space left on device" in line, line
                failures.add(Path(line.split("(")[-1].split(")")[0]).suffix)
    assert {"estimate", ".exr", ".png"} <= failures, failures
    # the videos take a few kB: fill the disk right before the real ffmpeg finishes them (they are
    # encoded as the frames come; x264 holds a few frames back until the end)
    from pipeline.media import VideoWriter

    real_exit = VideoWriter.__exit__

    def video_on_a_full_disk(self, *exc):
        fill.unlink(missing_ok=True)
        fill.write_bytes(b"0" * shutil.disk_usage(small_disk).free)
        return real_exit(self, *exc)

    shutil.rmtree(small_disk / "data" / "render", ignore_errors=True)
    fill.unlink(missing_ok=True)
    VideoWriter.__exit__ = video_on_a_full_disk
    try:
        capsys.readouterr()
        assert cli.main(["render", "--config", str(config)]) == 1
    finally:
        VideoWriter.__exit__ = real_exit
    line = _one_line(capsys.readouterr().err)
    assert "No space left on device" in line and line.split("(")[-1].startswith(str(small_disk)) and ".mp4)" in line
    fill.unlink()
    assert cli.main(["render", "--config", str(config)]) == 0


def test_a_damaged_output_of_a_finished_entry_is_redone_not_trusted(tiny_dam, caplog):
    """Sizes and times are checked on every run (a changed time has the file hashed), every hash
    with --verify; only the damaged frame is redone."""
    from pipeline.exr import read_exr

    caplog.set_level("WARNING")
    body = yaml.safe_load(tiny_dam.read_text())
    body["render"] = {"width": 48, "height": 48, "method": "nrf", "comparison": False}
    tiny_dam.write_text(yaml.safe_dump(body))
    args = ["--config", str(tiny_dam)]
    assert cli.main(["render", *args]) == 0
    (entry,) = (tiny_dam.parent / "data" / "render").iterdir()
    frames = entry / "frames"
    whole = (frames / "frame_0003.exr").read_bytes()
    kept = (frames / "frame_0001.exr").stat().st_mtime_ns
    (frames / "frame_0003.exr").write_bytes(whole[: len(whole) // 2])  # truncated
    assert cli.main(["render", *args]) == 0
    assert "frame_0003.exr is damaged" in caplog.text
    assert (frames / "frame_0003.exr").read_bytes() == whole
    assert read_exr(frames / "frame_0003.exr")["ViewLayer.Fluid.A"].any()
    assert (frames / "frame_0001.exr").stat().st_mtime_ns == kept

    flipped = bytearray(whole)
    flipped[-10] ^= 0xFF  # same size, other content: written to since, so hashed on reuse
    (frames / "frame_0003.exr").write_bytes(bytes(flipped))
    caplog.clear()
    assert cli.main(["render", *args]) == 0
    assert "content differs from the recorded hash" in caplog.text
    assert (frames / "frame_0003.exr").read_bytes() == whole

    stat = (frames / "frame_0003.exr").stat()  # the same, with its time put back: --verify hashes all
    (frames / "frame_0003.exr").write_bytes(bytes(flipped))
    os.utime(frames / "frame_0003.exr", ns=(stat.st_atime_ns, stat.st_mtime_ns))
    caplog.clear()
    assert cli.main(["render", *args]) == 0
    assert "damaged" not in caplog.text and (frames / "frame_0003.exr").read_bytes() == bytes(flipped)
    assert cli.main(["render", *args, "--verify"]) == 0
    assert "content differs from the recorded hash" in caplog.text
    assert (frames / "frame_0003.exr").read_bytes() == whole


def test_disk_full_while_exporting_is_one_line(tiny_dam, capsys, monkeypatch):
    from pathlib import Path

    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    monkeypatch.setattr(Path, "write_bytes", _enospc)
    capsys.readouterr()

    assert cli.main(["export", "--config", str(tiny_dam), "--format", "ply"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("export: error: No space left on device") and "frame_0001.ply" in line, line


def test_disk_full_while_saving_a_checkpoint_is_one_line(tmp_path, capsys, monkeypatch):
    import torch

    from tests.test_model import _tiny_train_config

    config = _tiny_train_config(tmp_path, "full")
    monkeypatch.setattr(torch, "save", _enospc)
    assert cli.main(["train", "--config", config]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("train: error: No space left on device") and "last.pt" in line, line
    assert not list((tmp_path / "full" / "data" / "train").glob("*/manifest.json"))


@pytest.mark.slow
def test_two_stages_killed_at_random_points_resume_to_a_clean_run(tmp_path):
    """simulate and dataset, each SIGKILLed twice at random points (seeded) and re-run: the outputs
    equal those of a clean run, and no temporary file is left."""
    import os
    import random
    import subprocess
    import sys

    from pipeline.exr import read_exr
    from tests.conftest import CAMERAS

    def config(name: str):
        folder = tmp_path / name
        scene = {"name": "tiny_dam", "domain_lo": [0, 0, 0], "domain_hi": [0.6, 0.5, 0.3],
                 "fluid": [{"shape": "box", "lo": [0, 0, 0], "hi": [0.2, 0.3, 0.3]}], "cameras": CAMERAS}
        from tests.conftest import write_config

        return write_config(folder, {"scenes": ["tiny_dam"], "seed": 3,
                                     "simulate": {"particle_radius": 0.0125, "frames": 24},
                                     "dataset": {"width": 48, "height": 48, "frame_stride": 1, "workers": 2}},
                            {"tiny_dam": scene})

    clean, killed = config("clean"), config("killed")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    rng = random.Random(2026)
    patterns = {"simulate": "frame_*.npz", "dataset": "*/frame_*.exr"}
    interrupted = 0
    for stage, pattern in patterns.items():
        cmd = [sys.executable, "-m", "stages.cli", stage, "--config"]
        assert subprocess.run(cmd + [str(clean)], cwd=ROOT, env=env, capture_output=True).returncode == 0
        total = len(list((clean.parent / "data" / stage).glob(f"*/{pattern}")))
        for _ in range(2):
            left = total - len(list((killed.parent / "data" / stage).glob(f"*/{pattern}")))
            kill_after_writes(cmd + [str(killed)], f"*/{pattern}", rng.randint(1, max(left - 1, 1)))
            entries = list((killed.parent / "data" / stage).iterdir())
            interrupted += bool(entries) and not (entries[0] / "manifest.json").exists()
        assert subprocess.run(cmd + [str(killed)], cwd=ROOT, env=env, capture_output=True).returncode == 0
    assert interrupted >= 3, "the kills must land while the stages run"
    for stage, pattern in patterns.items():
        (a,) = (clean.parent / "data" / stage).iterdir()
        (b,) = (killed.parent / "data" / stage).iterdir()
        files = sorted(p.relative_to(a) for p in a.glob(pattern))
        assert files == sorted(p.relative_to(b) for p in b.glob(pattern)) and files
        for f in files:
            if stage == "simulate":
                assert (a / f).read_bytes() == (b / f).read_bytes(), f
            else:
                ca, cb = read_exr(a / f), read_exr(b / f)
                assert ca.keys() == cb.keys() and all(np.array_equal(ca[k], cb[k]) for k in ca), f
        assert not list(b.parent.parent.rglob("*.tmp-*"))  # the entry and its staged writes


def test_a_damaged_middle_frame_of_an_unfinished_entry_is_redone(tiny_dam, caplog, monkeypatch):
    """A run stops half way (disk full at frame 5); a frame it had finished is then damaged. The
    journal of the unfinished entry records each finished file, so the resume redoes that frame
    and the sequence ends equal to a clean run's."""
    real = np.savez
    monkeypatch.setattr(np, "savez", _full_at_call(5, real))
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 1
    monkeypatch.setattr(np, "savez", real)
    (entry,) = (tiny_dam.parent / "data" / "simulate").iterdir()
    assert (entry / "journal.jsonl").exists() and not (entry / "manifest.json").exists()
    (entry / "frame_0002.npz").write_bytes((entry / "frame_0002.npz").read_bytes()[:100])
    caplog.set_level("WARNING")
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    assert "frame_0002.npz is damaged" in caplog.text
    assert not (entry / "journal.jsonl").exists(), "the manifest supersedes the journal"
    resumed = {f.name: f.read_bytes() for f in entry.glob("frame_*.npz")}
    import shutil

    shutil.rmtree(entry)
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    assert resumed == {f.name: f.read_bytes() for f in entry.glob("frame_*.npz")}


def test_a_read_only_disk_is_one_line(small_disk, tiny_dam, capsys):
    import subprocess

    body = yaml.safe_load(tiny_dam.read_text())
    body["data_dir"] = str(small_disk / "data")
    tiny_dam.write_text(yaml.safe_dump(body))
    (small_disk / "data").mkdir()
    assert subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], capture_output=True).returncode == 0
    capsys.readouterr()
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 1
    line = _one_line(capsys.readouterr().err)
    assert "Read-only file system" in line and str(small_disk) in line, line


SPLISH_FRAME = ROOT / "tests" / "data" / "double_dam_break_frame_01_4732_particles.vtk"


def _user_sequence(folder, frames: int) -> str:
    """``frames`` copies of the SPlisHSPlasH test frame as fluid_1.vtk ...; returns their pattern."""
    import shutil

    folder.mkdir(parents=True, exist_ok=True)
    for i in range(1, frames + 1):
        shutil.copy(SPLISH_FRAME, folder / f"fluid_{i}.vtk")
    return str(folder / "fluid_{}.vtk")


@pytest.mark.slow
@pytest.mark.parametrize("sig, code, word", [("SIGINT", 130, "interrupted"), ("SIGTERM", 143, "terminated")])
def test_a_signal_ends_a_render_within_two_seconds_and_the_same_command_resumes(tmp_path, sig, code, word):
    """Ctrl-C or SIGTERM right after the first frame's last file (its preview, written after the EXR):
    the render ends within 2 s with one line (exit 130 / 143), keeps that frame, and the same command
    then renders only the rest."""
    import signal
    import sys
    import time

    from tests.conftest import on_writes

    pattern, out = _user_sequence(tmp_path / "seq", 4), tmp_path / "out"
    cmd = [sys.executable, "-m", "stages.cli", "render", pattern, "--radius", "0.025", "--out", str(out),
           "--size", "160x120"]
    sent = {}

    def stop(proc) -> None:
        sent["at"] = time.perf_counter()
        proc.send_signal(getattr(signal, sig))

    proc = on_writes(cmd, "*/preview/frame_0001.png", 1, stop)
    waited = time.perf_counter() - sent["at"]
    assert proc.returncode == code and waited < 2.0, (proc.returncode, waited)
    assert [line for line in proc.log if line.startswith("render:")] == \
        [f"render: {word}; finished work is kept and the same command resumes\n"]
    (entry,) = (out / ".cache" / "render").glob("*")
    first = entry / "frames" / "frame_0001.exr"
    assert not (entry / "manifest.json").exists()
    kept = first.stat().st_mtime_ns
    assert cli.main(cmd[3:]) == 0
    assert sorted(p.name for p in out.glob("frame_*.exr")) == [f"frame_{i:04d}.exr" for i in range(1, 5)]
    assert first.stat().st_mtime_ns == kept, "a finished frame was redone"


def test_a_cloud_far_denser_than_a_fluid_is_refused_before_any_work(tmp_path, capsys):
    """150,000 particles of radius 1 cm in a 1 mm box (a units mistake): one line naming the file
    and --radius, before a frame renders, instead of a neighbour search of 2e10 pairs."""
    from pipeline.particles import ParticleFrame, write_particles

    x = np.random.default_rng(0).uniform(0.0, 0.001, (150_000, 3)).astype(np.float32)
    write_particles(tmp_path / "dense_1.ply", ParticleFrame(x, None, np.full(len(x), 0.01, np.float32)))
    out = tmp_path / "out"
    assert cli.main(["render", str(tmp_path / "dense_{}.ply"), "--out", str(out), "--size", "64x64"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert "dense_1.ply" in line and "150,000 particles" in line and "check --radius" in line
    assert not list(out.glob("frame_*.exr")) and not (out / ".cache" / "render").exists()


def test_a_render_that_cannot_fit_in_memory_is_refused_naming_the_size(tmp_path, capsys):
    pattern = _user_sequence(tmp_path / "seq", 1)
    out = tmp_path / "out"
    assert cli.main(["render", pattern, "--radius", "0.025", "--out", str(out), "--size", "16000x16000"]) == 1
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("render: error: --size: a 16000x16000 frame of 4,732 particles needs about") and \
        "GB of memory" in line
    assert not (out / ".cache" / "render").exists()


@pytest.mark.slow
def test_ctrl_c_ends_a_simulation_within_two_seconds_and_the_same_command_resumes(tiny_dam):
    import signal
    import sys
    import time

    from tests.conftest import on_writes

    body = yaml.safe_load(tiny_dam.read_text())
    body["simulate"]["frames"] = 40
    tiny_dam.write_text(yaml.safe_dump(body))
    cmd = [sys.executable, "-m", "stages.cli", "simulate", "--config", str(tiny_dam)]
    sent = {}

    def stop(proc) -> None:
        sent["at"] = time.perf_counter()
        proc.send_signal(signal.SIGINT)

    proc = on_writes(cmd, "*/frame_0010.npz", 1, stop)
    assert proc.returncode == 130 and time.perf_counter() - sent["at"] < 2.0
    (entry,) = (tiny_dam.parent / "data" / "simulate").iterdir()
    assert 10 <= len(list(entry.glob("frame_*.npz"))) < 40 and not (entry / "manifest.json").exists()
    assert cli.main(["simulate", "--config", str(tiny_dam)]) == 0
    assert len(list(entry.glob("frame_*.npz"))) == 40
