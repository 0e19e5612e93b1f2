"""The CPU launcher's worker threads and gang launches (one launch per thread, native barriers)."""

import numpy as np
import pytest
import warp as wp

from pipeline import gang
from pipeline.parallel import Launcher, init_warp

PHASES, BLOCKS, WIDTH = 12, 7, 100_000


@wp.kernel
def neighbour_sums(thread: int, threads: int, sync: wp.array(dtype=int), yield_address: wp.uint64,
                   values: wp.array(dtype=float, ndim=3), visits: wp.array(dtype=int, ndim=2),
                   owner: wp.array(dtype=int, ndim=2)):
    """Phase p: every block b's values become its own plus block b + 1's from phase p - 1 (a wrong
    answer unless the barrier holds every thread until the phase before is complete)."""
    for p in range(PHASES):
        src = p % 2
        b = gang.next_block(sync, p)
        while b < BLOCKS:
            nxt = (b + 1) % BLOCKS
            for k in range(WIDTH):
                values[1 - src, b, k] = values[src, b, k] + values[src, nxt, k]
            wp.atomic_add(visits, p, b, 1)
            owner[p, b] = thread
            b = gang.next_block(sync, p)
        gang.barrier(sync, p, threads, yield_address)


def _run(threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    init_warp((), "cpu")
    start = np.random.default_rng(0).uniform(0.0, 1.0, (BLOCKS, WIDTH)).astype(np.float32)
    values = wp.array(np.stack([start, np.zeros_like(start)]), dtype=float, device="cpu")
    visits = wp.zeros((PHASES, BLOCKS), dtype=int, device="cpu")
    owner = wp.zeros((PHASES, BLOCKS), dtype=int, device="cpu")
    launch = Launcher("cpu", threads)
    try:
        launch.gang(neighbour_sums, PHASES, [values, visits, owner])
    finally:
        launch.close()
    expect = start.astype(np.float64)
    for _ in range(PHASES):
        expect = expect + np.roll(expect, -1, axis=0)
    return values.numpy()[PHASES % 2], expect, visits.numpy(), owner.numpy()


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_a_gang_runs_every_block_once_per_phase_after_the_phase_before(threads):
    # three threads on this two-core machine: a waiting thread must yield its core, not spin forever
    got, expect, visits, owner = _run(threads)
    np.testing.assert_array_equal(visits, 1)
    np.testing.assert_allclose(got, expect, rtol=1e-5)
    assert set(np.unique(owner)) == set(range(threads)), "every thread must have taken blocks"


def test_a_gang_with_a_bad_argument_raises_before_any_thread_waits():
    init_warp((), "cpu")
    launch = Launcher("cpu", 2)
    wrong = wp.zeros((PHASES, BLOCKS), dtype=float, device="cpu")  # visits must hold ints
    values = wp.zeros((2, BLOCKS, WIDTH), dtype=float, device="cpu")
    with pytest.raises(RuntimeError, match="visits"):
        launch.gang(neighbour_sums, PHASES, [values, wrong, wrong])
    # the launcher's threads are free: a correct gang on it still completes
    visits = wp.zeros((PHASES, BLOCKS), dtype=int, device="cpu")
    owner = wp.zeros((PHASES, BLOCKS), dtype=int, device="cpu")
    launch.gang(neighbour_sums, PHASES, [values, visits, owner])
    launch.close()
    np.testing.assert_array_equal(visits.numpy(), 1)


def test_an_error_on_a_worker_thread_reaches_the_caller_and_the_crew_goes_on():
    init_warp((), "cpu")
    launch = Launcher("cpu", 2)
    ran = []

    def task(k: int) -> None:
        if k == 0:
            raise ValueError("worker failed")
        ran.append(k)

    with pytest.raises(ValueError, match="worker failed"):
        launch._crew.run(task, 2)
    launch._crew.run(lambda k: ran.append(10 + k), 2)
    launch.close()
    assert sorted(ran) == [1, 10, 11]


def test_a_launcher_dropped_without_close_stops_its_threads():
    import gc
    import threading

    init_warp((), "cpu")

    def crew_threads() -> list[threading.Thread]:
        return [t for t in threading.enumerate() if t.name.startswith("launcher-")]

    before = set(crew_threads())
    launch = Launcher("cpu", 3)
    launch._crew.run(lambda k, held=launch: None, 3)  # the workers ran a function holding the launcher
    started = set(crew_threads()) - before
    assert len(started) == 2
    del launch
    gc.collect()
    for thread in started:
        thread.join(timeout=5)
    assert not any(t.is_alive() for t in started), "a collected launcher's worker threads must end"
