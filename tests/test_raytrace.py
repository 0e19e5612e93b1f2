"""Ray-traced targets: the iso-surface of one and two kernels against the closed-form density."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from pipeline.camera import Camera, look_at
from pipeline.config import DatasetConfig
from pipeline.surface import kernels as K
from pipeline.surface import raytrace_maps

R = 0.01
P = DatasetConfig(iso_level=0.5, raytrace_step_radii=0.5, raytrace_bisections=20)


@pytest.fixture
def runners(ss, launch):
    return ss, launch


def _kernels(centres: np.ndarray, support: float):
    """Isotropic kernels G = I / support, as ``anisotropic_kernels`` would return them."""
    n = len(centres)
    g = np.repeat((np.eye(3) / support)[None], n, 0).astype(np.float32)
    return (wp.array(centres.astype(np.float32), dtype=wp.vec3), wp.array(g, dtype=wp.mat33),
            wp.array(np.full(n, support, np.float32), dtype=float))


def _density(x: np.ndarray, centres: np.ndarray, support: float) -> np.ndarray:
    amplitude = (2 * R) ** 3 * K.POLY6_NORM / support**3
    q2 = (((x[..., None, :] - centres) / support) ** 2).sum(-1)
    return amplitude * (np.clip(1 - q2, 0, None) ** 3).sum(-1)


def _gradient(x: np.ndarray, centres: np.ndarray, support: float) -> np.ndarray:
    d = x[..., None, :] - centres
    q2 = ((d / support) ** 2).sum(-1, keepdims=True)
    return (-6 * np.clip(1 - q2, 0, None) ** 2 * d / support**2).sum(-2)


def _camera(size: int = 96) -> Camera:
    return Camera(look_at((0, 0, 0), (0, 0, -1)), 10.0, size, size)


def test_one_kernel_is_the_closed_form_sphere(runners):
    """phi = A / H^3 (1 - |x - c|^2 / H^2)^3 crosses the iso-level on a sphere of radius
    H sqrt(1 - (iso H^3 / A)^(1/3)); depth, mask, thickness and normal against the ray-sphere hit."""
    ss, launch = runners
    support = 2.5 * R
    centre = np.array([0.002, -0.001, -0.3])
    cam = _camera()
    n, depth, mask, thick = raytrace_maps(_kernels(centre[None], support), R, P, cam, ss, launch,
                                          with_thickness=True)
    amplitude = (2 * R) ** 3 * K.POLY6_NORM
    radius = support * np.sqrt(1 - (P.iso_level * support**3 / amplitude) ** (1 / 3))
    assert 0.8 * R < radius < R
    rays = cam.pixel_rays().astype(np.float64)
    rays = rays / -rays[..., 2:3]
    a, b, cc = (rays**2).sum(-1), rays @ centre, centre @ centre - radius**2
    disc = b * b - a * cc
    hit = disc > 0
    inner = disc > 0.05 * disc.max()
    assert inner.sum() > 300
    assert (mask[inner] > 0).all() and not mask[~hit].any()
    t0 = (b - np.sqrt(np.where(hit, disc, 0))) / a
    np.testing.assert_allclose(depth[inner], t0[inner], atol=2e-6)
    normal = rays * t0[..., None] - centre
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    cos = (n[inner] * normal[inner]).sum(-1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.05
    chord = 2 * np.sqrt(np.where(hit, disc, 0)) / a * np.linalg.norm(rays, axis=-1)
    np.testing.assert_allclose(thick[inner], chord[inner], atol=5e-6)


def test_two_kernels_first_crossing_and_gradient_normal(runners):
    """Two overlapping kernels, one behind the other and offset: on every pixel the marched depth
    is the first iso crossing found by dense sampling of the closed-form density, the density there
    is the iso-level, and the normal is -grad phi."""
    ss, launch = runners
    support = 3.0 * R
    centres = np.array([[0.0, 0.0, -0.3], [0.012, 0.006, -0.315]])
    cam = _camera()
    n, depth, mask, _ = raytrace_maps(_kernels(centres, support), R, P, cam, ss, launch)
    rays = cam.pixel_rays().astype(np.float64)
    rays = rays / -rays[..., 2:3]
    ts = np.linspace(0.25, 0.35, 20001)
    fluid = np.argwhere(mask > 0)
    assert len(fluid) > 500
    for y, x in fluid[:: max(1, len(fluid) // 150)]:
        phi = _density(rays[y, x] * ts[:, None], centres, support)
        first = ts[np.argmax(phi >= P.iso_level)]
        assert phi.max() >= P.iso_level and abs(depth[y, x] - first) < 1e-5
        p = rays[y, x] * depth[y, x]
        assert abs(_density(p[None], centres, support)[0] - P.iso_level) < 1e-3
        g = -_gradient(p[None], centres, support)[0]
        g /= np.linalg.norm(g)
        assert np.degrees(np.arccos(np.clip(n[y, x] @ g, -1, 1))) < 0.1
    # and no pixel is missed where the ray stays inside for at least a march step (a fixed-step
    # march can step over a shorter grazing chord: what a finer raytrace_step_radii is for)
    sample = rays[::4, ::4, None, :] * ts[None, None, ::20, None]
    inside = (_density(sample, centres, support) >= P.iso_level).sum(-1) * (ts[20] - ts[0])
    assert (inside > 0).sum() > 30
    assert (mask[::4, ::4] > 0)[inside >= P.raytrace_step_radii * R].all()
