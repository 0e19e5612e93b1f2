"""Chunked Warp launches over the CPU cores.

Warp runs a CPU launch on one core but releases the GIL, so launching disjoint chunks of a kernel's
index range from worker threads uses every core (1.6-2x measured on 2 cores). Kernels take the chunk
``offset`` as their first argument and write only their own index, except under ``scatter_passes``,
which lets index i also write to (i, i + span]. On CUDA one launch covers all.

Each dispatch costs: ``wp.launch`` packs its arguments (about 60 us for 15 of them) and a hand-off
to the worker threads adds about 50 us here (the waking of a sleeping core in this VM; a
``ThreadPoolExecutor`` took 75 us). The calling thread therefore runs one chunk itself, and a
Launcher made with ``reuse=True`` records each distinct launch once and replays it (about 9 us),
which matters for the simulator's ~50 launches per step. Work with many dependent phases runs as a
``gang``: one launch per thread for all of them, the phases separated by barriers in native code
(``pipeline.gang``, 0.1 us each).
"""

from __future__ import annotations

import ctypes
import itertools
import os
import threading
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np
import warp as wp

# Chunks per thread of a launch (fewer when they would be shorter than min_chunk). Threads take
# chunks as they come free; more, smaller chunks would even out a stalling core but measured
# slower here (8.9, 8.3, 8.0, 6.9 steps/s of the PBF benchmark for 1, 2, 4, 8): each chunk costs
# a launch and a hand-off under the GIL.
CHUNKS_PER_THREAD = 1

# Recorded launches kept by a reusing Launcher before it starts afresh.
MAX_RECORDED = 512

# Serialises Warp initialisation and module loading across threads.
LOAD_LOCK = threading.Lock()


def init_warp(modules: tuple[Any, ...] = (), device: str = "cpu") -> None:
    """Initialise Warp and load kernel modules on the calling thread, before worker threads start."""
    with LOAD_LOCK:
        wp.init()
        for module in modules:
            wp.load_module(module, device=device)


def _yield_address() -> int:
    """The address of the C library's ``sched_yield``, which a gang's native barrier calls while it
    waits longer than a short spin (0 where there is none: the barrier then only spins)."""
    try:
        return ctypes.cast(ctypes.CDLL(None).sched_yield, ctypes.c_void_p).value or 0
    except (OSError, AttributeError, TypeError):
        return 0


class _Seat:
    """One persistent worker thread and the two locks that hand it a function and hand back its end."""

    def __init__(self, name: str):
        self._start, self._done = threading.Lock(), threading.Lock()
        self._start.acquire()
        self._done.acquire()
        self._fn: Callable[[], None] | None = None
        self._error: BaseException | None = None
        threading.Thread(target=self._serve, name=name, daemon=True).start()

    def _serve(self) -> None:
        while True:
            self._start.acquire()
            fn, self._fn = self._fn, None
            if fn is None:
                return
            try:
                fn()
            except BaseException as error:  # handed to the caller by wait()
                self._error = error
            # drop the function before waiting again: it may hold the launcher, which must stay
            # collectable (its finalizer stops these threads)
            fn = None
            self._done.release()

    def give(self, fn: Callable[[], None]) -> None:
        self._fn = fn
        self._start.release()

    def wait(self) -> BaseException | None:
        self._done.acquire()
        error, self._error = self._error, None
        return error

    def stop(self) -> None:
        self._fn = None
        self._start.release()


