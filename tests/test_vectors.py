"""Host helpers of pipeline.vectors that must give numpy's own numbers."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.vectors import bounds


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int64])
def test_bounds_are_numpys_axis_minimum_and_maximum(dtype):
    rng = np.random.default_rng(5)
    points = (rng.normal(size=(10_007, 3)) * 100).astype(dtype)
    lo, hi = bounds(points)
    np.testing.assert_array_equal(lo, points.min(0))
    np.testing.assert_array_equal(hi, points.max(0))
    assert lo.dtype == hi.dtype == points.dtype
    lo, hi = bounds(points[:0])
    assert np.all(lo == np.inf) and np.all(hi == -np.inf)


def test_bounds_keep_a_nan_as_numpy_does():
    points = np.zeros((5, 3), np.float32)
    points[2, 1] = np.nan
    lo, hi = bounds(points)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and lo[0] == hi[0] == 0
