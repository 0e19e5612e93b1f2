"""Deferred shading against closed-form values, and the compositing rules (premultiplied alpha,
depth of the nearest surface, Snell refraction, normals bent towards the viewer, environment maps)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.camera import Camera, look_at
from pipeline.config import RenderConfig
from pipeline.shading import Shader, fresnel_f0, load_environment, srgb_to_linear

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
    return shader.shade(n, d, t, m, bg, bgd, _camera(), p).beauty


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
    np.testing.assert_array_equal(out[..., 3], 1.0)  # the scene background is opaque


def test_thicker_fluid_absorbs_more_and_objects_in_front_win(black_env):
    bg = np.ones((SIZE, SIZE, 3), np.float32)
    p = RenderConfig(light_intensity=0.0, diffuse_weight=0.0)
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


def test_alpha_is_premultiplied_over_the_scene_and_over_nothing(black_env):
    """Half the image is fluid: the fluid layer is colour times coverage, the beauty is that over
    the background (opaque) or over transparent black, and depth is the nearest surface's."""
    n, d, t, m = _buffers()
    m[:, C:] = 0.0
    bg = np.full((SIZE, SIZE, 3), 0.25, np.float32)
    bgd = np.full((SIZE, SIZE), 3.0, np.float32)
    bgd[:4] = 0.0  # the sky above
    over = black_env.shade(n, d, t, m, bg, bgd, _camera(), RenderConfig())
    alone = black_env.shade(n, d, t, m, bg, np.zeros_like(bgd), _camera(), RenderConfig(background="none"))
    fluid = m > 0
    for out in (over, alone):
        np.testing.assert_array_equal(out.fluid[..., 3], fluid)
        assert not out.fluid[~fluid].any()
        np.testing.assert_array_equal(out.beauty[fluid], out.fluid[fluid])
    np.testing.assert_array_equal(over.beauty[~fluid], np.append(bg[0, 0], 1.0)[None].repeat((~fluid).sum(), 0))
    assert not alone.beauty[~fluid].any(), "RGB is 0 where A is 0"
    np.testing.assert_array_equal(over.depth[fluid], 1.0)
    np.testing.assert_array_equal(over.depth[~fluid & (bgd > 0)], 3.0)
    assert np.isinf(over.depth[~fluid & (bgd == 0)]).all() and np.isinf(alone.depth[~fluid]).all()
    assert not over.normals_view[~fluid].any()


def test_refraction_follows_snell_through_the_thickness(black_env):
    """A tilted surface over a horizontal ramp: the background is read where the refracted ray
    leaves the fluid's thickness, projected at that depth (for a centre pixel, analytically)."""
    ramp = np.broadcast_to(np.arange(SIZE, dtype=np.float32)[None, :, None], (SIZE, SIZE, 3)).copy()
    p = RenderConfig(light_intensity=0.0, diffuse_weight=0.0, absorption=0.0, ior=1.33, refraction_strength=1.0)
    tilt = np.radians(30)
    normal = (math.sin(tilt), 0.0, math.cos(tilt))
    thickness = 0.2
    out = _shade(black_env, p, background=ramp, thickness=thickness, normal=normal)[C, C, :3]
    cos_i = math.cos(tilt)
    sin_t = math.sin(tilt) / p.ior
    # the refracted direction in the plane of the view ray (-Z) and the normal, then its lateral
    # offset per unit depth (tan of the angle to -Z) over the thickness
    bend = tilt - math.asin(sin_t)  # the ray turns towards -normal by the difference of the angles
    offset_m = thickness * math.tan(-bend)
    col = C + 0.5 + _camera().focal_px * offset_m / (1.0 + thickness)
    f = fresnel_f0(p.ior) + (1 - fresnel_f0(p.ior)) * (1 - cos_i) ** 5
    np.testing.assert_allclose(out, (1 - f) * (col - 0.5), rtol=1e-4)
    assert col < C + 0.5 - 1, "a visible shift"


