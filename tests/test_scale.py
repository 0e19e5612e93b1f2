"""Scale-free refiner inputs: the working scale, area averaging, the depth features, quarter turns."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.camera import Camera, look_at
from pipeline.config import DatasetConfig
from pipeline.model.data import Frame, InputSpec, draw_crop, prepare, rotate_quarter
from pipeline.model.scale import area_average, resize_normals, scale_view, working_scale
from pipeline.surface import particle_ellipsoids
from pipeline.views import screen_space_inputs


def test_working_scale_moves_in_half_octaves_to_at_most_the_working_radius():
    depth = np.full((8, 8), 2.0, np.float32)  # f r / d = 100 * 0.05 / 2 = 2.5 px
    assert working_scale(depth, 100.0, 0.05, 3.0) == 1.0
    assert working_scale(depth, 100.0, 0.05, 0.0) == 1.0
    assert working_scale(np.zeros((4, 4)), 100.0, 0.05, 1.0) == 1.0
    for target in (0.3, 0.9, 1.2, 2.4, 4.0, 6.0, 9.0):  # down, and up for small particles
        s = working_scale(depth, 100.0, 0.05, target)
        assert target / 2**0.5 < 2.5 * s <= target + 1e-6
        assert abs(2 * np.log2(s) - round(2 * np.log2(s))) < 1e-9
    assert working_scale(depth, 100.0, 0.05, 100.0) == 4.0  # at most MAX_UPSCALE


def test_working_scale_upscales_only_within_the_pixel_budget():
    depth = np.zeros((100, 200), np.float32)
    depth[10:30, 50:100] = 2.0  # a 20 x 50 box of particles 2.5 px wide
    assert working_scale(depth, 100.0, 0.05, 10.0) == 4.0
    assert working_scale(depth, 100.0, 0.05, 10.0, max_pixels=16_000) == 4.0  # 1000 px x 16 fits
    assert working_scale(depth, 100.0, 0.05, 10.0, max_pixels=15_999) == 2**1.5  # a half octave less
    assert working_scale(depth, 100.0, 0.05, 10.0, max_pixels=2_000) == 2**0.5
    assert working_scale(depth, 100.0, 0.05, 10.0, max_pixels=1_999) == 1.0
    assert working_scale(depth, 100.0, 0.05, 10.0, max_pixels=10) == 1.0  # never below 1
    assert working_scale(depth, 100.0, 0.05, 1.0, max_pixels=10) == 2**-1.5  # downscaling: never bounded
    import torch

    assert working_scale(torch.from_numpy(depth), 100.0, 0.05, 10.0, max_pixels=15_999) == 2**1.5


def test_area_average_keeps_fluid_values_and_reports_coverage():
    values = np.zeros((2, 8, 8), np.float32)
    weight = np.zeros((8, 8), np.float32)
    weight[:, :3] = 1.0  # three columns of fluid with value 5 and 7, the rest empty with junk
    values[0] = np.where(weight > 0, 5.0, 99.0)
    values[1] = np.where(weight > 0, 7.0, -99.0)
    avg, cov = area_average(values, weight, (4, 4))
    np.testing.assert_allclose(cov[:, 0], 1.0)
    np.testing.assert_allclose(cov[:, 1], 0.5)
    np.testing.assert_allclose(cov[:, 2:], 0.0)
    np.testing.assert_allclose(avg[0][cov > 0], 5.0, rtol=1e-6)
    np.testing.assert_allclose(avg[1][cov > 0], 7.0, rtol=1e-6)


def _ball_view(size: int, distance: float, radius: float = 0.01):
    """A jittered lattice ball's ellipsoid-splat channels seen from ``distance`` at ``size`` px."""
    from pipeline.parallel import Launcher
    from pipeline.screen import ScreenSpace

    ax = np.arange(-0.12, 0.12 + 1e-9, 2 * radius)
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    pts = pts[np.linalg.norm(pts, axis=1) <= 0.12]
    pts = (pts + np.random.default_rng(3).uniform(-0.4, 0.4, pts.shape) * radius).astype(np.float32)
    p = DatasetConfig(width=size, height=size)
    ss, launch = ScreenSpace("cpu"), Launcher("cpu")
    cam = Camera(look_at((0.0, 0.3 * distance, distance), (0, 0, 0)), 30.0, size, size)
    ellipsoids = particle_ellipsoids(pts, radius, p, launch)
    ch = screen_space_inputs(pts, radius, cam, p, ss, filters=None, ellipsoids=ellipsoids, aniso_filters=("bilateral",))
    ss.close()
    launch.close()
    return ch, cam, radius


