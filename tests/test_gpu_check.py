"""The GPU check's script, read here: a lent GPU comes rarely and for minutes, so a step that would
fail on it for a renamed flag, or calls whose steps outgrow their time limits, are found on the CPU."""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.conftest import ROOT

CHECK = ROOT / "benchmarks" / "gpu_check.sh"
STAGE = ROOT / "benchmarks" / "gpu_stage.sh"
BOOT_S = 60
"""What the figures' call spends before its first step at most: unpacking the staged packages (144 MB
of xz, once: the next call finds them unpacked)."""


def _steps() -> dict[str, tuple[int, list[str]]]:
    """Each ``step NAME LIMIT COMMAND...`` of gpu_check.sh: its limit and its command's words, with
    the script's variables filled in."""
    text = CHECK.read_text().replace("\\\n", " ")
    values = {"$PY": "python", "$DEVICE": "cuda", "$TRACES": "/tmp/traces"}
    steps = {}
    for match in re.finditer(r"^\s*step (\S+) (\d+) (.+)$", text, re.MULTILINE):
        words = shlex.split(match.group(3))
        steps[match.group(1)] = (int(match.group(2)), [values.get(w, w) for w in words])
    return steps


def _calls() -> list[tuple[list[str], int]]:
    """The gpu_check.sh calls gpu_stage.sh prints: the steps each names and its timeout."""
    text = STAGE.read_text()
    figures = re.search(r'^FIGURES="([^"]+)"', text, re.MULTILINE).group(1)
    return [(names.replace("$FIGURES", figures).split(), int(timeout))
            for names, timeout in re.findall(r"gpu_check\.sh ([^\n]*?)    .*timeout_s: (\d+)", text)]


class _Parsed(Exception):
    """Raised in place of a benchmark's run once its arguments parsed."""


def test_the_calls_steps_fit_their_time_limits():
    steps = _steps()
    (figures, figures_s), (breakdowns, breakdowns_s) = _calls()
    assert figures + breakdowns == list(steps), "the two calls run every step once, in the script's order"
    assert BOOT_S + sum(steps[n][0] for n in figures) <= figures_s
    assert sum(steps[n][0] for n in breakdowns) <= breakdowns_s  # unpacked by the call before


@pytest.mark.parametrize("name", [n for n, (_, words) in _steps().items()
                                  if any(w.startswith("benchmarks/") for w in words)])
def test_every_benchmark_step_parses_its_arguments(name, monkeypatch):
    words = _steps()[name][1]
    script = next(k for k, w in enumerate(words) if w.startswith("benchmarks/"))
    path, args = ROOT / words[script], words[script + 1:]
    parse = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, *a, **k):
        parse(self, *a, **k)  # a wrong flag or value exits here with argparse's message
        raise _Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    monkeypatch.setattr(sys, "argv", [str(path), *args])
    monkeypatch.setattr(sys, "path", [str(path.parent), *sys.path])  # as `python benchmarks/X.py` has it
    with pytest.raises(_Parsed):
        runpy.run_path(str(path), run_name="__main__")


