"""Stage cache: hits, precise invalidation, atomic files and resume after SIGKILL."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline import cache, fencing
from pipeline.config_files import load
from pipeline.frames import load_frame
from stages import cli, simulate
from stages.common import Run
from tests.conftest import ROOT, kill_after_writes


def _run(config, *extra):
    return cli.main(["simulate", "--config", str(config), *extra])


def _entries(config, stage="simulate"):
    root = config.parent / "data" / stage
    return sorted(p.name for p in root.iterdir()) if root.exists() else []


def test_rerun_is_a_hit_and_param_change_recomputes(tiny_dam, caplog):
    caplog.set_level("INFO")
    assert _run(tiny_dam) == 0
    first = _entries(tiny_dam)
    manifest = (tiny_dam.parent / "data" / "simulate" / first[0] / "manifest.json")
    stamp = manifest.stat().st_mtime_ns
    caplog.clear()
    assert _run(tiny_dam) == 0
    assert "cached" in caplog.text
    assert manifest.stat().st_mtime_ns == stamp
    body = yaml.safe_load(tiny_dam.read_text())
    body["simulate"]["xsph_viscosity"] = 0.02
    tiny_dam.write_text(yaml.safe_dump(body))
    assert _run(tiny_dam) == 0
    assert len(_entries(tiny_dam)) == 2, "a changed parameter makes a new entry"
    assert _run(tiny_dam, "--force") == 0
    assert len(_entries(tiny_dam)) == 2


def test_keys_follow_config_inputs_and_code(tiny_dam):
    loaded = load(tiny_dam)
    run = Run(loaded, "cpu", False)
    scene = loaded.scenes["tiny_dam"]
    key = simulate.sim_entry(run, scene).key
    # a downstream-only parameter leaves the simulation key alone
    other = load(tiny_dam, overrides={"dataset": {"width": 77}})
    assert simulate.sim_entry(Run(other, "cpu", False), scene).key == key
    changed = load(tiny_dam, overrides={"simulate": {"substeps": 5}})
    assert simulate.sim_entry(Run(changed, "cpu", False), changed.scenes["tiny_dam"]).key != key
    # the key covers the inputs' keys
    a = cache.entry(tiny_dam.parent, "simulate", "n", {"a": 1}, {}, "cpu")
    assert cache.entry(tiny_dam.parent, "simulate", "n", {"a": 1}, {"up": "x"}, "cpu").key != a.key


def _stage_keys(code: Path) -> dict[str, str]:
    """The code hash of every stage, computed in a fresh interpreter over the code at ``code``."""
    import json as _json

    script = ("import json; from pipeline.cache import code_version; print(json.dumps({s: code_version('stages.' + s) "
              "for s in ('simulate', 'dataset', 'train', 'render', 'evaluate')}))")
    out = subprocess.run([sys.executable, "-c", script], cwd=code, env={"PYTHONPATH": str(code), "PATH": ""},
                         capture_output=True, text=True, check=True).stdout
    return _json.loads(out)


def test_the_import_closure_reads_each_source_once(tmp_path, monkeypatch):
    """Each source's imports are kept by the hash of its text: a second process (here, the closure's
    cache cleared) parses nothing and finds the same modules; where the file cannot be written or is
    garbage, the sources are parsed as before."""
    import ast

    monkeypatch.setattr(cache, "IMPORTS_CACHE", tmp_path / "imports.json")
    cache.import_closure.cache_clear()
    first = cache.import_closure("stages.render")
    assert "pipeline.model.inference" in first and (tmp_path / "imports.json").exists()
    cache.import_closure.cache_clear()
    real_parse = ast.parse
    monkeypatch.setattr(ast, "parse", lambda *a, **k: pytest.fail("parsed a source the cache holds"))
    assert cache.import_closure("stages.render") == first
    monkeypatch.setattr(ast, "parse", real_parse)
    (tmp_path / "imports.json").write_text("{not json")
    cache.import_closure.cache_clear()
    assert cache.import_closure("stages.render") == first
    cache.import_closure.cache_clear()


def test_a_stage_key_follows_every_module_it_imports(tmp_path):
    """Keys come from the stage's import closure, not a hand-kept list: editing a module a stage
    imports only indirectly changes that stage's key (and its dependents'), and editing a module
    it does not import leaves it alone. Edits happen in a temporary copy of the code."""
    import shutil

    code = tmp_path / "code"
    for package in ("pipeline", "stages"):
        shutil.copytree(ROOT / package, code / package, ignore=shutil.ignore_patterns("__pycache__", "weights"))
    before = _stage_keys(code)
    # pipeline.parallel reaches simulate only through the solver (a list once missed it)
    with open(code / "pipeline" / "parallel.py", "a") as fh:
        fh.write("\n# an edit\n")
    after = _stage_keys(code)
    assert all(after[s] != before[s] for s in before), "every stage runs the launcher"
    # the render-time refiner is imported by render and evaluate only
    with open(code / "pipeline" / "model" / "inference.py", "a") as fh:
        fh.write("\n# an edit\n")
    last = _stage_keys(code)
    assert last["render"] != after["render"] and last["evaluate"] != after["evaluate"]
    assert all(last[s] == after[s] for s in ("simulate", "dataset", "train"))


def test_sigkill_half_way_then_resume_equals_clean_run(tiny_dam, tmp_path):
    body = yaml.safe_load(tiny_dam.read_text())
    body["simulate"]["frames"] = 60
    tiny_dam.write_text(yaml.safe_dump(body))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "stages.cli", "simulate", "--config", str(tiny_dam)]
    assert kill_after_writes(cmd, "*/frame_0015.npz") == 1
    data = tiny_dam.parent / "data" / "simulate"
    (entry,) = list(data.iterdir())
    done = sorted(entry.glob("frame_*.npz"))
    assert 15 <= len(done) < 60 and not (entry / "manifest.json").exists()
    assert subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True).returncode == 0
    assert (entry / "manifest.json").exists()
    assert not list(data.parent.rglob("*.tmp-*"))  # in the entry or staged beside it

    clean = tmp_path / "clean"
    clean.mkdir()
    body["data_dir"] = str(clean / "data")
    body["scene_dir"] = str(tiny_dam.parent / "scenes")
    (clean / "config.yaml").write_text(yaml.safe_dump(body))
    assert _run(clean / "config.yaml") == 0
    (clean_entry,) = list((clean / "data" / "simulate").iterdir())
    assert clean_entry.name == entry.name
    for f in sorted(clean_entry.glob("frame_*.npz")):
        a, va = load_frame(f)
        b, vb = load_frame(entry / f.name)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(va, vb)


def test_corrupt_cache_file_is_named(tiny_dam, capsys):
    assert _run(tiny_dam) == 0
    (entry,) = list((tiny_dam.parent / "data" / "simulate").iterdir())
    (entry / "frame_0003.npz").write_bytes(b"garbage")
    (entry / "manifest.json").unlink()
    for later in ("frame_0004.npz", "frame_0005.npz", "frame_0006.npz"):
        (entry / later).unlink()
    assert _run(tiny_dam) == 1
    err = capsys.readouterr().err
    assert "frame_0003.npz" in err and "corrupt" in err


WORKER = """if True:
    import sys
    from pathlib import Path
    from pipeline import cache, fencing

    folder = Path(sys.argv[1])
    with fencing.journal_into([(folder, sys.argv[2])]):
        for name in sys.argv[3:]:
            with cache.atomic_path(folder / name) as tmp:
                tmp.write_bytes(name.encode() * 50)
    with cache.atomic_path(folder / "after.bin") as tmp:  # out of the block: not this process's to record
        tmp.write_bytes(b"x")
