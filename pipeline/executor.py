"""Where per-frame work runs: in this process (``local``) or sharded over a Ray cluster (``ray``).

With ``ray`` every task runs in a worker process of the cluster named by ``ray_address`` (empty:
the one ``ray start`` made on this machine, else a local one for the run), and writes its files
straight into the stage's cache entry, so every node must see the same ``data_dir`` (shared
storage). The driver keeps the entry's lock and writes its manifest once all tasks are back; the
work is cut into one shard per CPU of the cluster, counted once joined. A task that runs long
(a slow or hung node) while a slot is free gets a backup copy, the first copy to finish winning
(:data:`BACKUP_FACTOR`). Work that is not cut into frames (a scene's simulation) runs one task an
item, asking for the CPUs it uses (``run_tasks(cpus=...)``).

On a GPU every task asks Ray for ``1 / TASKS_PER_GPU`` of one, and Ray gives it its own
(``CUDA_VISIBLE_DEVICES`` set to it, so it is the task's ``cuda:0``); the work is cut into
``TASKS_PER_GPU`` shards per GPU of the cluster instead of one per CPU. A task that asks for none is
given none: it sees every GPU of its node (Ray 2.60; none at all where
``RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO`` is set, as older Ray did by default), so one task per CPU would
crowd onto each node's first GPU while the others idle.
"""

from __future__ import annotations

import contextlib
import logging
import os
import statistics
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from tqdm import tqdm

from pipeline import fencing

log = logging.getLogger("deep_ssfr")
T = TypeVar("T")
R = TypeVar("R")

TASKS_PER_GPU = 1
"""Ray tasks sharing one GPU when the run's device is CUDA (each holds 1 / this of it)."""

RAY_KEEPALIVE = {"RAY_grpc_client_keepalive_time_ms": "60000", "RAY_grpc_client_keepalive_timeout_ms": "20000"}
"""The driver's gRPC keepalive, set (unless the environment sets it) before Ray is imported, which
reads it then. A node that hangs, or is cut off with no connection closed, leaves the driver
waiting on its tasks until a keepalive ping goes unanswered: 7 minutes with Ray's defaults (300 s,
then 120 s for the answer), about 100 s with these (measured), after which Ray runs the tasks again elsewhere.
Ray's servers refuse pings more often than once a minute (``too_many_pings``)."""


BACKUP_FACTOR = 2.0
"""A Ray task still running this many times the median time of the finished ones (and
:data:`BACKUP_MIN_S` at least), while a slot of the cluster is free, gets a backup copy: a slow or
hung node holds up the run only until the copy finishes elsewhere, rather than to the end of its
own work or until its connections are found dead. Tasks write the same bytes wherever they run,
so either copy's files will do. ``DEEP_SSFR_RAY_BACKUP_FACTOR`` sets it (``0``: no copies)."""

BACKUP_FACTOR_ENV = "DEEP_SSFR_RAY_BACKUP_FACTOR"
BACKUP_MIN_S = 10.0
"""No task gets a backup copy before it has run this long: a worker's start and imports take
seconds of their own, and short tasks cost more to copy than to wait for."""

BACKUP_POLL_S = 1.0
"""How often the driver looks for tasks to back up while it waits for them."""

CANCEL_WAIT_S = 10.0
"""How long the driver waits for a cancelled copy's worker to end before it finishes the stage's
entry (a copy on a hung node never ends: the run token keeps its writes out)."""


def _is_cuda(device: str) -> bool:
    return str(device).startswith("cuda")