def test_the_cuda_step_selects_the_cuda_tests_the_readme_counts():
    words = _steps()["cuda_tests"][1]
    assert words[:3] == ["python", "-m", "pytest"] and words[words.index("-m", 3) + 1] == "cuda"
    said = re.search(r"`pytest -m cuda` runs the (\d+) tests", (ROOT / "docs" / "development.md").read_text())
    out = subprocess.run([sys.executable, *words[1:], "--collect-only"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    collected = re.search(r"^(\d+)/\d+ tests collected", out.stdout, re.MULTILINE)
    assert collected, out.stdout[-2000:] + out.stderr[-2000:]
    assert said and int(said.group(1)) == int(collected.group(1)), (said and said.group(1), collected.group(1))


def _pieces(folder, count: int = 3) -> bytes:
    """A packed site in ``count`` pieces laid out as gpu_stage.sh lays them out (``.gpu/pK/piece_K`` and
    one SHA256SUMS in each), holding Warp's library and a module; returns the library's bytes."""
    site = folder / "site"
    (site / "warp" / "bin").mkdir(parents=True)
    library = bytes(range(256)) * 400
    (site / "warp" / "bin" / "warp.so").write_bytes(library)
    (site / "staged_probe.py").write_text("WHERE = __file__\n")
    bundle = folder / "bundle.tar.xz"
    subprocess.run(f"tar -C {site} -cf - . | xz -0 > {bundle}", shell=True, check=True)
    data = bundle.read_bytes()
    cuts = [len(data) * k // count for k in range(count + 1)]
    sums = []
    for k in range(1, count + 1):
        piece = data[cuts[k - 1]:cuts[k]]
        (folder / "pieces" / f"p{k}").mkdir(parents=True)
        (folder / "pieces" / f"p{k}" / f"piece_{k}").write_bytes(piece)
        sums.append(f"{hashlib.sha256(piece).hexdigest()}  piece_{k}\n")
    for k in range(1, count + 1):
        (folder / "pieces" / f"p{k}" / "SHA256SUMS").write_text("".join(sums))
    return library


def _call(folder, piece: int | None, command: str, boot) -> subprocess.CompletedProcess:
    """One device call as the tool makes it: a fresh tree (here a folder) that holds only the piece it
    carries, run from that tree's root, with the machine's /tmp (``boot``) kept between calls."""
    tree = Path(tempfile.mkdtemp(prefix="tree_", dir=folder))
    (tree / ".gpu").mkdir()
    if piece is not None:
        shutil.copytree(folder / "pieces" / f"p{piece}", tree / ".gpu" / f"p{piece}")
    env = {**os.environ, "GPU_BOOT_DIR": str(boot), "BOOT": str(ROOT / "benchmarks" / "gpu_boot.sh")}
    env.pop("PYTHONPATH", None)
    return subprocess.run(["bash", "-c", command], cwd=tree, env=env, capture_output=True, text=True, timeout=60)


def test_the_pieces_parked_one_a_call_unpack_on_the_last(tmp_path):
    library = _pieces(tmp_path)
    boot = tmp_path / "machine_tmp"
    for k in (1, 2):
        parked = _call(tmp_path, k, 'bash "$BOOT" park', boot)
        assert parked.returncode == 0 and f"kept {k} piece(s)" in parked.stdout, parked.stdout + parked.stderr
    probe = 'source "$BOOT" && python3 -c "import staged_probe; print(staged_probe.WHERE)" && echo "$DEEP_SSFR_DEVICE"'
    last = _call(tmp_path, 3, probe, boot)
    assert last.returncode == 0, last.stdout + last.stderr
    assert "unpacked 3 pieces" in last.stdout and last.stdout.split()[-2:] == [
        str(boot / "site" / "staged_probe.py"), "cuda"]
    assert (boot / "site" / "warp" / "bin" / "warp.so").read_bytes() == library
    again = _call(tmp_path, None, probe, boot)  # the breakdowns' call carries nothing: the site stays
    assert again.returncode == 0 and "unpacked" not in again.stdout, again.stdout + again.stderr


def test_a_missed_or_damaged_piece_stops_the_boot_with_what_to_do(tmp_path):
    _pieces(tmp_path)
    missed = tmp_path / "missed"
    _call(tmp_path, 1, 'bash "$BOOT" park', missed)
    out = _call(tmp_path, 3, 'source "$BOOT" && echo booted', missed)
    assert out.returncode != 0 and "booted" not in out.stdout
    assert "2 of 3 pieces are here" in out.stderr and "park them again" in out.stderr, out.stderr
    damaged = tmp_path / "damaged"
    piece = tmp_path / "pieces" / "p2" / "piece_2"
    piece.write_bytes(b"x" + piece.read_bytes()[1:])
    for k in (1, 2):
        _call(tmp_path, k, 'bash "$BOOT" park', damaged)
    out = _call(tmp_path, 3, 'source "$BOOT" && echo booted', damaged)
    assert out.returncode != 0 and "booted" not in out.stdout and "a piece is damaged" in out.stderr, out.stderr
    assert not (damaged / "site").exists()