"""


def test_files_a_worker_process_writes_into_an_open_entry_are_checked_on_resume(tmp_path, caplog):
    """Worker processes (Ray tasks) writing into the entry a driver opened keep journals of their own
    beside the driver's; a resume reads them all, redoes a damaged file of either, folds the rest into
    one journal, and the manifest supersedes them."""
    entry = cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")
    assert entry.begin()
    with cache.atomic_path(entry.path("driver.bin")) as tmp:
        tmp.write_bytes(b"d" * 100)
    ((folder, token),) = fencing.open_entries()
    assert folder == entry.dir.resolve()
    for names in (["a.bin", "b.bin"], ["c.bin"]):  # two workers, as two Ray tasks
        subprocess.run([sys.executable, "-c", WORKER, str(folder), token, *names], cwd=ROOT, check=True)
    workers = [p.name for p in entry.dir.glob("journal-*.jsonl")]
    assert len(workers) == 2 and all(re.fullmatch(r"journal-.+-\d+-[0-9a-f]{8}\.jsonl", n) for n in workers), workers
    assert "driver.bin" in entry.path("journal.jsonl").read_text()
    entry.release()  # the driver is killed: its lock goes, the entry stays unfinished

    entry.path("b.bin").write_bytes(b"short")  # a worker's file damaged after the kill
    entry.path("driver.bin").unlink()  # and one of the driver's lost
    again = cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")
    caplog.set_level("WARNING")
    assert again.begin()
    assert "b.bin is damaged (5 bytes, 250 recorded)" in caplog.text
    assert "driver.bin is damaged (missing)" in caplog.text
    assert not again.path("b.bin").exists() and again.path("a.bin").exists() and again.path("c.bin").exists()
    assert [p.name for p in again.dir.glob("journal*.jsonl")] == ["journal.jsonl"]
    kept = {json.loads(line)["file"] for line in again.path("journal.jsonl").read_text().splitlines()}
    assert kept == {"a.bin", "c.bin"}, "after.bin was written outside the worker's block"
    again.finish(["a.bin", "c.bin"])
    assert not list(again.dir.glob("journal*.jsonl"))


def test_the_manifest_takes_the_journals_hash_unless_the_file_changed_since(tmp_path, monkeypatch):
    """A file journaled as it was written is not read again for the manifest while its size and time
    are the journaled ones; one written to since (here: the same size, a later time) is hashed anew.
    Either way the manifest holds the file's true hash."""
    entry = cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")
    assert entry.begin()
    for name in ("kept.bin", "edited.bin"):
        with cache.atomic_path(entry.path(name)) as tmp:
            tmp.write_bytes(name.encode() * 1000)
    edited = entry.path("edited.bin")
    edited.write_bytes(b"x" * edited.stat().st_size)
    os.utime(edited, ns=(edited.stat().st_atime_ns, edited.stat().st_mtime_ns + 10**9))
    hashed = []
    real_hash = cache.file_hash
    monkeypatch.setattr(cache, "file_hash", lambda path: hashed.append(Path(path).name) or real_hash(path))
    entry.finish(["kept.bin", "edited.bin"])
    assert hashed == ["edited.bin"]
    checks = json.loads(entry.path(cache.MANIFEST).read_text())["checks"]
    assert {n: c[cache.HASH] for n, c in checks.items()} == {n: real_hash(entry.path(n)) for n in checks}