def shards(items: Sequence[T], count: int) -> list[list[T]]:
    """``items`` cut into at most ``count`` contiguous, nearly equal, non-empty runs (in order)."""
    if not items:
        return []
    count = max(1, min(count, len(items)))
    bounds = [len(items) * k // count for k in range(count + 1)]
    return [list(items[bounds[k]:bounds[k + 1]]) for k in range(count)]


_SCOPES: list[contextlib.ExitStack] = []


@contextlib.contextmanager
def cluster_scope() -> Iterator[None]:
    """Ray started by work inside the block stays up until the block ends, rather than each call's
    end, so a stage's scenes, sequences and sizes share one cluster (the command line opens one a
    command)."""
    with contextlib.ExitStack() as stack:
        _SCOPES.append(stack)
        try:
            yield
        finally:
            _SCOPES.pop()


@contextlib.contextmanager
def connected(executor: str, address: str = "") -> Iterator[None]:
    """Ray joined for the block when ``executor`` is ``ray``: the cluster at ``address`` (or
    ``RAY_ADDRESS``; empty: the one ``ray start`` made on this machine, else a local one started
    here). Already connected, it stays so; inside a :func:`cluster_scope` its end disconnects."""
    if executor == "local":
        yield
        return
    if executor != "ray":
        raise ValueError(f"unknown executor {executor!r} (local or ray)")
    for name, value in RAY_KEEPALIVE.items():
        os.environ.setdefault(name, value)  # read once, when Ray is first imported
    try:
        import ray
    except ImportError:
        raise RuntimeError("executor 'ray' needs Ray: pip install 'deep-ssfr[scale]' (or ray)") from None
    if ray.is_initialized():
        yield
        return
    # no num_cpus: Ray refuses it when joining a cluster, and counts this machine's CPUs itself
    ray.init(address=address or os.environ.get("RAY_ADDRESS") or None, include_dashboard=False,
             configure_logging=False, log_to_driver=False, runtime_env={"env_vars": _worker_env()})
    if _SCOPES:
        _SCOPES[-1].callback(ray.shutdown)
        yield
        return
    try:
        yield
    finally:
        ray.shutdown()


def run_tasks(fn: Callable[[T], R], tasks: Sequence[T], executor: str = "local", address: str = "",
              device: str = "cpu", cpus: int = 1, backups: bool = True,
              on_result: Callable[[int, R], None] | None = None) -> list[R]:
    """``fn(task)`` for every task, results in task order: here one after another (``local``), or
    as Ray tasks (``ray``; ``fn`` and the tasks travel by cloudpickle, so closures over paths,
    configs and networks are fine, open devices and files are not). With a CUDA ``device`` each Ray
    task holds a share of one GPU, which it sees as ``cuda:0``; else ``cpus`` CPUs (at most the
    largest node's, so that every task fits somewhere). ``backups=False``: no backup copies
    (:data:`BACKUP_FACTOR`), for tasks whose time says nothing of the others'. ``on_result(k, r)``
    is called as each task's result arrives, while the others run (so that a driver killed later
    keeps what it did with the finished ones)."""
    if executor == "local":
        results = []
        for k, task in enumerate(tasks):
            results.append(fn(task))
            if on_result is not None:
                on_result(k, results[-1])
        return results
    factor = backup_factor() if backups else 0.0  # a bad setting is an error before the cluster is joined
    with connected(executor, address):
        import ray

        have = ray.cluster_resources()
        alive = [n for n in ray.nodes() if n.get("Alive")]
        where = address or os.environ.get("RAY_ADDRESS") or "this machine"
        if _is_cuda(device):
            if have.get("GPU", 0) < 1 / TASKS_PER_GPU:  # its tasks would wait for ever
                raise RuntimeError(f"the run's device is {device} but the Ray cluster at {where} has no GPU: "
                                   "start its nodes with --num-gpus, or run with DEEP_SSFR_DEVICE=cpu")
            options: dict[str, float] = {"num_gpus": 1 / TASKS_PER_GPU}
            each = f", {have.get('GPU', 0):g} GPUs, {1 / TASKS_PER_GPU:g} a task"
        else:
            largest = max((n.get("Resources", {}).get("CPU", 0) for n in alive), default=0)
            options = {"num_cpus": max(1, min(cpus, int(largest) or cpus))}
            if options["num_cpus"] < cpus:
                log.warning("ray: a task asks for %d CPUs and the largest node has %g: it gets those, and its %d "
                            "threads share them", cpus, largest, cpus)
            each = f", {options['num_cpus']:g} a task" if cpus != 1 else ""
        log.info("ray: %d tasks on %s (%d node%s, %g CPUs%s)", len(tasks), where, len(alive),
                 "s" * (len(alive) != 1), have.get("CPU", 0), each)
        entries = fencing.open_entries()

        def journaled(task: T) -> tuple[str, R]:  # a function, not a partial: ray.remote takes only functions
            return _journaled(fn, entries, task)

        remote = ray.remote(**options)(journaled)
        per = 1 if _is_cuda(device) else int(options["num_cpus"])
        return _gather(ray, lambda k: remote.remote(tasks[k]), len(tasks), where,
                       lambda: max(1, cluster_slots(executor, device, address) // per), factor, on_result)


def backup_factor() -> float:
    """:data:`BACKUP_FACTOR`, or ``DEEP_SSFR_RAY_BACKUP_FACTOR`` where set (``0``: no backup copies)."""
    text = os.environ.get(BACKUP_FACTOR_ENV, "")
    try:
        factor = float(text) if text else BACKUP_FACTOR
    except ValueError:
        factor = -1.0
    if not factor >= 0:
        raise ValueError(f"{BACKUP_FACTOR_ENV}={text!r}: a number, 0 or more (0 starts no backup copies)")
    return factor


def overdue(unfinished: Sequence[int], started: dict[int, float], took: Sequence[float], backed: set[int],
            slots: int, now: float, factor: float, floor: float = BACKUP_MIN_S) -> list[int]:
    """The tasks to give a backup copy now, the longest running first: of the first ``slots``
    ``unfinished`` ones (the others wait for a slot, so none is free), those without a copy yet that
    have run longer than ``factor`` times the median of the finished ones' times ``took`` (and
    ``floor`` seconds), as many as the slots that neither those tasks nor the copies already
    ``backed`` hold. ``started``: when each of the running ones was (or could have been) started."""
    if factor <= 0 or not took:
        return []
    running = list(unfinished[:slots])
    free = slots - len(running) - len(backed.intersection(unfinished))
    if free <= 0:
        return []
    limit = max(floor, factor * statistics.median(took))
    late = [k for k in running if k not in backed and now - started[k] > limit]
    return sorted(late, key=lambda k: started[k])[:free]


def _gather(ray: Any, submit: Callable[[int], Any], count: int, where: str, slots: Callable[[], int],
            factor: float, on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
    """The results of the ``count`` tasks ``submit(k)`` starts, in task order, as they finish (so
    that the bar moves and a failed task stops the run early). A task that runs long while the
    cluster has a free slot (:func:`overdue`) gets one backup copy; the first copy to finish gives
    the result, and the other is cancelled and waited for (:data:`CANCEL_WAIT_S` at most), so that no copy
    writes once the stage finishes its entry. A copy's loss (its node or worker gone, retries spent)
    ends the run only when no other copy of its task is left. ``on_result(k, result)`` is called
    as task ``k``'s first copy finishes (a cancelled copy of it may still be ending then)."""
    copies = {k: [submit(k)] for k in range(count)}
    task_of = {copies[k][0]: k for k in range(count)}
    results: list[Any] = [None] * count
    ran_on: Counter[str] = Counter()
    unfinished = list(range(count))
    now = time.monotonic()
    started = {k: now for k in unfinished[:slots()]}  # when each task was (or could have been) started
    backups: dict[Any, float] = {}  # every backup copy, and when it was started
    took: list[float] = []
    cancelled: list[Any] = []
    won = 0
    with tqdm(total=count, desc="ray tasks", unit="task", leave=False) as bar:
        while unfinished:
            done, _ = ray.wait(list(task_of), num_returns=1, timeout=BACKUP_POLL_S if factor > 0 else None)
            now = time.monotonic()
            for ref in done:
                k = task_of.pop(ref)
                backup = ref in backups
                copies[k].remove(ref)
                try:
                    node, results[k] = ray.get(ref)
                except ray.exceptions.RayError as exc:
                    if copies[k] and not isinstance(exc, ray.exceptions.RayTaskError):
                        log.warning("ray: a copy of task %d of %d was lost (%s); its other copy goes on",
                                    k + 1, count, _first_line(exc))
                        continue
                    _raise(ray, exc, where)
                for other in copies.pop(k):  # the task's other copy, still running or waiting
                    with contextlib.suppress(ray.exceptions.RayError):
                        ray.cancel(other, force=True)
                    task_of.pop(other)
                    cancelled.append(other)
                won += backup
                if backup or k in started:  # not one that ran outside the slots counted
                    took.append(now - (backups[ref] if backup else started[k]))
                unfinished.remove(k)
                ran_on[node] += 1
                bar.update()
                if on_result is not None:
                    on_result(k, results[k])
            if factor <= 0 or not took:
                continue
            n = slots()  # nodes may have joined or died
            for k in unfinished[:n]:
                started.setdefault(k, now)
            live = {task_of[ref] for ref in backups if ref in task_of}
            for k in overdue(unfinished, started, took, live, n, now, factor):
                log.info("ray: task %d of %d has run %.0f s, over %g times the %.1f s median of the finished "
                         "ones: a backup copy started", k + 1, count, now - started[k], factor,
                         statistics.median(took))
                ref = submit(k)
                copies[k].append(ref)
                task_of[ref] = k
                backups[ref] = now
    if cancelled:  # a force-cancelled copy's worker is killed; its file written or not, none after this
        _, left = ray.wait(cancelled, num_returns=len(cancelled), timeout=CANCEL_WAIT_S)
        if left:
            log.warning("ray: %d cancelled %s did not end within %g s (on a hung node?); once the entry is "
                        "finished, %s writes are refused", len(left), _copies(len(left)), CANCEL_WAIT_S,
                        "its" if len(left) == 1 else "their")
    if backups:
        log.info("ray: %d backup %s, %d of them finished first", len(backups), _copies(len(backups)), won)
    log.info("ray: the tasks ran on %s", ", ".join(f"{node} ({n})" for node, n in sorted(ran_on.items())))
    return results


def _copies(n: int) -> str:
    return "copy" if n == 1 else "copies"


def _raise(ray: Any, exc: Exception, where: str) -> None:
    """A task's failure raised as a local run's would be, so that the stage's one-line error says
    what went wrong rather than the remote traceback (``DEEP_SSFR_DEBUG=1`` shows it, chained), and
    Ray's own failures (retries spent on lost nodes) as one line too."""
    if isinstance(exc, ray.exceptions.RayTaskError):
        if isinstance(exc.cause, Exception):
            raise exc.cause from exc
        raise RuntimeError(f"a Ray task on {where} failed: {_first_line(exc)}") from exc
    raise RuntimeError(f"a Ray task on {where} failed ({type(exc).__name__}: {_first_line(exc)}); the "
                       "files it finished are kept and a re-run resumes") from exc


def _first_line(exc: BaseException) -> str:
    """The first non-empty line of ``exc``'s message (Ray's run to many lines)."""
    return next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)


def run_sharded(fn: Callable[[list[int]], R], count: int, executor: str, address: str = "",
                device: str = "cpu") -> list[R]:
    """``fn`` over ``range(count)`` cut into one contiguous shard per slot (:func:`cluster_slots`) of
    the cluster it runs on, counted once connected: the driver's own CPUs say nothing of a cluster's."""
    with connected(executor, address):
        parts = shards(list(range(count)), cluster_slots(executor, device, address))
        return run_tasks(fn, parts, executor, address, device)


def cluster_slots(executor: str, device: str = "cpu", address: str = "") -> int:
    """How many tasks to cut the work into: the CPUs of this machine or of the Ray cluster (joined
    for the count if need be), or on a CUDA ``device`` ``TASKS_PER_GPU`` per GPU of it."""
    resource = "GPU" if _is_cuda(device) else "CPU"
    per = TASKS_PER_GPU if resource == "GPU" else 1
    if executor == "ray":
        with connected(executor, address):
            import ray

            return max(1, int(ray.cluster_resources().get(resource, 1) * per))
    if resource == "GPU":
        import torch

        return max(1, torch.cuda.device_count() * per)
    return os.cpu_count() or 1


def _journaled(fn: Callable[[T], R], entries: list[tuple[Any, str]], task: T) -> tuple[str, R]:
    """``fn(task)`` in a Ray worker, with the address of the node it ran on; its finished files
    inside the driver's open cache entries journaled there (:func:`pipeline.fencing.journal_into`), so
    a resume after a kill checks them, and refused once the driver's run no longer holds them (a
    worker on a cut-off node that outlives it)."""
    import ray

    with fencing.journal_into(entries):
        return ray.util.get_node_ip_address(), fn(task)


def _worker_env() -> dict[str, Any]:
    """The environment variables a worker needs to behave like this process: every ``DEEP_SSFR_``
    setting (device, logs, EXR threads, synchronised timers), GL's platform and the import path."""
    return {k: v for k, v in os.environ.items()
            if k.startswith("DEEP_SSFR_") or k in ("PYOPENGL_PLATFORM", "PYTHONPATH")}
