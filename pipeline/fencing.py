"""Writes into an open cache entry, from its own process or from workers on other nodes: staged,
journaled and fenced.

Design. The run that begins an entry holds its lock and writes a fresh run token into it
(``RUN_TOKEN``). Workers it starts (Ray tasks, perhaps on other nodes over a shared file system)
join the entry with that token (:func:`journal_into`). Every write goes through :func:`atomic_path`,
which guards against the three failures a cluster run meets, each tested in ``tests/test_cache.py``
and ``tests/test_multinode.py``:

- a kill mid-write: the temporary is staged outside the entry and renamed into place only whole;
- a resume after a kill: each finished file's size and hash go to a journal, one a process (appends
  from several NFS clients can interleave), which the next ``begin`` checks, so finished files are
  kept and damaged ones redone;
- a worker that outlives its run (its node cut off or frozen, its task run again elsewhere by Ray):
  it writes nothing more once the token has changed or gone, checked before and after each write,
  and it places files by hard link, which never replaces a file a newer run wrote.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import logging
import os
import secrets
import threading
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger("deep_ssfr")
TMP_MARK = ".tmp-"
"""Marks a temporary file's name: whatever carries it was never finished."""


HASH = "sha256"
"""The hash the journals and manifests record of each file (their key for it): SHA-256, which the
SHA extensions of current x86 and ARM CPUs compute at twice BLAKE2b's speed (24 MB: 13 against 25
ms on the development machine)."""


def file_hash(path: Path) -> str:
    """The :data:`HASH` of a file's bytes: what ``--verify`` compares with the manifest."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


JOURNAL = "journal.jsonl"
"""The journal of the process that opened an entry; each worker process of a Ray run keeps its own
beside it (``journal-<host>-<pid>-<random>.jsonl``), since appends from several NFS clients can interleave."""
RUN_TOKEN = ".run-token"
"""The token of the run that holds an entry, from ``begin`` to ``finish``: its workers' writes check
it, so a worker that outlives its run (on a cut-off node, its task already run again elsewhere)
writes nothing more into the entry."""


@dataclass(frozen=True)
class _Open:
    """An entry this process writes into: its journal, and the run token its writes need."""

    lock: threading.Lock
    journal: str
    token: str
    owner: bool
    """This process began the entry (and holds its lock); else it is a worker writing into another's."""


_OPEN_ENTRIES: dict[Path, _Open] = {}  # the folders of the entries this process writes into


class StaleWrite(RuntimeError):
    """A worker's write into an entry whose run has finished or given way to another run."""


def _holder(target: Path) -> tuple[Path, _Open] | None:
    """The open entry whose folder holds ``target`` (a resolved path), if any."""
    for folder, state in list(_OPEN_ENTRIES.items()):
        if folder in target.parents:
            return folder, state
    return None


def _fence(held: tuple[Path, _Open] | None, target: Path) -> None:
    """Refuse a worker's write into an entry that its run no longer holds: the entry's run token is
    gone (finished; a forced run's folder swapped in) or another's (the driver was killed and a new
    run resumed). The owner's writes pass: it holds the lock."""
    if held is None or held[1].owner:
        return
    folder, state = held
    try:
        token = (folder / RUN_TOKEN).read_text()
    except FileNotFoundError:
        token = ""
    if token != state.token:
        why = "another run has taken it over" if token else "its run has finished"
        raise StaleWrite(f"{target}: not written, since {why} (a worker that outlived its run, its task "
                         "run again elsewhere)")


def _journal(held: tuple[Path, _Open] | None, target: Path) -> None:
    """Append a finished file's size, modification time and hash (``target``, a resolved path) to
    the journal of the open entry that holds it, so a resumed run can check the files of an
    unfinished entry as the manifest checks a finished one, and the manifest takes the hash from
    here rather than reading every file again."""
    if held is None:
        return
    folder, state = held
    stat = target.stat()
    line = json.dumps({"file": str(target.relative_to(folder)), "size": stat.st_size,
                       "mtime_ns": stat.st_mtime_ns, HASH: file_hash(target)})
    if state.owner:
        with state.lock, open(folder / state.journal, "a") as fh:
            fh.write(line + "\n")
        return
    # A worker's journal was made when it joined (journal_into) and is only appended to: one frozen
    # after placing a file, thawed once its run finished or a new run took over (either drops the
    # workers' journals), makes none anew in the finished entry: its record is refused instead.
    try:
        fd = os.open(folder / state.journal, os.O_WRONLY | os.O_APPEND)
    except FileNotFoundError:
        raise StaleWrite(f"{target}: not journaled, since its run has finished or been taken over (a worker "
                         "that outlived its run)") from None
    with state.lock, os.fdopen(fd, "a") as fh:
        fh.write(line + "\n")