class _Crew:
    """Worker threads that run one function at the same time as the calling thread.

    Unlike a thread pool, every seat has its own thread, so ``run`` starts all its copies at once
    (a gang's barriers need every member running), and a hand-off is one lock release. The threads
    hold no reference to the owner: they stop when the crew is closed or collected."""

    def __init__(self, workers: int):
        self._seats = [_Seat(f"launcher-{k}") for k in range(workers)]
        self._finalizer = weakref.finalize(self, _stop_seats, self._seats)

    def run(self, fn: Callable[[int], None], count: int) -> None:
        """``fn(k)`` for k in [0, count) at once: k < count - 1 on the workers, the last here."""
        seats = self._seats[: max(0, min(count, len(self._seats) + 1) - 1)]
        for k, seat in enumerate(seats):
            seat.give(lambda k=k: fn(k))
        error: BaseException | None = None
        try:
            fn(len(seats))
        except BaseException as e:  # wait for the workers before raising
            error = e
        for seat in seats:
            error = seat.wait() or error
        if error is not None:
            raise error

    def close(self) -> None:
        self._finalizer()


def _stop_seats(seats: list[_Seat]) -> None:
    for seat in seats:
        seat.stop()


def _key(value: Any) -> Any:
    """A hashable stand-in for a kernel argument: arrays by identity, vectors and scalars by value."""
    if isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, wp.array):
        return ("array", id(value))
    if isinstance(getattr(value, "value", None), (bool, int, float)):  # Warp scalars such as wp.int64
        return ("scalar", type(value).__name__, value.value)
    try:
        return ("value", type(value).__name__, tuple(value))
    except TypeError:
        return ("object", id(value))