def test_normals_facing_away_are_bent_towards_the_viewer(black_env):
    """A normal pointing away from the camera (screen-space noise at an edge) is shaded as one
    that faces it at ``min_facing``, not as a mirror of what lies behind the camera."""
    p = RenderConfig(min_facing=0.3)
    n, d, t, m = _buffers(normal=(0.0, 0.6, -0.8))
    out = black_env.shade(n, d, t, m, np.ones((SIZE, SIZE, 3), np.float32), np.zeros((SIZE, SIZE), np.float32),
                          _camera(), p)
    bent = out.normals_view[C, C]
    np.testing.assert_allclose(np.linalg.norm(bent), 1.0, rtol=1e-5)
    # n + v (0.3 - n.v) = (0, 0.6, 0.3), normalised; v = +Z at the centre pixel
    np.testing.assert_allclose(bent, np.array([0.0, 0.6, 0.3]) / np.linalg.norm([0.0, 0.6, 0.3]), rtol=1e-5)
    assert bent[1] > 0, "it keeps its direction across the image"
    untouched = black_env.shade(*_buffers(normal=(0.0, 0.6, 0.8)), np.ones((SIZE, SIZE, 3), np.float32),
                                np.zeros((SIZE, SIZE), np.float32), _camera(), p).normals_view[C, C]
    np.testing.assert_allclose(untouched, [0.0, 0.6, 0.8], atol=1e-6)


def _longitude_map(width: int = 64) -> np.ndarray:
    """A lat-long map whose red is the column (so a lookup tells which longitude it hit)."""
    env = np.zeros((32, width, 3), np.float32)
    env[..., 0] = np.arange(width)[None, :]
    env[..., 1] = 1.0
    return env


def test_environment_rotation_and_strength():
    """The centre pixel looks down -Z, the middle of the map; turned by 90 degrees counter-clockwise
    (seen from above) the map shows there what it had at +X (three quarters across)."""
    w = 64
    shader = Shader("cpu", environment=_longitude_map(w))
    empty = np.zeros((SIZE, SIZE, 3), np.float32), np.zeros((SIZE, SIZE), np.float32)
    base = shader.fill_sky(*empty, _camera(), RenderConfig())[C, C]
    turned = shader.fill_sky(*empty, _camera(), RenderConfig(environment_rotation_deg=90.0))[C, C]
    strong = shader.fill_sky(*empty, _camera(), RenderConfig(environment_strength=2.5))[C, C]
    shader.close()
    assert base[0] == pytest.approx(w / 2 - 0.5, abs=1e-3)  # u = 0.5: between columns 31 and 32
    assert turned[0] == pytest.approx(3 * w / 4 - 0.5, abs=1e-3)  # what was at +X turned to -Z
    np.testing.assert_allclose(strong, 2.5 * base, rtol=1e-6)


def _write_rgbe(path, rgb: np.ndarray) -> None:
    """A flat (not run-length encoded) Radiance file, written by hand from exact powers of two."""
    h, w, _ = rgb.shape
    e = np.floor(np.log2(np.maximum(rgb.max(-1), 1e-30))).astype(int) + 1
    mant = np.round(rgb / np.ldexp(1.0, e)[..., None] * 256).clip(0, 255)
    data = np.concatenate([mant, (e + 128)[..., None]], -1).astype(np.uint8)
    path.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode() + data.tobytes())


def test_environment_maps_load_from_exr_and_hdr(tmp_path):
    from pipeline.exr import write_exr

    rgb = np.ldexp(1.0, np.arange(-3, 9)).reshape(2, 2, 3).astype(np.float32)  # exact in RGBE
    _write_rgbe(tmp_path / "flat.hdr", rgb)
    np.testing.assert_array_equal(load_environment(tmp_path / "flat.hdr"), rgb)
    write_exr(tmp_path / "env.exr", {c: rgb[..., k] for k, c in enumerate("RGB")})
    np.testing.assert_array_equal(load_environment(tmp_path / "env.exr"), rgb)
    with pytest.raises(ValueError, match="bad.png"):
        load_environment(tmp_path / "bad.png")


def test_run_length_encoded_hdr_matches_openimageio(tmp_path):
    """A second writer: OpenImageIO's .hdr (run-length encoded scanlines) reads back the same."""
    oiio = pytest.importorskip("OpenImageIO")
    rng = np.random.default_rng(1)
    rgb = (rng.random((9, 40, 3)) * 50).astype(np.float32)
    rgb[:, 10:30] = 3.0  # runs
    out = oiio.ImageOutput.create(str(tmp_path / "env.hdr"))
    assert out.open(str(tmp_path / "env.hdr"), oiio.ImageSpec(40, 9, 3, oiio.FLOAT))
    assert out.write_image(rgb)
    out.close()
    expected = oiio.ImageBuf(str(tmp_path / "env.hdr")).get_pixels(oiio.FLOAT)
    np.testing.assert_allclose(load_environment(tmp_path / "env.hdr"), expected, rtol=1e-6)
    assert (np.abs(expected - rgb) <= rgb.max(-1, keepdims=True) / 64).all(), "RGBE keeps 8 bits of the largest"


