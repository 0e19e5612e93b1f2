"""The per-pixel temporal error: pixels followed with the particles' motion through two cameras, and
a method scored by how its change of normal differs from the reference's."""

from __future__ import annotations

import numpy as np

from pipeline.camera import Camera, look_at
from pipeline.config import DatasetConfig
from pipeline.evaluate.temporal import _world, normal_change, surface_flow, temporal_errors
from pipeline.metrics import angular_errors

R = 0.02
SIZE = 160


def _ball() -> np.ndarray:
    g = np.arange(-0.2, 0.2 + 1e-9, 1.6 * R)
    ball = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    ball = ball[np.linalg.norm(ball, axis=1) <= 0.2]
    return (ball + np.random.default_rng(3).uniform(-0.2, 0.2, ball.shape) * R).astype(np.float32)


def _surface(ss, x: np.ndarray, cam: Camera):
    """(view normals, mask, depth) of the particles' bilateral-filtered sphere splat: the reference."""
    sp = ss.splat(x, R, cam)
    depth = ss.bilateral(sp.depth, cam, R, DatasetConfig(width=cam.width, height=cam.height))
    return ss.normals(depth, cam), sp.mask > 0, depth


def test_a_translated_ball_is_followed_and_a_method_scored_against_the_references_change(ss):
    cam = Camera(look_at((0.0, 0.0, 1.2), (0.0, 0.0, 0.0)), 40.0, SIZE, SIZE)
    x0 = _ball()
    x1 = x0 + np.float32([0.05, 0.0, 0.0])
    n0, m0, d0 = _surface(ss, x0, cam)
    n1, m1, d1 = _surface(ss, x1, cam)
    flow = surface_flow(ss, x0, x1, R, cam, cam, d0, m0, d1, m1)
    assert flow.valid.sum() > 0.8 * m0.sum()
    # the ball's centre moves by this many pixels, and every followed pixel with it (perspective: a
    # point nearer the camera moves further, by up to a tenth here)
    # every followed pixel moves as the particles under it: 0.05 m across at its depth (a point
    # nearer the camera further), within the particle centres' radius behind the surface
    rr, cc = np.mgrid[0:SIZE, 0:SIZE]
    shift = (flow.cols - cc)[flow.valid]
    expected = cam.focal_px * 0.05 / d0[flow.valid]
    assert expected.min() > 8
    np.testing.assert_allclose(shift, expected, rtol=0.06)
    assert np.abs((flow.rows - rr)[flow.valid]).max() < 1.0
    # the reference against itself: no error, every followed pixel scored
    truth = normal_change(flow, n0, n1, m1, cam, cam)
    same, missed = temporal_errors(flow, (n0, m0), (n1, m1), truth, cam, cam)
    assert missed == 0 and same.size == flow.valid.sum() and same.max() < 1e-5
    # a method that does not move with the fluid changes where the reference does not
    still, _ = temporal_errors(flow, (n0, m0), (n0, m0), truth, cam, cam)
    assert np.median(still) > 5.0
    # a method that turns its normals over from one frame to the next: 180 degrees
    flipped, _ = temporal_errors(flow, (n0, m0), (-n1, m1), truth, cam, cam)
    np.testing.assert_allclose(flipped, 180.0, atol=0.5)
    # pixels a method does not show at t+1 are counted apart, not scored
    holed = m1.copy()
    holed[:, : SIZE // 2] = False
    part, missed = temporal_errors(flow, (n0, m0), (n1, holed), truth, cam, cam)
    assert missed > 0 and part.size + missed == flow.valid.sum()


def test_a_still_fluid_under_a_turning_camera_keeps_its_world_normals(ss):
    """The camera turns 6 degrees about the ball; the fluid holds still, so a followed pixel's
    world normal on its mesh stays where the view normals differ by the camera's turn."""
    from pipeline.parallel import Launcher
    from pipeline.surface import reconstruct
    from pipeline.views import target_channels

    x = _ball()
    eye = np.array([0.0, 0.0, 1.2])
    turn = np.radians(6.0)
    eye1 = np.array([np.sin(turn), 0.0, np.cos(turn)]) * 1.2
    cam0 = Camera(look_at(eye, (0.0, 0.0, 0.0)), 40.0, SIZE, SIZE)
    cam1 = Camera(look_at(eye1, (0.0, 0.0, 0.0)), 40.0, SIZE, SIZE)
    launch = Launcher("cpu")
    try:
        mesh = reconstruct(x, R, DatasetConfig(), launch)
        (n0, m0, d0), (n1, m1, d1) = (
            (np.stack([t[f"target.N.{a}"] for a in "XYZ"], -1), t["target.A"] > 0, np.where(t["target.A"] > 0,
                                                                                             t["target.Z"], 0.0))
            for t in (target_channels(mesh, cam, launch) for cam in (cam0, cam1)))
    finally:
        launch.close()
    flow = surface_flow(ss, x, x, R, cam0, cam1, d0, m0, d1, m1)
    assert flow.valid.sum() > 0.8 * m0.sum()
    on = flow.valid
    everywhere = np.ones(on.sum(), bool)
    world = angular_errors(flow.sample(_world(n1, cam1), m1)[on], _world(n0, cam0)[on], everywhere)
    view = angular_errors(flow.sample(n1.astype(np.float64), m1)[on], n0[on], everywhere)
    assert np.median(world) < 1.0 and np.median(view) > 4.0