class Launcher:
    """Launches ``kernel(offset, *inputs)`` over ``n`` indices, split across threads on the CPU."""

    def __init__(self, device: str, threads: int = 0, min_chunk: int = 2048, reuse: bool = False):
        self.device = device
        self.threads = threads or os.cpu_count() or 1
        self.min_chunk = min_chunk
        self.cpu = not str(device).startswith("cuda")
        self._loaded: set = set()
        self._crew = _Crew(self.threads - 1) if self.cpu and self.threads > 1 else None
        self._sync: wp.array | None = None
        self._yield = _yield_address()
        # Recorded launches by (kernel, chunk slot, argument keys). Each entry keeps its inputs
        # alive, so an array's id cannot be reused by another array while its entry exists.
        self._recorded: dict | None = {} if reuse else None

    def _load(self, kernel: Any) -> None:
        # compile once here, not concurrently from several threads or Launchers (Warp's module
        # loading is not thread-safe: two dataset workers loading at once failed about 1 run in 30)
        if kernel.module not in self._loaded:
            with LOAD_LOCK:
                wp.load_module(kernel.module, device=self.device)
            self._loaded.add(kernel.module)

    def _launch(self, kernel: Any, slot: int, start: int, count: int, inputs: list[Any]) -> None:
        """One launch over [start, start + count); ``slot`` tells apart the chunks of one call."""
        if count <= 0:
            return
        if self._recorded is None:
            wp.launch(kernel, dim=count, inputs=[start, *inputs], device=self.device)
            return
        self._command(kernel, slot, start, count, inputs).launch()

    def _command(self, kernel: Any, slot: int, start: int, count: int, inputs: list[Any]) -> Any:
        """The recorded launch over [start, start + count) (recorded now if new, else updated)."""
        if self._recorded is None:
            return wp.launch(kernel, dim=count, inputs=[start, *inputs], device=self.device, record_cmd=True)
        # The chunk bounds change from step to step (scatter blocks follow the pair counts), so
        # they are not part of the key: a replay sets the offset and the dimension.
        key = (kernel, slot, *map(_key, inputs))
        entry = self._recorded.get(key)
        if entry is None:
            if len(self._recorded) >= MAX_RECORDED:
                self._recorded.clear()
            cmd = wp.launch(kernel, dim=count, inputs=[start, *inputs], device=self.device, record_cmd=True)
            entry = self._recorded[key] = [cmd, inputs, start, count]
        cmd = entry[0]
        if entry[2] != start:
            cmd.set_param_at_index(0, start)
            entry[2] = start
        if entry[3] != count:
            cmd.set_dim(count)
            entry[3] = count
        return cmd

    def _run(self, tasks: list[tuple[int, int, list[Any]]], kernel: Any, slot_base: int = 0) -> None:
        """Run (start, count, inputs) launches of one kernel on the pool and the calling thread."""
        self._run_tasks([[(kernel, slot_base + k, start, count, inputs)]
                         for k, (start, count, inputs) in enumerate(tasks)])

    def _run_tasks(self, tasks: list[list[tuple[Any, int, int, int, list[Any]]]]) -> None:
        """Run tasks, each a sequence of (kernel, slot, start, count, inputs) launches, on the pool and
        the calling thread; a task's launches run in order on one thread.

        Threads take the next task as they come free, so a core that stalls (a busy neighbour on
        a shared host) holds up one small task rather than half of the work.
        """
        tasks = [t for t in ([launch for launch in task if launch[3] > 0] for task in tasks) if t]

        def run(task: list[tuple[Any, int, int, int, list[Any]]]) -> None:
            for kernel, slot, start, count, inputs in task:
                self._launch(kernel, slot, start, count, inputs)

        if self._crew is None or len(tasks) <= 1:
            for task in tasks:
                run(task)
            return
        counter = itertools.count()  # next() is atomic under the GIL

        def work(_: int) -> None:
            for k in counter:
                if k >= len(tasks):
                    return
                run(tasks[k])

        self._crew.run(work, min(self.threads, len(tasks)))

    def split(self, n: int) -> list[tuple[int, int]]:
        """The (start, count) chunks a launch over n indices uses."""
        chunks = 1 if self._crew is None else max(1, min(CHUNKS_PER_THREAD * self.threads, n // self.min_chunk))
        bounds = [n * c // chunks for c in range(chunks + 1)]
        return [(bounds[c], bounds[c + 1] - bounds[c]) for c in range(chunks) if bounds[c + 1] > bounds[c]]

    def __call__(self, kernel: Any, n: int, inputs: list[Any]) -> None:
        """Launch over indices [0, n)."""
        if n <= 0:
            return
        self._load(kernel)
        self._run([(start, count, inputs) for start, count in self.split(n)], kernel)

    def tasks(self, kernel: Any, n: int, inputs_per_task: list[list[Any]]) -> None:
        """Launch the whole range [0, n) once per entry of ``inputs_per_task``, the launches spread
        over the threads; each must write its own outputs (e.g. its own band of image rows)."""
        if n <= 0:
            return
        self._load(kernel)
        self._run([(0, n, inputs) for inputs in inputs_per_task], kernel)

    def map(self, kernel: Any, n: int, inputs_for_chunk: Any) -> int:
        """Launch chunks with per-chunk inputs (``inputs_for_chunk(c)``), e.g. a private output
        buffer per chunk for scatter kernels that would otherwise race. Returns the chunk count."""
        self._load(kernel)
        chunks = self.split(n)
        self._run([(start, count, inputs_for_chunk(c)) for c, (start, count) in enumerate(chunks)], kernel)
        return len(chunks)

    def scatter_blocks(self, n: int, span: int, cumulative: np.ndarray | None = None,
                       per_thread: int = CHUNKS_PER_THREAD) -> list[tuple[int, int]]:
        """(start, count) blocks of [0, n) for ``scatter_passes``: 2 x ``per_thread`` per thread, each at least
        span + 1 long.

        With ``cumulative`` (a prefix sum of per-index work, length n + 1, such as the pair counts of
        a packed neighbour list) the cuts balance the work rather than the index count. The blocks
        depend on n, span, the work and the thread count, so a run is bit-identical to another with
        the same thread count. On CUDA there is one block.
        """
        if not self.cpu or n <= 0:
            return [(0, n)]
        count = max(1, min(2 * per_thread * self.threads, n // (span + 1)))
        if cumulative is None:
            cuts = [n * c // count for c in range(1, count)]
        else:
            targets = float(cumulative[n]) * np.arange(1, count) / count
            cuts = np.searchsorted(cumulative[: n + 1], targets).tolist()
        # every block at least span + 1 long: push cuts forward, then back from the end
        gap = span + 1
        bounds = [0, *cuts, n]
        for c in range(1, count):
            bounds[c] = max(bounds[c], bounds[c - 1] + gap)
        for c in range(count - 1, 0, -1):
            bounds[c] = min(bounds[c], bounds[c + 1] - gap)
        return [(bounds[c], bounds[c + 1] - bounds[c]) for c in range(count)]

    def scatter_passes(self, blocks: list[tuple[int, int]],
                       passes: list[tuple[Any, list[Any], Any, list[Any]]]) -> None:
        """Run scatter passes one after another, each (pair kernel, inputs, finish kernel, inputs): index
        i of the pair kernel also adds into indices (i, i + span], and the finish kernel then turns a
        block's completed sums into per-particle results, without races.

        ``blocks`` come from ``scatter_blocks``: each is at least span + 1 long, so a block writes
        only into itself and the next one; the even blocks run concurrently, then the odd ones. A
        block's sums are complete once it and the block before it have run, so an odd block
        finishes right after its own pairs (the even blocks ran in the phase before), and an even
        block finishes at the start of its task in the next pass's first phase: the next pass reads
        only its own block and the next, both finished by then. Each pass thus costs two thread
        hand-offs, not three, and the finish launch shares the block's warm cache. A finish that
        clears its accumulators leaves them ready for the next pass. On CUDA (one block) each pass
        is its pair launch, then its finish.
        """
        for kernel, _, finish, _ in passes:
            self._load(kernel)
            self._load(finish)
        # chunk slots of the recorded launches: even blocks 0, 2, ..., odd blocks 1, 3, ...
        even = [(2 * b, start, count) for b, (start, count) in enumerate(blocks[0::2])]
        odd = [(2 * b + 1, start, count) for b, (start, count) in enumerate(blocks[1::2])]
        finish_before: tuple[Any, list[Any]] | None = None
        for kernel, inputs, finish, finish_inputs in passes:
            head = [] if finish_before is None else [finish_before]
            self._run_tasks([[(k, slot, start, count, args) for k, args in [*head, (kernel, inputs)]]
                             for slot, start, count in even])
            self._run_tasks([[(kernel, slot, start, count, inputs), (finish, slot, start, count, finish_inputs)]
                             for slot, start, count in odd])
            finish_before = (finish, finish_inputs)
        if finish_before is not None:
            self._run_tasks([[(finish_before[0], slot, start, count, finish_before[1])] for slot, start, count in even])

    def gang(self, kernel: Any, phases: int, inputs: list[Any]) -> None:
        """Run ``kernel(thread, threads, sync, yield_address, *inputs)`` once on every thread at the same
        time (CPU only), for work of ``phases`` dependent phases: the kernel separates them with
        ``gang.barrier`` and shares each phase's blocks out with ``gang.next_block`` on ``sync``
        (zeroed here). One launch per thread instead of a hand-off per phase.

        Every thread's launch is recorded before any starts, so an argument error raises here rather
        than leaving the others waiting at a barrier."""
        if not self.cpu:
            raise ValueError("a gang runs on the CPU; on CUDA launch the passes one after another")
        self._load(kernel)
        size = 2 + phases
        if self._sync is None or self._sync.shape[0] < size:
            self._sync = wp.zeros(size, dtype=int, device=self.device)
        else:
            self._sync.zero_()
        threads = self.threads if self._crew is not None else 1
        args = [threads, self._sync, wp.uint64(self._yield), *inputs]
        commands = [self._command(kernel, t, t, 1, args) for t in range(threads)]
        if self._crew is None:
            commands[0].launch()
        else:
            self._crew.run(lambda t: commands[t].launch(), threads)

    def close(self) -> None:
        """Stop the worker threads and drop recorded launches."""
        if self._crew is not None:
            self._crew.close()
            self._crew = None
        if self._recorded is not None:
            self._recorded.clear()
