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


def test_refined_pixels_may_reach_past_the_splat_by_the_reach_only():
    """A splat disc of radius 8 px and a predicted normal map of unit vectors everywhere but for a
    short vector inside: with a reach of 3 px the mask is the disc grown by 3 px (Euclidean), without
    the noise pixel; with no reach it is the disc."""
    from pipeline.evaluate.metrics import refined_mask

    yy, xx = np.mgrid[0:40, 0:40]
    dist = np.hypot(yy - 20, xx - 20)
    fluid = dist <= 8
    n = np.zeros((40, 40, 3))
    n[..., 2] = 1.0
    n[20, 20, 2] = 0.3
    strict = refined_mask(n, fluid, 0.5)
    assert np.array_equal(strict, fluid & (dist > 0))
    grown = refined_mask(n, fluid, 0.5, reach_px=3)
    ring = (dist > 8) & (dist <= 10.5)
    assert grown[ring].all() and not grown[dist > 11.5].any() and not grown[20, 20]
    assert grown.sum() > strict.sum()


def test_extended_depth_copies_the_nearest_splat_depth():
    from pipeline.methods import extend_depth

    depth = np.zeros((5, 8), np.float32)
    depth[:, :3] = 2.0
    depth[:, 3:5] = 3.0
    mask = np.zeros((5, 8), bool)
    mask[:, :7] = True
    out = extend_depth(depth, mask)
    np.testing.assert_array_equal(out[:, :5], depth[:, :5])
    np.testing.assert_array_equal(out[:, 5:7], 3.0)
    assert not out[:, 7].any()
    assert not extend_depth(np.zeros((3, 3), np.float32), np.ones((3, 3), bool)).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_windowed_distance_transforms_give_the_whole_image_results(seed):
    """``near`` and ``extend_depth`` run the distance transform on the fluid's bounding box only; on
    blobs anywhere in the image (touching its border too), with equidistant candidates on a
    lattice of depths, they must give what the transform of the whole image gives."""
    from scipy.ndimage import binary_dilation, distance_transform_edt

    from pipeline.evaluate.metrics import near
    from pipeline.methods import extend_depth

    rng = np.random.default_rng(seed)
    h, w = 96, 128
    fluid = np.zeros((h, w), bool)
    for _ in range(5):
        r, c = rng.integers(0, h), rng.integers(0, w)
        fluid[max(r - 6, 0):r + 6, max(c - 9, 0):c + 9] = True
    fluid &= rng.random((h, w)) > 0.3
    depth = np.where(fluid, rng.integers(1, 5, (h, w)).astype(np.float32), 0.0).astype(np.float32)
    mask = binary_dilation(fluid, iterations=4) & (rng.random((h, w)) > 0.2)
    for reach in (0.5, 3.0, 4.7):
        np.testing.assert_array_equal(near(fluid, reach), distance_transform_edt(~fluid) <= reach)
    rows, cols = distance_transform_edt(~fluid, return_distances=False, return_indices=True)
    whole = np.where(mask, depth[rows, cols], 0.0)
    np.testing.assert_array_equal(extend_depth(depth, mask), whole)
    # the renderer's shared transform (refine): the mask within the reach, the same depths
    from pipeline.evaluate.metrics import NearestFluid

    nearest = NearestFluid.of(fluid, 4.0)
    within = mask & nearest.near(4.0)
    assert within.sum() > 0.5 * mask.sum()
    np.testing.assert_array_equal(nearest.near(4.0), near(fluid, 4.0))
    np.testing.assert_array_equal(nearest.spread(depth, within), np.where(within, whole, 0.0))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_vector_length_is_numpys_norm_bit_for_bit(dtype):
    """``pipeline.vectors.length`` replaces ``np.linalg.norm`` on images for speed: it must add the
    same squares in the same order (another order differs in the last bit on some of these)."""
    from pipeline.vectors import length

    rng = np.random.default_rng(5)
    v = (rng.normal(size=(64, 48, 3)) * rng.uniform(1e-3, 1e3, size=(64, 48, 3))).astype(dtype)
    np.testing.assert_array_equal(length(v), np.linalg.norm(v, axis=-1))
    chw = np.ascontiguousarray(np.moveaxis(v, -1, 0))
    np.testing.assert_array_equal(length(chw, axis=0), np.linalg.norm(chw, axis=0))
    x, y, z = np.moveaxis(v, -1, 0)
    assert not np.array_equal(np.sqrt((z * z + y * y) + x * x), np.linalg.norm(v, axis=-1))
    # a torch tensor (the refiner's output on its device) gets the same lengths, as a tensor
    import torch

    t = length(torch.from_numpy(chw), axis=0)
    assert isinstance(t, torch.Tensor)
    np.testing.assert_array_equal(t.numpy(), np.linalg.norm(chw, axis=0))


def test_median_and_box_mean_agree_on_numpy_and_torch():
    """``pipeline.vectors.median`` takes the mean of the two middle values of an even count, as
    numpy does (torch's own median takes the lower); ``box_mean`` is scipy's constant-edge
    uniform filter on both kinds, windows wider than the image included."""
    import torch
    from scipy.ndimage import uniform_filter

    from pipeline.vectors import box_mean, median, xp

    even = np.array([4.0, 1.0, 3.0, 2.0], np.float32)
    assert median(even) == median(torch.from_numpy(even)) == 2.5
    assert median(torch.tensor([5.0, 1.0, 3.0])) == 3.0
    img = np.random.default_rng(1).uniform(size=(13, 21)).astype(np.float32)
    for size in (1, 3, 9, 31):
        want = uniform_filter(img, size, mode="constant")
        np.testing.assert_array_equal(box_mean(img, size), want)
        got = box_mean(torch.from_numpy(img), size)
        assert got.shape == img.shape and xp(got) is torch
        np.testing.assert_allclose(got.numpy(), want, atol=1e-6)