def _journals(folder: Path) -> list[Path]:
    """An entry's journals, the opener's first and then the workers' by age (a later record of a
    file wins)."""
    workers = sorted(folder.glob("journal-*.jsonl"), key=lambda p: (p.stat().st_mtime_ns, p.name))
    return [p for p in [folder / JOURNAL] if p.exists()] + workers


@functools.cache
def _process_tag() -> str:
    """This process's name among a cluster's: host, pid and a random part (containers on several
    nodes may share a host name and pid)."""
    import socket

    return f"{socket.gethostname()}-{os.getpid()}-{secrets.token_hex(4)}"


def close(folder: Path) -> None:
    """Stop writing into the open entry at ``folder``: no more journal records, and, where this
    process began it, its run token removed, so that its workers write nothing more there."""
    state = _OPEN_ENTRIES.pop(folder, None)
    if state is not None and state.owner:
        (folder / RUN_TOKEN).unlink(missing_ok=True)


def claim(folder: Path) -> str:
    """Give the entry at ``folder`` a fresh run token, which this process opens it with
    (:func:`open_entry`): from now on a worker of an earlier, killed run writes nothing there."""
    token = secrets.token_hex(8)
    with atomic_path(folder / RUN_TOKEN) as tmp:
        tmp.write_text(token)
    return token


def open_entry(folder: Path, token: str) -> None:
    """Write into the entry at ``folder`` as the run that holds it: finished files go to its journal."""
    _OPEN_ENTRIES[folder.resolve()] = _Open(threading.Lock(), JOURNAL, token, owner=True)


def journal_records(folder: Path) -> dict[str, dict]:
    """The files an unfinished entry's journals record (a later record of a file wins), by name."""
    records: dict[str, dict] = {}
    for journal in _journals(folder):
        for line in journal.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut short by a kill: its file is checked by the stage
            records[rec["file"]] = rec
    return records


def rewrite_journal(folder: Path, records: dict[str, dict]) -> None:
    """One journal in place of all of an entry's, of ``records`` (the files that passed their
    check), so that the next resume reads them in order."""
    journals = _journals(folder)
    if not journals:
        return
    tmp = folder / f".{JOURNAL}{TMP_MARK}{os.getpid()}"
    tmp.write_text("".join(json.dumps(r) + "\n" for r in records.values()))
    os.replace(tmp, folder / JOURNAL)
    for worker in journals:
        if worker.name != JOURNAL:
            worker.unlink()


def drop_journals(folder: Path) -> None:
    """Delete an entry's journals (its manifest now records the files)."""
    for journal in _journals(folder):
        journal.unlink()


def open_entries() -> list[tuple[Path, str]]:
    """The folders of the entries this process has begun and not finished, with their run tokens
    (for :func:`journal_into` in the workers it starts)."""
    return [(folder, state.token) for folder, state in _OPEN_ENTRIES.items() if state.owner]


@contextmanager
def journal_into(entries: list[tuple[Path, str]]) -> Iterator[None]:
    """Write into ``entries`` (folders and run tokens from :func:`open_entries`), entries another
    process opened (a Ray task writing into its driver's entry): the files finished there go into a
    journal of this process's own, so a resumed run checks them as it checks the driver's, and none
    is written once the entry's run no longer holds it (:data:`RUN_TOKEN`)."""
    mine = [(Path(f), token) for f, token in entries if Path(f) not in _OPEN_ENTRIES]
    name = f"journal-{_process_tag()}.jsonl"
    for folder, token in mine:
        state = _OPEN_ENTRIES[folder] = _Open(threading.Lock(), name, token, owner=False)
        with suppress(StaleWrite):  # a run already over: the writes are refused one by one
            _join((folder, state))
    try:
        yield
    finally:
        for folder, _ in mine:
            _OPEN_ENTRIES.pop(folder, None)