KILLED_MID_WRITE = """
import os, sys
from pathlib import Path
from pipeline import cache, fencing
with fencing.journal_into([(Path(sys.argv[1]), sys.argv[2])]):
    with cache.atomic_path(Path(sys.argv[1]) / "half.bin") as tmp:
        tmp.write_bytes(b"h" * 10)
        os.kill(os.getpid(), 9)
"""


def test_a_worker_killed_mid_write_leaves_no_temporary_in_the_finished_entry(tmp_path):
    """A Ray task on a node that dies is killed inside a write and runs again elsewhere within the
    same run: the finished entry holds its files and none of the dead worker's temporaries."""
    entry = cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")
    assert entry.begin()
    ((folder, token),) = fencing.open_entries()
    killed = subprocess.run([sys.executable, "-c", KILLED_MID_WRITE, str(folder), token], cwd=ROOT)
    assert killed.returncode == -9
    staged = tmp_path / ".staging" / "dataset" / folder.name
    assert [p.name for p in staged.glob(".half.bin.tmp-*")], "the killed write left its temporary"
    inside = sorted(p.name for p in entry.dir.iterdir())
    assert inside[0] == ".run-token" and len(inside) == 2, "the temporary was staged outside the entry"
    assert inside[1].startswith("journal-") and not entry.path(inside[1]).read_text(), "the worker's, empty"
    with cache.atomic_path(entry.path("half.bin")) as tmp:  # the task again, on another node
        tmp.write_bytes(b"h" * 10)
    entry.finish(["half.bin"])
    assert sorted(p.name for p in entry.dir.iterdir()) == ["half.bin", "manifest.json"]
    assert not staged.exists()


