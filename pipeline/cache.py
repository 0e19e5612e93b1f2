"""Stage cache: content-keyed folders under ``data/<stage>/<name>-<key>/`` with a JSON manifest.

A key hashes the stage's resolved config fields, its inputs' keys, the device and a hash of the
source files the stage runs, so editing a kernel, changing a parameter or changing an upstream
result each lead to a new entry, while untouched upstream entries stay hits. Every file is written
to a temporary name and renamed (``atomic_path``), so a killed stage leaves only whole files;
per-frame outputs let it resume, and the manifest (written last) marks the entry complete. How
writes from several processes and nodes stay safe is :mod:`pipeline.fencing`'s concern.
"""

from __future__ import annotations

import ast
import contextlib
import errno
import functools
import hashlib
import importlib.util
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline import fencing
from pipeline.fencing import HASH, TMP_MARK, atomic_path, file_hash

log = logging.getLogger("deep_ssfr")
MANIFEST = "manifest.json"
_HELD: set[Any] = set()  # the entry locks (filelock.FileLock) this process holds


class CacheError(RuntimeError):
    """A cache file is missing or unreadable; the message names the file."""


PROJECT_PACKAGES = ("pipeline", "stages")


@functools.cache
def import_closure(module: str) -> tuple[str, ...]:
    """The project modules ``module`` imports, directly or through others (itself included): the
    code its results depend on, so a cache key over them cannot go stale when one of them changes.

    Read from the source (``ast``), imports inside functions included; packages count with their
    ``__init__``; anything outside ``pipeline`` and ``stages`` (numpy, warp, torch) is left out, and
    so is a module's ``if __name__ == "__main__":`` block (how it is started, not what it computes).
    Each source's imports are kept in ``IMPORTS_CACHE`` by the hash of its text."""
    known = _read_imports_cache()
    size = len(known)
    seen: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen or name.split(".")[0] not in PROJECT_PACKAGES:
            continue
        origin = module_file(name)
        if origin is None:  # "pkg.module.function": not a module
            continue
        seen.add(name)
        parts = name.split(".")
        package = parts if origin.name == "__init__.py" else parts[:-1]
        todo += [".".join(parts[:k]) for k in range(1, len(parts))]  # parent packages' __init__
        todo += _imports(origin, package, known)
    if len(known) > size:
        _write_imports_cache(known)
    return tuple(sorted(seen))


IMPORTS_CACHE = Path(os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")) / "deep-ssfr" / "imports.json"
"""Where ``import_closure`` keeps each source's imports, by the hash of its text and its package:
parsing every project module took 0.3-0.6 s of each command's start. Not used where there is no
home folder to put it in (the path is then relative)."""

IMPORTS_CACHE_SIZE = 2000
"""Most sources kept in ``IMPORTS_CACHE`` (the oldest go first): edits add versions."""


def _imports(origin: Path, package: list[str], known: dict[str, list[str]]) -> list[str]:
    """The names a source's import statements name (``import_closure``'s reading of them), from
    ``known`` when this text in this package was read before (added to it otherwise)."""
    text = origin.read_bytes()
    key = f"{hashlib.sha256(text).hexdigest()[:24]}:{'.'.join(package)}"
    if key not in known:
        tree = ast.parse(text, str(origin))
        tree.body = [n for n in tree.body if not _is_main_guard(n)]
        names: list[str] = []
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names += [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else [])) \
                    if node.level else (node.module or "")
                names += [base] + [f"{base}.{a.name}" for a in node.names]
        known[key] = names
    return known[key]


def _read_imports_cache() -> dict[str, list[str]]:
    """``IMPORTS_CACHE``'s entries; none when it is missing or unreadable (it is only a shortcut)."""
    if not IMPORTS_CACHE.is_absolute():
        return {}
    try:
        known = json.loads(IMPORTS_CACHE.read_text())
    except (OSError, ValueError):
        return {}
    return known if isinstance(known, dict) else {}


def _write_imports_cache(known: dict[str, list[str]]) -> None:
    """Keep the newest ``IMPORTS_CACHE_SIZE`` entries, through a temporary file; nothing where the
    folder cannot be written."""
    if not IMPORTS_CACHE.is_absolute():
        return
    keep = dict(list(known.items())[-IMPORTS_CACHE_SIZE:])  # in insertion order: not write_json_atomic's sorted keys
    with contextlib.suppress(OSError), atomic_path(IMPORTS_CACHE) as tmp:
        tmp.write_text(json.dumps(keep))