def _stats(inputs: np.ndarray, fluid: np.ndarray) -> np.ndarray:
    """Mean and standard deviation over the fluid of every input channel (C x 2)."""
    return np.array([[inputs[k][fluid].mean(), inputs[k][fluid].std()] for k in range(inputs.shape[0])])


def test_inputs_agree_across_resolution_and_distance():
    """One ball: 96 px from 0.6 m (particles ~3.4 px), 192 px from the same place (~7 px, scaled
    down by half to the working radius of 4 px) and 192 px from twice as far (~3.4 px again). The scale-free inputs'
    statistics agree; the working image of the larger render is the smaller one's size."""
    spec = InputSpec(True, "ellipsoid", "radius", 4.0)
    views = {}
    for name, size, distance in (("near", 96, 0.6), ("fine", 192, 0.6), ("far", 192, 1.2)):
        ch, cam, r = _ball_view(size, distance)
        views[name] = prepare(ch, spec, cam.focal_px, r)
    assert views["fine"].scale == pytest.approx(0.5)
    assert views["near"].scale == views["far"].scale == 1.0
    assert views["fine"].inputs.shape == views["near"].inputs.shape
    ref = _stats(views["near"].inputs, views["near"].fluid)
    for other in ("fine", "far"):
        got = _stats(views[other].inputs, views[other].fluid)
        # normals (3), bumps in radii, relief, log2 projected radius / 2
        np.testing.assert_allclose(got[:3], ref[:3], atol=0.04, err_msg=other)
        np.testing.assert_allclose(got[3:5], ref[3:5], atol=0.08, err_msg=other)
        np.testing.assert_allclose(got[5, 0], ref[5, 0], atol=0.06, err_msg=other)
    share = {k: v.fluid.mean() for k, v in views.items()}
    assert abs(share["fine"] - share["near"]) < 0.01 and share["near"] > 0.15


def test_scaled_target_and_upsampling_keep_a_constant_normal():
    n = np.zeros((3, 32, 32), np.float32)
    n[2] = 1.0
    raw = np.full((32, 32), 1.0, np.float32)
    view = scale_view(n, raw, raw, 600.0, 0.01, 1.5, target=n)  # 6 px particles to 1.5: a quarter
    assert view.scale == 0.25 and view.raw.shape == (8, 8)
    np.testing.assert_allclose(view.target[2], 1.0)
    up = resize_normals(np.moveaxis(view.normals, 0, -1), (32, 32))
    np.testing.assert_allclose(up[..., 2], 1.0, atol=1e-6)