def test_finished_entries_leave_no_staging_folders_and_keep_another_entrys_staged_writes(tmp_path):
    """An entry that finishes drops ``.staging/<stage>/`` and ``.staging/`` once they are empty, but
    not while another entry of the stage has a write staged there, which then lands whole."""
    a, b = (cache.entry(tmp_path, "dataset", name, {"a": 1}, {}, "cpu", module="pipeline.cache") for name in "ab")
    assert a.begin() and b.begin()
    with cache.atomic_path(a.path("view.bin")) as tmp:  # a's write staged while b finishes
        tmp.write_bytes(b"a" * 10)
        with cache.atomic_path(b.path("view.bin")) as tmp_b:
            tmp_b.write_bytes(b"b" * 10)
        b.finish(["view.bin"])
        assert tmp.parent == tmp_path / ".staging" / "dataset" / a.dir.name and tmp.exists()
    a.finish(["view.bin"])
    assert a.path("view.bin").read_bytes() == b"a" * 10 and b.path("view.bin").read_bytes() == b"b" * 10
    assert not (tmp_path / ".staging").exists()


def test_a_write_whose_staging_parent_another_run_drops_midway_makes_it_again(tmp_path, monkeypatch):
    """Another run drops the empty ``.staging/<stage>/`` in the instant after this one made it and
    before it made its entry's folder there (the mkdir then finds no parent): the write makes the
    parents again and lands."""
    entry = cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")
    assert entry.begin()
    stage_folder, mkdir, dropped = tmp_path / ".staging" / "dataset", os.mkdir, []

    def racing_mkdir(path, *args, **kwargs):
        mkdir(path, *args, **kwargs)
        if Path(path) == stage_folder and len(dropped) < 3:  # three times in a row
            dropped.append(path)
            os.rmdir(path)

    monkeypatch.setattr(os, "mkdir", racing_mkdir)
    with cache.atomic_path(entry.path("view.bin")) as tmp:
        tmp.write_bytes(b"v" * 10)
    monkeypatch.undo()
    assert len(dropped) == 3, "the race was not staged"
    entry.finish(["view.bin"])
    assert entry.path("view.bin").read_bytes() == b"v" * 10 and not (tmp_path / ".staging").exists()