def _random_buffers(seed: int):
    """Random unit normals facing the camera, depth, thickness, a mask with holes, a background
    and its depth: every branch of the shading kernel in one frame."""
    rng = np.random.default_rng(seed)
    n = rng.normal(size=(SIZE, SIZE, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[..., 2] = np.abs(n[..., 2])
    depth = rng.uniform(0.5, 2.0, (SIZE, SIZE)).astype(np.float32)
    thickness = rng.uniform(0.0, 0.2, (SIZE, SIZE)).astype(np.float32)
    mask = (rng.random((SIZE, SIZE)) > 0.3).astype(np.float32)
    bg = rng.random((SIZE, SIZE, 3)).astype(np.float32)
    bgd = rng.uniform(1.0, 3.0, (SIZE, SIZE)).astype(np.float32)
    return n, depth, thickness, mask, bg, bgd


def test_the_gpu_way_of_returning_passes_gives_the_same_passes():
    """On a GPU the shader writes device arrays and copies each into its host pass (``_result``);
    run that way on the CPU (a device array, then the copy) it must give every pass as the direct
    write into the host arrays does."""
    n, depth, thickness, mask, bg, bgd = _random_buffers(3)
    passes = []
    for device_way in (False, True):
        shader = Shader("cpu")
        shader._cpu = not device_way
        out = shader.shade(n, depth, thickness, mask, bg, bgd, _camera(), RenderConfig())
        passes.append(out)
        shader.close()
    for name in ("beauty", "fluid", "depth", "normals_view", "normals_world"):
        np.testing.assert_array_equal(getattr(passes[1], name), getattr(passes[0], name), err_msg=name)
    assert passes[0].beauty[..., 3].min() > 0


def test_the_shader_reads_torch_tensors_as_it_reads_arrays():
    """On a GPU the refined frame hands the shader torch tensors on the device (its normals and
    thickness). Read where they lie (``wp.from_torch``), even as a strided view of a bigger tensor,
    they must shade into the passes the same values as host arrays give."""
    import torch

    n, depth, thickness, mask, bg, bgd = _random_buffers(4)
    shader = Shader("cpu")
    want = shader.shade(n, depth, thickness, mask, bg, bgd, _camera(), RenderConfig())
    both = torch.from_numpy(np.stack([thickness, depth], -1))  # the thickness as a strided view
    got = shader.shade(torch.from_numpy(n.copy()), depth, both[..., 0], torch.from_numpy(mask), bg, bgd, _camera(),
                       RenderConfig())
    shader.close()
    for name in ("beauty", "fluid", "depth", "normals_view", "normals_world"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def test_a_silhouette_wider_than_the_splat_is_shaded_to_its_edge():
    """A refined or mesh silhouette reaches past the particles' splat, where the splat's thickness
    is 0 and the shader would show nothing. ``shade_frame`` gives each such pixel a covered
    neighbour's thickness, ring by ring: the fluid shows over the method's whole mask, the splat's
    own pixels keep their thickness, pixels off the mask stay empty; a tensor (the GPU's way) gets
    the same thickness, as a tensor."""
    import torch

    from pipeline.methods import shade_frame, shading_thickness

    yy, xx = np.mgrid[:SIZE, :SIZE]
    r = np.hypot(yy - C, xx - C)
    thickness = np.where(r < 6, 0.05 + 0.01 * (6 - r), 0.0).astype(np.float32)  # the splat
    mask = (r < 10).astype(np.float32)  # the method's wider silhouette
    n, depth, _, _ = _buffers()
    src = {"normals": n, "depth": depth, "thickness": thickness, "mask": mask}
    bg = np.full((SIZE, SIZE, 3), 0.5, np.float32)
    shader = Shader("cpu")
    frame = shade_frame(src, bg, np.zeros((SIZE, SIZE), np.float32), _camera(), RenderConfig(), shader)
    bare = shader.shade(n, depth, thickness, mask, bg, np.zeros((SIZE, SIZE), np.float32), _camera(), RenderConfig())
    shader.close()
    rim = (r >= 6) & (r < 10)
    assert (bare.fluid[rim, 3] == 0).all()  # the splat's thickness alone leaves the rim out
    assert (frame.fluid[mask > 0, 3] > 0).all() and (frame.fluid[mask == 0, 3] == 0).all()
    np.testing.assert_array_equal(frame.thickness[r < 6], thickness[r < 6])
    assert (frame.thickness[rim] > 0).all() and (frame.thickness[rim] <= 0.05 + 0.01 * 1.0 + 1e-6).all()
    np.testing.assert_array_equal(frame.thickness[mask == 0], 0.0)
    assert shading_thickness(thickness, thickness > 0) is thickness  # nothing to fill: the same map
    on_device = shading_thickness(torch.from_numpy(thickness), mask)
    assert isinstance(on_device, torch.Tensor)
    np.testing.assert_array_equal(on_device.numpy(), frame.thickness)


def test_the_sky_left_on_the_device_is_the_host_sky_and_shades_alike():
    """On a GPU the render loop keeps the filled background on the device for every method of the
    frame (``fill_sky(on_device=True)``): the same pixels as the host background, and the same
    passes shaded over it."""
    import torch

    n, depth, thickness, mask, bg, bgd = _random_buffers(5)
    bgd[:, : SIZE // 2] = 0.0  # half the frame has no rasterised background: the sky shows there
    shader = Shader("cpu", environment=_longitude_map())
    host = shader.fill_sky(bg, bgd, _camera(), RenderConfig())
    dev = shader.fill_sky(bg, bgd, _camera(), RenderConfig(), on_device=True)
    assert isinstance(dev, torch.Tensor) and dev.shape == host.shape
    np.testing.assert_array_equal(dev.numpy(), host)
    assert not np.array_equal(host[:, : SIZE // 2], bg[:, : SIZE // 2])
    want = shader.shade(n, depth, thickness, mask, host, bgd, _camera(), RenderConfig())
    got = shader.shade(n, depth, thickness, mask, dev, bgd, _camera(), RenderConfig())
    shader.close()
    for name in ("beauty", "fluid", "depth", "normals_view", "normals_world"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)


def test_tonemap_table_is_within_one_code_of_the_curve():
    """The preview's table lookup follows the exact ACES + sRGB curve to one 8-bit code over the whole
    HDR range and at any exposure; below zero and NaN are black, +inf white."""
    from pipeline.shading import tonemap, tonemap_exact

    ramp = np.geomspace(1e-6, 1e4, 200_000, dtype=np.float32)
    rgb = np.stack([ramp, ramp[::-1], np.linspace(0, 2, ramp.size, dtype=np.float32)], -1)[None]
    for exposure in (0.0, -1.5, 2.0):
        got, want = tonemap(rgb, exposure).astype(int), tonemap_exact(rgb, exposure).astype(int)
        assert np.abs(got - want).max() <= 1
        assert (got != want).mean() < 0.01
        assert np.unique(got).size == 256  # every code reached: no bucket swallows a range
    odd = np.array([[[-1.0, np.nan, -0.0], [np.inf, -np.inf, 1e30]]], np.float32)
    np.testing.assert_array_equal(tonemap(odd), [[[0, 0, 0], [255, 0, 255]]])


def test_srgb_codes_decode_to_the_standard_curve():
    """The 256 8-bit codes (looked up) give the sRGB curve: linear below 0.04045, the 2.4 power
    above, 0 and 1 at the ends, and any array of codes decodes as the same values in float."""
    codes = np.arange(256, dtype=np.uint8)
    x = codes / 255.0
    curve = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    table = srgb_to_linear(codes)
    assert table.dtype == np.float32 and table[0] == 0.0 and table[255] == 1.0
    np.testing.assert_allclose(table, curve, rtol=1e-6)
    image = np.random.default_rng(0).integers(0, 256, (5, 7, 3)).astype(np.uint8)
    np.testing.assert_array_equal(srgb_to_linear(image), srgb_to_linear(image.astype(np.float64)))