def module_file(name: str) -> Path | None:
    """The source file of project module ``name`` (``pkg/mod.py`` or ``pkg/mod/__init__.py``),
    found on disk next to its top-level package without importing it (importing would load Warp
    and torch just to hash the code), or None when ``name`` is not a module."""
    spec = importlib.util.find_spec(name.split(".")[0])  # the top-level package alone: no heavy imports
    if spec is None or not spec.submodule_search_locations:
        return None
    base = Path(next(iter(spec.submodule_search_locations))).joinpath(*name.split(".")[1:])
    for candidate in (base / "__init__.py", base.with_suffix(".py")):
        if candidate.is_file():
            return candidate
    return None


def _is_main_guard(node: ast.stmt) -> bool:
    """``if __name__ == "__main__":`` at module level."""
    test = getattr(node, "test", None)
    return (isinstance(node, ast.If) and isinstance(test, ast.Compare) and isinstance(test.left, ast.Name)
            and test.left.id == "__name__" and any(getattr(c, "value", None) == "__main__" for c in test.comparators))


@functools.cache
def code_version(stage_module: str) -> str:
    """Hash of the source of every project module ``stage_module`` imports (``import_closure``);
    computed once per process (stages ask for entries many times, the source does not change)."""
    digest = hashlib.sha256()
    for name in import_closure(stage_module):
        digest.update(name.encode())
        digest.update(module_file(name).read_bytes())
    return digest.hexdigest()[:16]