LATE = """if True:
    import sys
    from pathlib import Path
    from pipeline import cache, fencing

    folder = Path(sys.argv[1])
    pause = sys.argv[3:]
    if pause == ["pause-late"]:  # frozen past the second check, just before the rename
        fence, checks = fencing._fence, []

        def _fence(*args):
            fence(*args)
            checks.append(args)
            if len(checks) == 2:
                print("checked twice", flush=True)
                sys.stdin.readline()

        fencing._fence = _fence
    if pause == ["pause-join"]:  # frozen as it joins the entry, past the check, before its journal
        fence, calls = fencing._fence, []

        def _fence(*args):
            fence(*args)
            calls.append(args)
            if len(calls) == 1:
                print("joining", flush=True)
                sys.stdin.readline()

        fencing._fence = _fence
    if pause == ["pause-placed"]:  # frozen once its file is in place, before its journal record
        journal = fencing._journal

        def _journal(*args):
            print("placed", flush=True)
            sys.stdin.readline()
            journal(*args)

        fencing._journal = _journal
    if pause == ["no-links"]:  # a file system without hard links (some FUSE and SMB mounts)
        import errno
        import os

        def _link(*args):
            raise OSError(errno.EPERM, "Operation not permitted")

        os.link = _link
    with fencing.journal_into([(folder, sys.argv[2])]):
        try:
            with cache.atomic_path(folder / "views" / "late.bin") as tmp:
                if pause == ["pause"]:  # frozen past the first check until told to go on
                    print("checked", flush=True)
                    sys.stdin.readline()
                tmp.write_bytes(b"late")
        except fencing.StaleWrite as exc:
            print(exc)
"""


def _late_write(folder: Path, token: str, *how: str) -> str:
    """A worker's write into ``folder`` under ``token``: what it printed (the refusal, or nothing)."""
    return subprocess.run([sys.executable, "-c", LATE, str(folder), token, *how], cwd=ROOT, check=True,
                          capture_output=True, text=True).stdout.strip()


