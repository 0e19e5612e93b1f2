"""Metric sanity: identical maps give 0 degrees and IoU 1; a known rotation gives its angle."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluate.metrics import angular_errors, iou, normal_mask, summarize_angles


def _random_normals(seed=0, shape=(32, 40)):
    n = np.random.default_rng(seed).normal(size=(*shape, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.5
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def test_identical_maps():
    n = _random_normals()
    m = normal_mask(n)
    s = summarize_angles(angular_errors(n, n, m))
    assert s["mean_deg"] < 1e-4 and s["under_5"] == 1.0
    assert iou(m, m) == 1.0


@pytest.mark.parametrize("degrees", [3.0, 12.5, 40.0])
def test_rotated_map_gives_its_angle(degrees):
    n = _random_normals(1)
    a = np.radians(degrees)
    axis = np.array([0.3, -0.5, 0.8])
    # rotate each normal about an axis perpendicular to it: exactly `degrees` apart
    perp = np.cross(n, axis)
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    rotated = n * np.cos(a) + np.cross(perp, n) * np.sin(a)
    err = angular_errors(rotated, n, normal_mask(n))
    np.testing.assert_allclose(err, degrees, atol=1e-6)


def test_iou_of_half_overlap():
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    a[:, :6] = True
    b[:, 4:] = True
    assert iou(a, b) == pytest.approx(20 / 100)
