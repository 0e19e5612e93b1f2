"""The background frame writer: order, errors, and what an interruption keeps."""

from __future__ import annotations

import threading

import pytest

from pipeline.writer import BackgroundWriter


def test_writes_run_in_order_and_the_first_error_reaches_the_caller():
    done: list[int] = []

    def fail() -> None:
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"), BackgroundWriter() as writer:
        writer.submit(done.append, 1)
        writer.submit(fail)
        writer.submit(done.append, 2)
    assert done[0] == 1


def test_an_interrupt_finishes_the_write_in_progress_and_drops_the_queued_ones():
    """Ctrl-C leaves the block only after the running write has ended (native code must not still be
    running as the interpreter exits), and the writes not yet started never run."""
    started, release, done = threading.Event(), threading.Event(), []

    def slow(tag: str) -> None:
        started.set()
        release.wait(5)
        done.append(tag)

    timer = threading.Timer(0.2, release.set)
    with pytest.raises(KeyboardInterrupt), BackgroundWriter(max_pending=3) as writer:
        writer.submit(slow, "running")
        writer.submit(done.append, "queued")
        started.wait(5)
        timer.start()
        raise KeyboardInterrupt
    assert done == ["running"]
    assert not writer._thread.is_alive()
