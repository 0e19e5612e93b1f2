"""Deferred shading against closed-form values, and the compositing rules."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.camera import Camera, look_at
from pipeline.config import RenderConfig
from pipeline.shading import Shader, fresnel_f0

SIZE = 33  # odd: the centre pixel looks exactly down -Z
C = SIZE // 2


def _camera() -> Camera:
    return Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, SIZE, SIZE)


def _buffers(thickness=0.1, normal=(0.0, 0.0, 1.0)):
    n = np.zeros((SIZE, SIZE, 3), np.float32)
    n[...] = normal
    depth = np.ones((SIZE, SIZE), np.float32)
    return n, depth, np.full((SIZE, SIZE), thickness, np.float32), np.ones((SIZE, SIZE), np.float32)


def _shade(shader, p, background=None, background_depth=None, **kw):
    n, d, t, m = _buffers(**kw)
    bg = np.zeros((SIZE, SIZE, 3), np.float32) if background is None else background
    bgd = np.zeros((SIZE, SIZE), np.float32) if background_depth is None else background_depth
    return shader.shade(n, d, t, m, bg, bgd, _camera(), p)


@pytest.fixture(scope="module")
def black_env():
    s = Shader("cpu", environment=np.zeros((4, 8, 3), np.float32))
    yield s
    s.close()


@pytest.mark.parametrize("model", ["ggx", "blinn"])
def test_flat_normal_facing_the_light_gives_the_analytic_value(black_env, model):
    p = RenderConfig(light_dir=(0.0, 0.0, 1.0), specular=model, roughness=0.3, light_intensity=2.0,
                     diffuse_weight=0.2, fluid_color=(0.5, 0.7, 0.9))
    out = _shade(black_env, p)[C, C]
    f0 = fresnel_f0(p.ior)
    alpha = p.roughness**2
    if model == "ggx":
        spec = f0 / (4 * math.pi * alpha**2)  # D = 1 / (pi alpha^2), G = 1, F = F0, at N = L = V = H
    else:
        spec = (2 / alpha**2 - 2 + 8) / (8 * math.pi) * f0
    expected = np.array(p.fluid_color) * p.diffuse_weight * p.light_intensity + spec * p.light_intensity
    np.testing.assert_allclose(out[:3], expected, rtol=1e-4)
    assert out[3] == 1.0


def test_fresnel_at_normal_incidence_is_f0():
    white = Shader("cpu", environment=np.ones((4, 8, 3), np.float32))
    p = RenderConfig(light_intensity=0.0, diffuse_weight=0.0)
    out = _shade(white, p)[C, C]
    white.close()
    assert abs(fresnel_f0(1.33) - 0.0201) < 1e-4
    np.testing.assert_allclose(out[:3], fresnel_f0(p.ior), rtol=1e-5)


def test_zero_thickness_leaves_the_background_unchanged(black_env):
    rng = np.random.default_rng(0)
    bg = rng.random((SIZE, SIZE, 3)).astype(np.float32)
    out = _shade(black_env, RenderConfig(), background=bg, thickness=0.0)
    np.testing.assert_array_equal(out[..., :3], bg)
    assert not out[..., 3].any()


def test_thicker_fluid_absorbs_more_and_objects_in_front_win(black_env):
    bg = np.ones((SIZE, SIZE, 3), np.float32)
    p = RenderConfig(light_intensity=0.0, diffuse_weight=0.0, refraction_strength=0.0)
    thin = _shade(black_env, p, background=bg, thickness=0.05)[C, C, :3]
    thick = _shade(black_env, p, background=bg, thickness=0.5)[C, C, :3]
    assert np.all(thick < thin)
    # red is absorbed most for a blue-green fluid colour
    assert thick[0] < thick[2]
    f0 = fresnel_f0(p.ior)
    sigma = -np.log(np.array(p.fluid_color)) * p.absorption
    np.testing.assert_allclose(thin, (1 - f0) * np.exp(-sigma * 0.05), rtol=1e-4)
    near = np.full((SIZE, SIZE), 0.5, np.float32)  # an object at 0.5 m, the fluid at 1 m
    out = _shade(black_env, p, background=bg, background_depth=near)
    np.testing.assert_array_equal(out[..., :3], bg)