def make_key(payload: dict[str, Any]) -> str:
    """Stable short hash of a JSON-able payload."""
    blob = json.dumps(payload, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def write_json_atomic(path: Path, payload: Any) -> None:
    """Write JSON through a temporary file and rename."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(payload, indent=2, sort_keys=True, default=str))


STAGES = ("simulate", "dataset", "train", "render", "evaluate")

# Check the recorded hash of every output of a finished entry, not only its size (``--verify``).
VERIFY_HASHES = False


def write_failure(folder: Path, fallback: str) -> tuple[int, str]:
    """(errno, reason) for a writer that failed without saying why (OpenEXR, ffmpeg): a full disk,
    a folder that cannot be written, else ``fallback``."""
    try:
        if shutil.disk_usage(folder).free < 2**20:
            return errno.ENOSPC, "No space left on device"
    except OSError:
        pass
    if not os.access(folder, os.W_OK):
        return errno.EROFS, "the folder is not writable (read-only file system or permissions)"
    return errno.EIO, fallback


def redo_hint(path: str | Path) -> str:
    """What to run to rebuild the cache entry holding ``path``: a stage writes
    ``<data>/<stage>/<scene>-<key>/...``, so the command is ``make <stage> FORCE=1 SCENE=<scene>``;
    ``deep-ssfr render PATTERN --out OUT`` keeps its cache in ``OUT/.cache``, and is run again."""
    parts = Path(path).parts
    for i, part in enumerate(parts[:-1]):
        if part in STAGES and i > 0 and parts[i - 1] == ".cache":
            return (f"delete it or run the same `deep-ssfr render PATTERN --out {Path(*parts[:i - 1])}` again "
                    f"with --force to rebuild it")
        if part in STAGES and i + 1 < len(parts):
            name = parts[i + 1].rsplit("-", 1)[0]
            scene = f" SCENE={name}" if part in ("simulate", "dataset", "render") else ""
            return f"delete it or run `make {part} FORCE=1{scene}` (with the same CONFIG) to rebuild it"
    return "delete it and run the stage that wrote it again"


def read_json(path: Path) -> Any:
    """Read a JSON cache file, naming the file when it is corrupt."""
    try:
        return json.loads(Path(path).read_text())
    except json.JSONDecodeError as exc:
        raise CacheError(f"corrupt cache file {path}: {exc}; {redo_hint(path)}") from None


@dataclass
class CacheEntry:
    """One stage output folder."""

    root: Path
    stage: str
    name: str
    key: str
    meta: dict[str, Any]

    building: Path | None = None
    """Where a forced rebuild writes until ``finish`` swaps it in for the old entry."""
    held: Any = None
    """This run's lock on the entry (a ``filelock.FileLock``) between ``begin`` and ``finish``."""

    @property
    def final_dir(self) -> Path:
        """The entry's folder (``<root>/<stage>/<name>-<key>``)."""
        return self.root / self.stage / f"{self.name}-{self.key}"

    @property
    def dir(self) -> Path:
        """Where the entry's files are: the folder, or its rebuild while a forced run writes it."""
        return self.building or self.final_dir

    @property
    def lock_path(self) -> Path:
        """The entry's lock file, outside every stage folder (``<root>/.locks/<stage>/``)."""
        return self.root / ".locks" / self.stage / f"{self.final_dir.name}.lock"

    def path(self, filename: str) -> Path:
        """Path of a file inside the entry."""
        return self.dir / filename

    def is_complete(self) -> bool:
        """True when the stage finished (its manifest exists) and every output it recorded is still
        whole: the recorded size always, the recorded hash too with ``--verify``. A bad file
        is deleted with the manifest and named in the log, so the stage's resume redoes just it."""
        if not (self.dir / MANIFEST).exists():
            return False
        if not self._drop_damaged(self.manifest().get("checks", {})):
            return True
        (self.dir / MANIFEST).unlink()
        return False

    def manifest(self) -> dict[str, Any]:
        """The manifest of a complete entry."""
        return read_json(self.dir / MANIFEST)

    def begin(self, force: bool = False, reopen: bool = False) -> bool:
        """Claim the entry for this run and prepare its folder; False (and nothing claimed) when it
        is complete already, perhaps finished by another run this one waited for.

        One run works in an entry at a time: a lock beside the folder is held until ``finish`` (or
        the process ends), so concurrent runs of one config wait and then find the work done. The
        folder's temporaries of a killed run are dropped, and the files its journal recorded are
        checked (a size or, with ``--verify``, a hash that differs is deleted, so the resume redoes
        it). ``force`` builds a new folder beside the old one, which stays whole and readable until
        ``finish`` swaps them; ``reopen`` claims a complete entry to add to it (more epochs)."""
        self._lock()
        if not force and not reopen and self.is_complete():
            self.release()
            return False
        if force:
            for old in self.final_dir.parent.glob(f"{self.final_dir.name}.new-*"):
                shutil.rmtree(old)  # a killed forced run's half-built folder
            self.building = self.final_dir.with_name(f"{self.final_dir.name}.new-{os.getpid()}")
        self.dir.mkdir(parents=True, exist_ok=True)
        token = fencing.claim(self.dir)
        self._drop_temporaries()
        records = fencing.journal_records(self.dir)
        self._drop_damaged(records)
        fencing.rewrite_journal(self.dir, {n: r for n, r in records.items() if (self.dir / n).exists()})
        fencing.open_entry(self.dir, token)
        return True

    def _lock(self) -> None:
        """Take the entry's lock, saying so when another run holds it."""
        import filelock

        self.lock_path.parent.mkdir(parents=True, exist_ok=True)
        lock = self.held or filelock.FileLock(self.lock_path, thread_local=False)
        try:
            lock.acquire(timeout=0)
        except filelock.Timeout:
            log.info("%s %s: another run is writing %s; waiting for it", self.stage, self.name, self.final_dir)
            lock.acquire()
        self.held = lock
        _HELD.add(lock)

    def release(self) -> None:
        """Give up the entry's lock (``finish`` does; a stage that stops early may): the files this
        process writes there from now on are no longer journaled, and its workers' are refused."""
        fencing.close(self.dir.resolve())
        if self.held is not None:
            self.held.release(force=True)
            _HELD.discard(self.held)
            self.held = None

    def _drop_temporaries(self) -> None:
        """Delete the entry's temporary files, staged (:func:`pipeline.fencing.staging`) and in the folder: a killed
        run's or worker's, never a live one's, since the caller holds the entry's lock and no write
        of its own is under way. The staging folders above it go too once empty: ``rmdir`` drops
        only an empty folder, so another entry's staged files keep theirs, and a run making its own
        in between makes the parents again (:func:`pipeline.fencing.make_folder`)."""
        staged = fencing.staging(self.dir.resolve())
        shutil.rmtree(staged, ignore_errors=True)
        for parent in (staged.parent, staged.parent.parent):  # .staging/<stage>/, then .staging/
            try:
                parent.rmdir()
            except OSError:  # not empty (another entry's writes), or gone already
                break
        for stale in self.dir.rglob(f"*{TMP_MARK}*"):
            stale.unlink(missing_ok=True)

    def _drop_damaged(self, checks: dict[str, dict]) -> bool:
        """Delete (and name in the log) the recorded files that are missing or differ in size (or
        hash, with --verify), so the stage's resume redoes them; True when there were any."""
        bad = []
        for name, want in checks.items():
            path = self.dir / name
            if not path.exists():
                bad.append((name, "missing"))
                continue
            stat = path.stat()
            touched = "mtime_ns" in want and stat.st_mtime_ns != want["mtime_ns"]  # written to since: hash it
            if stat.st_size != want["size"]:
                bad.append((name, f"{stat.st_size} bytes, {want['size']} recorded"))
            elif (VERIFY_HASHES or touched) and file_hash(path) != want.get(HASH):
                bad.append((name, "content differs from the recorded hash"))
        for name, why in bad:
            log.warning("%s %s: %s is damaged (%s); redoing it", self.stage, self.name, self.dir / name, why)
            (self.dir / name).unlink(missing_ok=True)
        return bool(bad)

    def finish(self, files: list[str], timings: dict | None = None, **extra: Any) -> None:
        """Write the manifest last: config, inputs, code version, timings and files."""
        fencing.close(self.dir.resolve())  # first: the run's workers write nothing more here
        journaled = fencing.journal_records(self.dir)
        payload = {
            "stage": self.stage,
            "name": self.name,
            "key": self.key,
            **self.meta,
            "files": sorted(files),
            "checks": {f: _check_of(self.dir / f, journaled.get(f)) for f in sorted(files)},
            "timings": timings or {},
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
            **extra,
        }
        write_json_atomic(self.dir / MANIFEST, payload)
        fencing.drop_journals(self.dir)
        self._drop_temporaries()  # of workers killed mid-write (a lost Ray node's, its task run again)
        if self.building is not None:  # swap the rebuilt folder in; readers saw the old one until now
            old = self.final_dir.with_name(f"{self.final_dir.name}.old-{os.getpid()}")
            if self.final_dir.exists():
                os.replace(self.final_dir, old)
            os.replace(self.building, self.final_dir)
            self.building = None
            shutil.rmtree(old, ignore_errors=True)
        self.release()


def release_all() -> None:
    """Give up every entry lock this process holds (a stage that failed half way holds its own)."""
    for folder, _ in fencing.open_entries():
        fencing.close(folder)
    for lock in list(_HELD):
        lock.release(force=True)
    _HELD.clear()


def entry(root: Path, stage: str, name: str, config: Any, inputs: dict[str, str], device: str,
          module: str = "") -> CacheEntry:
    """The cache entry of ``stage`` for ``name`` given its config fields, inputs and code (the source
    of ``module``, by default ``stages.<stage>``, and of every project module it imports)."""
    code = code_version(module or f"stages.{stage}")
    meta = {"config": config, "inputs": inputs, "code_version": code, "device": device}
    return CacheEntry(Path(root), stage, name, make_key(meta), meta)


def _check_of(path: Path, journaled: dict | None = None) -> dict[str, Any]:
    """What a manifest records of an output: size and modification time (checked on every reuse; a
    changed time has the file hashed) and its hash, the one its ``journaled`` record took as
    it was written when the file still has that record's size and time (a 1M-particle frame's copy
    is 24 MB: 30 ms of hashing saved a frame)."""
    stat = path.stat()
    check = {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns}
    same = journaled is not None and HASH in journaled and all(journaled.get(k) == v for k, v in check.items())
    return {**check, HASH: journaled[HASH] if same else file_hash(path)}


def publish(source: Path, target: Path) -> None:
    """Copy a finished cache file to ``target`` (a user's output folder), atomically: the user's file
    is their own, so editing or damaging it leaves the cache whole, and the other way round. A
    target with the source's size and modification time (a copy made before) is left as it is."""
    source, target = Path(source), Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    have, want = (target.stat() if target.exists() else None), source.stat()
    if have is not None and (have.st_size, have.st_mtime_ns) == (want.st_size, want.st_mtime_ns):
        return
    tmp = target.with_name(f".{target.name}{TMP_MARK}{os.getpid()}")
    try:
        shutil.copy2(source, tmp)  # the time too, so an untouched copy is recognised next time
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def list_entries(root: Path) -> list[dict[str, Any]]:
    """Every entry under ``root`` with its size and state, for ``make cache-ls``."""
    rows = []
    root = Path(root)
    if not root.exists():
        return rows
    for stage_dir in sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")):
        for d in sorted(p for p in stage_dir.iterdir() if p.is_dir()):
            size = sum(f.stat().st_size for f in d.rglob("*") if f.is_file())
            rows.append({"stage": stage_dir.name, "entry": d.name, "bytes": size,
                         "complete": (d / MANIFEST).exists(),
                         "files": sum(1 for f in d.rglob("*") if f.is_file())})
    return rows
