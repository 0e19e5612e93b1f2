"""Frame outputs written on a background thread, so encoding a frame overlaps computing the next.

EXR compression (zlib), PNG encoding and file I/O release the GIL for most of their time, so on
two cores the writer mostly uses time the compute kernels leave idle. At most ``max_pending`` frames
wait, which bounds memory and surfaces a failed write (disk full, read-only) within two frames.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any


class BackgroundWriter:
    """``with BackgroundWriter() as w: w.submit(write_exr, path, channels)``; leaving the block
    waits for every write and raises the first error."""

    def __init__(self, max_pending: int = 2):
        self.max_pending = max_pending
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="writer")
        self._pending: deque[Future] = deque()

    def submit(self, fn: Callable[..., Any], *args: Any) -> None:
        """Queue ``fn(*args)``; blocks while ``max_pending`` writes are already waiting."""
        while len(self._pending) >= self.max_pending:
            self._pending.popleft().result()
        self._pending.append(self._pool.submit(fn, *args))

    def drain(self) -> None:
        """Wait for every queued write; raises the first error."""
        while self._pending:
            self._pending.popleft().result()

    def close(self) -> None:
        """Drain, then stop the thread."""
        try:
            self.drain()
        finally:
            self._pool.shutdown(wait=True)

    def __enter__(self) -> BackgroundWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
