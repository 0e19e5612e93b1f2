"""Step timers: totals and counts, and the GPU wait that gives each step its own work."""

from __future__ import annotations

import time

import pytest

from pipeline import timing
from pipeline.timing import Timings


def test_steps_add_up_their_calls():
    t = Timings()
    for _ in range(3):
        with t("a"):
            time.sleep(0.002)
    with t("b"):
        pass
    assert t.count["a"] == 3 and t.count["b"] == 1
    assert t.total["a"] >= 0.006 and t.mean_ms("a") >= 2.0
    other = Timings()
    with other("a"):
        pass
    t.merge(other)
    assert t.count["a"] == 4


@pytest.mark.parametrize("env, sync, waits", [("", None, 0), ("1", None, 2), ("", True, 2), ("1", False, 0)])
def test_synchronised_timers_wait_for_the_gpu_at_both_ends(monkeypatch, env, sync, waits):
    """``DEEP_SSFR_SYNC_TIMINGS=1`` (or ``sync=True``) waits for the GPU as a step starts and as it
    ends; by default a timer never waits (the render loop keeps the GPU's overlap)."""
    calls = []
    monkeypatch.setenv(timing.SYNC_ENV, env)
    monkeypatch.setattr(timing, "synchronize", lambda: calls.append(1))
    t = Timings(sync)
    with t("step"):
        assert len(calls) == waits // 2
    assert len(calls) == waits


def test_synchronize_without_a_gpu_does_nothing():
    timing.synchronize()