def _join(held: tuple[Path, _Open]) -> None:
    """Make a worker's journal in the entry it joins, the only place one is made (``_journal`` only
    appends), and only while the entry's run holds it: checked before and again after, since a worker
    frozen between the first check and the file, thawed once its run finished (the workers' journals
    dropped), would otherwise leave an empty journal in the finished entry."""
    folder, state = held
    journal = folder / state.journal
    _fence(held, folder)
    try:
        journal.touch()
    except FileNotFoundError:  # the folder of a forced run, swapped in meanwhile
        _fence(held, folder)
        raise
    try:
        _fence(held, folder)
    except StaleWrite:
        journal.unlink(missing_ok=True)
        raise


def staging(folder: Path) -> Path:
    """Where the writes into the open entry at ``folder`` keep their temporaries until the rename:
    beside the stage folders (``<root>/.staging/<stage>/<entry>/``), on the entry's file system but
    outside every entry, so a write that is refused or cut short leaves the entry as it was."""
    return folder.parent.parent / ".staging" / folder.parent.name / folder.name


_MKDIR_TRIES = 20
"""Each retry of :func:`_make_folder` means another run emptied and dropped a parent in the
instant between two mkdirs: a handful in a row is already unlikely."""


def make_folder(folder: Path) -> None:
    """``folder`` and its parents, made again where another run removed an empty parent between
    two of the steps (a run that finishes an entry of the same stage drops ``.staging/<stage>/``
    once it is empty: :meth:`CacheEntry._drop_temporaries`)."""
    for _ in range(_MKDIR_TRIES - 1):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            return
        except FileNotFoundError:
            continue
    folder.mkdir(parents=True, exist_ok=True)


def _place(tmp: Path, target: Path, held: tuple[Path, _Open] | None) -> None:
    """Put a finished temporary at ``target``. A worker links it there, which never replaces a file:
    one frozen between its last check and here, thawed as its run finishes, finds the file its task
    run again elsewhere wrote and is refused, leaving that file as it was. Only a file already there
    while its run still holds the entry (a frame half done before a kill) is replaced."""
    if held is None or held[1].owner:
        os.replace(tmp, target)
        return
    try:
        os.link(tmp, target)
    except FileExistsError:
        _fence(held, target)
        os.replace(tmp, target)
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP):
            raise
        os.replace(tmp, target)  # a file system without hard links
    else:
        tmp.unlink()


@contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """Yield a temporary path; on success put it at ``target`` (:func:`_place`), else delete it.
    Outside an open entry the temporary is a sibling; inside one it is staged outside the entry, so a
    frozen worker thawed after its run finished leaves nothing in the finished entry. Inside an
    entry another process opened, the write is refused
    (:class:`StaleWrite`) once that run no longer holds it, checked before the write and again
    before the file is put in place, and the target's folder is made only after the second check."""
    target = Path(target)
    where = target.resolve()
    held = _holder(where)
    _fence(held, target)
    if held is None:
        home, name = target.parent, target.name
    else:  # the path inside the entry in the name, so that two targets of one name stay apart
        home, name = staging(held[0]), "%".join(where.relative_to(held[0]).parts)
    make_folder(home)
    tmp = home / f".{name}{TMP_MARK}{os.getpid()}-{threading.get_ident()}"
    try:
        yield tmp
        _fence(held, target)
        target.parent.mkdir(parents=True, exist_ok=True)
        _place(tmp, target, held)
        _journal(held, where)
        log.debug("wrote %s", target)  # one event per finished file (tests kill runs on them)
    except OSError as exc:
        try:  # a write whose run finished meanwhile, its staged temporaries dropped, is refused
            _fence(held, target)
        except StaleWrite as stale:
            raise stale from exc
        if exc.filename is None:  # a writer that does not say which file: this one
            raise OSError(exc.errno, exc.strerror or str(exc), str(target)) from exc
        raise
    finally:
        if tmp.exists():
            tmp.unlink()