def _sphere_normals(size: int) -> np.ndarray:
    """3 x H x W view-space normals of a sphere filling the image (row 0 at the top, +Y up)."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c, -c)
    inside = x**2 + y**2 < 0.9
    z = np.sqrt(np.clip(1 - x**2 - y**2, 0, 1))
    return (np.stack([x, y, z]) * inside).astype(np.float32)


@pytest.mark.parametrize("turns", [1, 2, 3])
def test_quarter_turns_rotate_the_normals_with_the_image(turns):
    """A sphere's normal map is the same seen from a rolled camera: turning the image and its
    normals together must give the map back (wrong signs or a missing turn of the vectors do not)."""
    n = _sphere_normals(32)
    np.testing.assert_allclose(rotate_quarter(n, turns, (slice(0, 3),)), n, atol=1e-6)
    assert not np.allclose(np.rot90(n, turns, axes=(-2, -1)), n, atol=1e-3)


def test_crops_pad_small_frames_and_turn_inputs_and_targets_alike():
    n = _sphere_normals(24)
    frame = Frame(np.concatenate([n, n[:1]]), n, "ball", np.abs(n).sum(0) > 0)
    rng = np.random.default_rng(0)
    for _ in range(8):
        x, y = draw_crop(frame, 32, rng, flip=True, rotate=True)
        assert x.shape == (4, 32, 32) and y.shape == (3, 32, 32)
        np.testing.assert_allclose(x[:3], y, atol=1e-6)


def test_small_particles_are_scaled_up_and_back():
    """A disc of constant normals whose particles project to 1 px goes up by 2^1.5 to the working
    radius of 3 px (the mask by nearest neighbour, the fluid's share kept), and its normals come back
    down to the view's size unchanged."""
    yy, xx = np.mgrid[0:40, 0:40]
    disc = np.hypot(yy - 20, xx - 20) < 12
    n = np.zeros((3, 40, 40), np.float32)
    n[1], n[2] = 0.6 * disc, 0.8 * disc
    raw = np.where(disc, 1.0, 0.0).astype(np.float32)
    view = scale_view(n, raw, raw, 100.0, 0.01, 3.0, target=n)  # 100 * 0.01 / 1 = 1 px
    assert view.scale == pytest.approx(2**1.5, rel=0.02) and view.raw.shape == (113, 113)
    assert abs(view.fluid.mean() - disc.mean()) < 0.01
    np.testing.assert_allclose(view.normals[1][view.fluid], 0.6, atol=1e-5)
    np.testing.assert_allclose(view.target[2][view.fluid], 0.8, atol=1e-5)
    np.testing.assert_allclose(view.raw[view.fluid], 1.0, atol=1e-6)
    back = resize_normals(np.moveaxis(view.normals, 0, -1), (40, 40))
    inner = np.hypot(yy - 20, xx - 20) < 10
    np.testing.assert_allclose(back[inner], np.moveaxis(n, 0, -1)[inner], atol=1e-5)


@pytest.mark.parametrize("spec, scale", [(InputSpec(True, "ellipsoid", "radius", 4.0), 1.0),
                                         (InputSpec(True, "ellipsoid", "radius", 3.0), 0.708),
                                         (InputSpec(True, "ellipsoid", "radius", 12.0), 2.833),
                                         (InputSpec(False, "ellipsoid", "radius", 3.0), 0.708),
                                         (InputSpec(True, "ellipsoid", "frame", 0.0), 1.0)])
def test_prepare_on_tensors_gives_numpys_input(spec, scale):
    """The refiner's input made from torch tensors (as on a GPU) is numpy's to rounding, at the
    working scale, scaled down (area) and up (bilinear), with either depth features, and so is the
    scaled target; the kind of the input is kept."""
    import torch

    ch, cam, r = _ball_view(96, 0.6)
    ch.update({f"target.N.{a}": ch[f"aniso_bilateral.N.{a}"] * 0.5 for a in "XYZ"})
    want = prepare(ch, spec, cam.focal_px, r, with_target=True)
    got = prepare({k: torch.from_numpy(v) for k, v in ch.items()}, spec, cam.focal_px, r, with_target=True)
    assert want.scale == got.scale == pytest.approx(scale, abs=1e-3)
    assert isinstance(got.inputs, torch.Tensor) and got.inputs.dtype == torch.float32
    np.testing.assert_array_equal(got.fluid.numpy(), want.fluid)
    np.testing.assert_allclose(got.inputs.numpy(), want.inputs, atol=5e-5)
    np.testing.assert_allclose(got.target.numpy(), want.target, atol=1e-6)
