"""Metric sanity: identical maps give 0 degrees and IoU 1; a known rotation gives its angle."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.masks import normal_mask
from pipeline.metrics import MISSED_DEG, angular_errors, errors_over_reference, iou, summarize_angles


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


def test_leaving_out_the_hard_pixels_no_longer_pays():
    """Two methods against one target: A shows every target pixel, 1 degree off on the easy 80% and
    40 degrees off on the hard 20%; B is exact on the easy pixels and leaves the hard ones out. On
    each method's own mask B looks better (0 against 8.8 degrees); over the target's pixels, a missed
    one scoring 90 degrees, A is better (8.8 against 18), and B's misses are counted."""
    n = _random_normals(2, (20, 50))
    target_mask = np.ones(n.shape[:2], bool)
    hard = np.zeros_like(target_mask)
    hard[:, :10] = True
    axis = np.array([0.3, -0.5, 0.8])
    perp = np.cross(n, axis)
    perp /= np.linalg.norm(perp, axis=-1, keepdims=True)
    a_deg = np.where(hard, 40.0, 1.0)[..., None]
    a_map = n * np.cos(np.radians(a_deg)) + np.cross(perp, n) * np.sin(np.radians(a_deg))
    a_err, a_on_mask, a_missed = errors_over_reference(a_map, n, target_mask, target_mask)
    b_err, b_on_mask, b_missed = errors_over_reference(n, n, ~hard, target_mask)
    assert b_on_mask.mean() < 1e-4 < a_on_mask.mean()
    assert a_err.mean() == pytest.approx(0.8 * 1 + 0.2 * 40, abs=1e-4)
    assert b_err.mean() == pytest.approx(0.2 * MISSED_DEG, abs=1e-4) and b_err.mean() > a_err.mean()
    assert (a_missed, b_missed) == (0, hard.sum()) and a_err.size == b_err.size == target_mask.sum()
    # pixels outside the target do not enter the errors, only the IoU
    extra = np.ones((20, 60), bool)
    wide = np.concatenate([n, n[:, :10]], axis=1)
    e, _, missed = errors_over_reference(wide, wide, extra, np.pad(target_mask, ((0, 0), (0, 10))))
    assert e.size == target_mask.sum() and missed == 0


def test_refined_pixels_may_reach_past_the_splat_by_the_reach_only():
    """A splat disc of radius 8 px and a predicted normal map of unit vectors everywhere but for a
    short vector inside: with a reach of 3 px the mask is the disc grown by 3 px (Euclidean), without
    the noise pixel; with no reach it is the disc."""
    from pipeline.masks import refined_mask

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

    from pipeline.masks import near
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
    from pipeline.masks import NearestFluid

    nearest = NearestFluid.of(fluid, 4.0)
    within = mask & nearest.near(4.0)
    assert within.sum() > 0.5 * mask.sum()
    np.testing.assert_array_equal(nearest.near(4.0), near(fluid, 4.0))
    np.testing.assert_array_equal(nearest.spread(depth, within), np.where(within, whole, 0.0))


def _transform_cases():
    """Masks for the feature transform: sparse to dense noise, lone pixels, a row of pixels (ties
    along every column), a checkerboard (ties everywhere), a full and an empty image, odd shapes."""
    rng = np.random.default_rng(7)
    cases = [rng.random((int(h), int(w))) < share
             for h, w, share in zip(rng.integers(1, 70, 24), rng.integers(1, 70, 24),
                                    np.tile([0.001, 0.01, 0.1, 0.5, 0.9, 0.3], 4), strict=True)]
    row = np.zeros((41, 37), bool)
    row[20, ::3] = True
    lone = np.zeros((50, 64), bool)
    lone[[0, 49, 17], [63, 0, 30]] = True
    checker = (np.indices((33, 40)).sum(0) % 7 == 0)
    return [*cases, row, lone, checker, np.ones((5, 9), bool), np.zeros((6, 4), bool), np.ones((1, 1), bool)]


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_the_device_feature_transform_gives_scipys_numbers(device):
    """``nearest_fluid_pixels`` (the transform a GPU's refined frame uses) gives scipy's distances
    and nearest pixels bit for bit, equidistant candidates included; without fluid, infinite
    distances and -1."""
    import torch
    from scipy.ndimage import distance_transform_edt

    from pipeline.screen import nearest_fluid_pixels

    for k, fluid in enumerate(_transform_cases()):
        distance, rows, cols = (a.cpu().numpy() for a in nearest_fluid_pixels(torch.from_numpy(fluid).to(device)))
        if not fluid.any():
            assert np.isinf(distance).all() and (rows == -1).all() and (cols == -1).all()
            continue
        expected, (er, ec) = distance_transform_edt(~fluid, return_indices=True)
        assert distance.dtype == expected.dtype
        np.testing.assert_array_equal(distance, expected, err_msg=f"case {k}")
        np.testing.assert_array_equal(rows, er, err_msg=f"case {k}")
        np.testing.assert_array_equal(cols, ec, err_msg=f"case {k}")


@pytest.mark.parametrize("seed", [0, 1])
def test_nearest_fluid_of_a_tensor_gives_the_host_reach_and_spread(seed):
    """The tensor way of ``NearestFluid`` and ``extend_depth`` (the whole image, where the tensor
    lies) gives the host's windowed results exactly, an image without fluid included."""
    import torch
    from scipy.ndimage import binary_dilation

    from pipeline.masks import NearestFluid
    from pipeline.methods import extend_depth

    rng = np.random.default_rng(seed)
    fluid = np.zeros((80, 100), bool)
    for _ in range(4):
        r, c = rng.integers(0, 80), rng.integers(0, 100)
        fluid[max(r - 5, 0):r + 5, max(c - 8, 0):c + 8] = True
    fluid &= rng.random(fluid.shape) > 0.3
    depth = np.where(fluid, rng.integers(1, 5, fluid.shape), 0).astype(np.float32)
    mask = binary_dilation(fluid, iterations=3) & (rng.random(fluid.shape) > 0.2)
    host, dev = NearestFluid.of(fluid, 3.5), NearestFluid.of(torch.from_numpy(fluid), 3.5)
    for reach in (0.5, 2.0, 3.5):
        assert isinstance(dev.near(reach), torch.Tensor)
        np.testing.assert_array_equal(dev.near(reach).numpy(), host.near(reach))
    within = mask & host.near(3.5)
    np.testing.assert_array_equal(dev.spread(torch.from_numpy(depth), torch.from_numpy(within)).numpy(),
                                  host.spread(depth, within))
    np.testing.assert_array_equal(extend_depth(torch.from_numpy(depth), torch.from_numpy(mask)).numpy(),
                                  extend_depth(depth, mask))
    empty = torch.zeros((6, 7))
    assert not extend_depth(empty, torch.ones((6, 7), dtype=torch.bool)).any()
    assert not NearestFluid.of(empty > 0, 2.0).near(2.0).any()


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
