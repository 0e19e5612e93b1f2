"""Frame outputs written on a background thread, so encoding a frame overlaps computing the next.

EXR compression (zlib), PNG encoding and file I/O release the GIL for most of their time, so on
two cores the writer mostly uses time the compute kernels leave idle. At most ``max_pending`` frames
wait, which bounds memory and surfaces a failed write (disk full, read-only) within two frames.
An interrupted run drops the writes not yet started but waits for the one in progress (a fraction of
a second): that write runs native code (torch, OpenEXR) which must not be running while the
interpreter tears those libraries down (C++ ``terminate``, SIGABRT, seen about one Ctrl-C in three).
Each output is a temporary file until its rename, so nothing half-written is ever taken as done.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any


class BackgroundWriter:
    """``with BackgroundWriter() as w: w.submit(write_exr, path, channels)``; leaving the block
    waits for every write and raises the first error (on Ctrl-C, for none)."""

    def __init__(self, max_pending: int = 2):
        self.max_pending = max_pending
        self._queue: queue.SimpleQueue[tuple[Future, Callable[..., Any], tuple] | None] = queue.SimpleQueue()
        self._pending: deque[Future] = deque()
        self._thread = threading.Thread(target=self._serve, name="writer", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while (item := self._queue.get()) is not None:
            future, fn, args = item
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn(*args))
                except BaseException as exc:  # handed to the caller by result()
                    future.set_exception(exc)

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        """Queue ``fn(*args)``; blocks while ``max_pending`` writes are already waiting."""
        while len(self._pending) >= self.max_pending:
            self._pending.popleft().result()
        future: Future = Future()
        self._pending.append(future)
        self._queue.put((future, fn, args))

    def drain(self) -> None:
        """Wait for every queued write; raises the first error."""
        while self._pending:
            self._pending.popleft().result()

    def close(self) -> None:
        """Drain, then stop the thread."""
        try:
            self.drain()
        finally:
            self._queue.put(None)
            self._thread.join()

    def cancel(self) -> None:
        """Drop the writes not yet started and stop once the one in progress has finished."""
        for future in self._pending:
            future.cancel()
        self._pending.clear()
        self._queue.put(None)
        self._thread.join()

    def __enter__(self) -> BackgroundWriter:
        return self

    def __exit__(self, kind: type | None, *exc: object) -> None:
        if kind is not None and issubclass(kind, KeyboardInterrupt):
            self.cancel()
        else:
            self.close()