def _paused_write(tmp_path: Path, pause: str, force: bool = False
                  ) -> tuple[cache.CacheEntry, Path, subprocess.Popen]:
    """A begun (``force``: rebuilt) entry, its folder, and a worker paused inside its write into it
    (``pause``: as it joins, past the first check, the second, or once placed), which goes on once
    sent a line."""
    first = cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")
    assert first.begin(force=force)
    ((folder, token),) = fencing.open_entries()
    worker = subprocess.Popen([sys.executable, "-c", LATE, str(folder), token, pause], cwd=ROOT,
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert worker.stdout is not None
    assert worker.stdout.readline().strip() == {"pause": "checked", "pause-late": "checked twice",
                                                "pause-placed": "placed", "pause-join": "joining"}[pause]
    return first, folder, worker


def test_a_write_frozen_past_its_first_check_leaves_the_finished_entry_as_it_was(tmp_path):
    """A worker frozen inside a write (past the check at its start), thawed once its run has finished
    the entry: its temporary and its target's folder go nowhere in the entry, so the entry's
    folders keep their contents and times, and the write is refused (found in CI: a thawed worker's
    temporary, made and deleted in a view folder, changed that folder's time)."""
    first, folder, worker = _paused_write(tmp_path, "pause")
    first.finish([])
    before = {p: p.stat().st_mtime_ns for p in [folder, *folder.rglob("*")]}
    out, _ = worker.communicate("go\n", timeout=60)
    assert "its run has finished" in out
    assert {p: p.stat().st_mtime_ns for p in [folder, *folder.rglob("*")]} == before
    assert sorted(p.name for p in folder.iterdir()) == ["manifest.json"]


def test_a_write_frozen_past_its_last_check_leaves_the_file_its_rerun_wrote(tmp_path):
    """A worker frozen between its last check and its rename, thawed as its run finishes (the run's
    token gone, its staged temporaries not yet dropped): the file its task run again elsewhere wrote
    keeps its inode and time, and the write is refused, since a worker's write never replaces a file
    once its run no longer holds the entry."""
    first, folder, worker = _paused_write(tmp_path, "pause-late")
    with cache.atomic_path(first.path("views/late.bin")) as tmp:  # the task again, on another node
        tmp.write_bytes(b"late")
    rerun = first.path("views/late.bin").stat()
    (folder / fencing.RUN_TOKEN).unlink()  # finish's first step: the run holds the entry no more
    out, _ = worker.communicate("go\n", timeout=60)
    assert "its run has finished" in out
    now = first.path("views/late.bin").stat()
    assert (now.st_ino, now.st_mtime_ns) == (rerun.st_ino, rerun.st_mtime_ns)
    first.finish(["views/late.bin"])
    assert not (tmp_path / ".staging" / "dataset" / folder.name).exists()


def test_a_worker_frozen_before_its_journal_record_makes_no_journal_in_the_finished_entry(tmp_path):
    """A worker frozen between putting its file in place and recording it, thawed once its run has
    finished the entry (its journals dropped): the record is refused and no journal appears in the
    finished entry (found in CI, a hung node's worker thawed after a run that backup copies ended)."""
    first, folder, worker = _paused_write(tmp_path, "pause-placed")
    assert list(folder.glob("journal-*.jsonl")), "a worker's journal is made when it joins"
    first.finish(["views/late.bin"])
    before = sorted(p.name for p in folder.iterdir())
    out, _ = worker.communicate("go\n", timeout=60)
    assert "not journaled, since its run has finished" in out
    assert sorted(p.name for p in folder.iterdir()) == before == ["manifest.json", "views"]


@pytest.mark.parametrize("force", [False, True], ids=["resumed", "forced"])
def test_a_worker_frozen_as_it_joins_makes_no_journal_in_the_finished_entry(tmp_path, force):
    """A worker frozen as it joins an entry (past the check, before its journal is made), thawed once
    its run has finished the entry: its journal is dropped again at once, and its write refused. In
    a forced run the folder it joined has been swapped in meanwhile, and is not made again."""
    first, folder, worker = _paused_write(tmp_path, "pause-join", force)
    assert not list(folder.glob("journal-*.jsonl"))
    first.finish([])
    out, _ = worker.communicate("go\n", timeout=60)
    assert worker.returncode == 0, out
    assert "its run has finished" in out
    assert folder != first.final_dir and not folder.exists() if force else folder == first.final_dir
    assert sorted(p.name for p in first.final_dir.iterdir()) == ["manifest.json"]


def test_a_worker_that_outlives_its_run_writes_nothing_into_the_entry(tmp_path):
    """A Ray worker cut off from its cluster keeps running while its task runs again elsewhere: once
    its run has finished the entry, or a new run has taken over from a killed one, its writes are
    refused, and the entry gets no file, temporary, journal or (forced) folder of it."""
    def entry():
        return cache.entry(tmp_path, "dataset", "scene", {"a": 1}, {}, "cpu", module="pipeline.cache")

    first = entry()
    assert first.begin()
    ((folder, token),) = fencing.open_entries()
    assert _late_write(folder, token) == "", "a worker of the live run writes"
    assert first.path("views/late.bin").read_bytes() == b"late"
    written = first.path("views/late.bin").stat().st_ino
    assert _late_write(folder, token) == "", "and, while its run holds the entry, replaces its file"
    assert first.path("views/late.bin").stat().st_ino != written
    first.path("views/late.bin").unlink()
    assert _late_write(folder, token, "no-links") == "", "without hard links a worker renames"
    assert first.path("views/late.bin").read_bytes() == b"late"
    first.release()  # the driver is killed; a new run resumes the entry
    second = entry()
    assert second.begin()
    ((_, token2),) = fencing.open_entries()
    assert token2 != token
    first.path("views/late.bin").unlink()
    assert "another run has taken it over" in _late_write(folder, token)
    assert not first.path("views/late.bin").exists()
    second.finish([])
    assert "its run has finished" in _late_write(folder, token2)
    assert sorted(p.name for p in folder.rglob("*")) == ["manifest.json", "views"]

    forced = entry()
    assert forced.begin(force=True)
    ((building, token3),) = fencing.open_entries()
    assert building.name.startswith(f"{folder.name}.new-")
    forced.finish([])
    assert "its run has finished" in _late_write(building, token3)
    assert not building.exists(), "the late write made the swapped-in folder again"
    assert sorted(p.name for p in folder.parent.iterdir()) == [folder.name]


def test_cache_ls_lists_entries_only_and_clean_drops_the_staged_temporaries(tiny_dam, capsys):
    """``cache ls`` lists the stage entries, not the lock and staging folders beside them, and
    ``cache clean`` deletes the entries and the temporaries a write cut short left staged."""
    assert _run(tiny_dam) == 0
    data = tiny_dam.parent / "data"
    (entry,) = (data / "simulate").iterdir()
    left = data / ".staging" / "simulate" / entry.name / ".frame_0001.npz.tmp-1-2"  # a write killed after its run
    left.parent.mkdir(parents=True)
    left.write_bytes(b"half")
    capsys.readouterr()
    assert cli.main(["cache", "ls", "--config", str(tiny_dam)]) == 0
    listed = capsys.readouterr().out.splitlines()
    assert listed[0].split()[:2] == ["simulate", entry.name] and listed[0].split()[-1] == "complete"
    assert listed[1].startswith("1 entries")
    assert cli.main(["cache", "clean", "--config", str(tiny_dam)]) == 0
    assert not (data / "simulate").exists() and not (data / ".staging").exists()


def test_a_same_size_change_to_a_finished_entry_is_caught_without_verify(tmp_path, caplog):
    """A file written to after its entry finished (its time changed) is hashed on reuse: a change
    of the same size is found and redone though ``--verify`` is off."""
    caplog.set_level("WARNING")
    e = cache.entry(tmp_path, "render", "drop", {"a": 1}, {}, "cpu", "pipeline.cache")
    assert e.begin()
    e.path("frame.bin").write_bytes(b"0123456789" * 100)
    e.path("kept.bin").write_bytes(b"x" * 100)
    e.finish(["frame.bin", "kept.bin"])
    assert cache.VERIFY_HASHES is False and e.is_complete()
    os.utime(e.path("kept.bin"))  # a new time, the same bytes: still whole
    assert e.is_complete()
    data = bytearray(e.path("frame.bin").read_bytes())
    data[500] ^= 1
    e.path("frame.bin").write_bytes(bytes(data))
    assert not e.is_complete()
    assert "frame.bin is damaged (content differs from the recorded hash)" in caplog.text
    assert not e.path("frame.bin").exists() and e.path("kept.bin").exists()


def test_published_files_are_the_users_own(tmp_path):
    """A published output is a copy: damaging it leaves the cache's file whole; publishing again
    restores it, and leaves an untouched copy as it is."""
    source, target = tmp_path / "cache" / "frame.exr", tmp_path / "out" / "frame_0001.exr"
    source.parent.mkdir()
    source.write_bytes(b"exr" * 1000)
    cache.publish(source, target)
    assert target.read_bytes() == source.read_bytes() and not os.path.samefile(source, target)
    before = target.stat()
    cache.publish(source, target)  # an untouched copy is not made again
    assert (target.stat().st_ino, target.stat().st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
    target.write_bytes(b"EXR" * 1000)  # the user's edit, the same size
    assert source.read_bytes() == b"exr" * 1000
    cache.publish(source, target)
    assert target.read_bytes() == source.read_bytes()


def test_the_advice_for_a_damaged_file_is_the_command_that_wrote_it(tmp_path):
    stage = cache.redo_hint(tmp_path / "data" / "simulate" / "dam_break-0123abcd" / "frame_0003.npz")
    assert stage == "delete it or run `make simulate FORCE=1 SCENE=dam_break` (with the same CONFIG) to rebuild it"
    user = cache.redo_hint(tmp_path / "out" / ".cache" / "simulate" / "fluid-0123abcd" / "frame_0003.npz")
    assert f"`deep-ssfr render PATTERN --out {tmp_path / 'out'}` again with --force" in user and "make" not in user
