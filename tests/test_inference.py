"""Render-time refiner inference: the folded, channels-last, cropped network computes what the
plain training-time module computes, on the pixels that matter."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from pipeline.model.inference import CROP_MARGIN_PX, Refiner, fluid_window
from pipeline.model.networks import Generator
from pipeline.model.trainer import predict


def _trained_looking_generator(seed: int = 0) -> Generator:
    """A small generator whose batch-norm statistics are far from the identity (so folding them
    into the convolutions is exercised)."""
    torch.manual_seed(seed)
    g = Generator(in_channels=5, base_channels=8, downsamples=2, res_blocks=2)
    g.train()
    with torch.no_grad():
        for _ in range(3):
            g(torch.randn(2, 5, 32, 32) * 3 + 1)
    return g.eval()


def _blob_input(h: int, w: int, centre: tuple[int, int], radius: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """C x H x W input that is zero outside a disc of fluid (like a real frame's background)."""
    yy, xx = np.mgrid[:h, :w]
    fluid = (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 < radius**2
    x = np.random.default_rng(seed).normal(size=(5, h, w)).astype(np.float32)
    return np.where(fluid, x, 0.0).astype(np.float32), fluid


def test_refiner_matches_plain_forward_inside_the_fluid(monkeypatch):
    import pipeline.model.inference as inference

    monkeypatch.setattr(inference, "FLIP_MAX_PIXELS", 0)  # one pass: the crop and folding alone
    g = _trained_looking_generator()
    x, fluid = _blob_input(150, 210, (97, 61), 20)  # sizes not multiples of the stride
    plain = predict(g, x)
    fast = Refiner(g, margin=g.receptive_radius())(x, fluid)
    window = fluid_window(fluid, g.receptive_radius(), g.stride)
    assert window[0] > 0 and window[2] > 0 and window[3] < 210, "the crop must actually cut the image"
    np.testing.assert_allclose(fast[fluid], plain[fluid], atol=2e-5)
    outside = np.ones(fluid.shape, bool)
    outside[window[0]:window[1], window[2]:window[3]] = False
    assert not fast[outside].any() and np.abs(fast[fluid]).min() < np.abs(fast[fluid]).max()
    # without cropping, every pixel agrees (folding and the memory layout change only rounding)
    np.testing.assert_allclose(Refiner(g, crop=False)(x), plain, atol=2e-5)


def test_small_inputs_are_refined_as_the_mean_of_the_view_and_its_mirror(monkeypatch):
    """Under ``FLIP_MAX_PIXELS`` the refiner averages the network's normals of the view and of its
    left-right mirror (normal X negated), so a mirrored view gets exactly the mirrored normals;
    above it, one plain pass."""
    import pipeline.model.inference as inference

    g = _trained_looking_generator()
    x, _ = _blob_input(96, 160, (50, 70), 30)  # multiples of the stride: no padding to mirror
    flip = np.array([-1.0, 1.0, 1.0], np.float32)
    mirror_in = x[:, :, ::-1] * np.array([-1, 1, 1, 1, 1], np.float32)[:, None, None]
    plain = predict(g, x)
    mirrored = predict(g, np.ascontiguousarray(mirror_in))[:, ::-1] * flip
    fast = Refiner(g, crop=False)(x)
    np.testing.assert_allclose(fast, 0.5 * (plain + mirrored), atol=2e-5)
    assert np.abs(plain - mirrored).max() > 1e-3  # the untrained network is not mirror-symmetric
    np.testing.assert_allclose(Refiner(g, crop=False)(np.ascontiguousarray(mirror_in))[:, ::-1] * flip, fast,
                               atol=2e-5)
    monkeypatch.setattr(inference, "FLIP_MAX_PIXELS", 96 * 160 - 1)
    np.testing.assert_allclose(Refiner(g, crop=False)(x), plain, atol=2e-5)


def test_receptive_radius_bounds_the_influence_of_far_pixels():
    """Changing every input pixel farther than the receptive radius (Chebyshev distance) from a pixel
    leaves its output unchanged; changing pixels somewhat inside it does not."""
    g = _trained_looking_generator(2)
    r = g.receptive_radius()
    size = 2 * r + 40
    c = size // 2 - size // 2 % g.stride
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, size, size)).astype(np.float32)
    yy, xx = np.mgrid[:size, :size]
    dist = np.maximum(np.abs(yy - c), np.abs(xx - c))
    far = np.where(dist > r, rng.normal(size=x.shape).astype(np.float32), x)
    base = predict(g, x)[c, c]
    np.testing.assert_allclose(predict(g, far)[c, c], base, atol=1e-6)
    near = np.where((dist > r // 2) & (dist <= r), rng.normal(size=x.shape).astype(np.float32), x)
    assert np.abs(predict(g, near)[c, c] - base).max() > 1e-4


def test_the_default_crop_keeps_the_shipped_refiners_normals():
    """The network's input reaches ``CROP_MARGIN_PX`` past the fluid, less than its receptive radius:
    the shipped generator's fluid normals must stay within a hundredth of a degree of the whole
    image's (on this small view, whose fluid lies near its box's edge, 16 px moved them by 0.08 degree
    on average, at most 0.5; 8 px by 0.5, at most 2.4)."""
    from pipeline.methods import MAX_WORKING_PIXELS, UPSCALE_BELOW_PX
    from pipeline.model.data import prepare

    refiner, ch, cam = _refine_view()
    view = prepare(ch, refiner.spec, cam.focal_px, VIEW_RADIUS, max_pixels=MAX_WORKING_PIXELS,
                   upscale_below_px=UPSCALE_BELOW_PX)
    h, w = view.fluid.shape
    y0, y1, x0, x1 = fluid_window(view.fluid, refiner.margin, refiner.stride)
    assert refiner.margin == CROP_MARGIN_PX and (y1 - y0) * (x1 - x0) < h * w, "the crop must cut"
    whole = copy.copy(refiner)
    whole.crop = False
    a, b = refiner(view.inputs, view.fluid)[view.fluid], whole(view.inputs)[view.fluid]
    cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    assert 0.0 < angle.mean() < 0.02 and angle.max() < 0.2


def test_refiner_without_fluid_returns_zeros():
    g = _trained_looking_generator()
    x = np.zeros((5, 64, 64), np.float32)
    assert not Refiner(g)(x, np.zeros((64, 64), bool)).any()


VIEW_RADIUS = 0.012
"""Particles of about 5 px in ``_refine_view``'s 160 px view: the working scale brings them down."""


def _refine_view():
    """The shipped refiner and the channels of a small blob of particles at 160 px, which its
    working scale resamples (with the ellipsoid splat when the refiner takes it)."""
    from pipeline.camera import Camera, look_at
    from pipeline.config import DatasetConfig
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner
    from pipeline.screen import ScreenSpace
    from pipeline.views import screen_space_inputs

    x = (np.random.default_rng(2).normal(size=(2500, 3)) * (0.06, 0.03, 0.05) + (0, 0, -0.5)).astype(np.float32)
    cam = Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, 160, 160)
    ss = ScreenSpace("cpu")
    ch = screen_space_inputs(x, VIEW_RADIUS, cam, DatasetConfig(), ss, filters=("bilateral",))
    ss.close()
    # float32, so that two ways of making the same input compare to its rounding (bfloat16 would
    # round them further apart: test_bfloat16_refiner_stays_within_rounding_of_float32)
    refiner = load_refiner(SHIPPED_WEIGHTS, precision="float32")
    if refiner.splat != "sphere":
        from pipeline.parallel import Launcher
        from pipeline.surface import particle_ellipsoids

        launch, ss = Launcher("cpu"), ScreenSpace("cpu")
        ch.update(screen_space_inputs(x, VIEW_RADIUS, cam, DatasetConfig(), ss, filters=None,
                                      ellipsoids=particle_ellipsoids(x, VIEW_RADIUS, DatasetConfig(), launch,
                                                                     density=True),
                                      aniso_filters=("bilateral",)))
        launch.close()
        ss.close()
    return refiner, ch, cam


def test_refine_gives_the_rule_of_refined_mask_and_extend_depth():
    """``refine`` computes the mask's reach and the extended depth from one distance transform and
    normalises only masked pixels; it must give what the separate rules give (``refined_mask``,
    ``extend_depth``, the normalised network output), at a size the working scale changes."""
    from pipeline.masks import REFINED_REACH_PX, refined_mask
    from pipeline.methods import MAX_WORKING_PIXELS, UPSCALE_BELOW_PX, extend_depth, refine
    from pipeline.model.data import input_channels, prepare
    from pipeline.model.scale import resize_normals

    refiner, ch, cam = _refine_view()
    names = input_channels(refiner.splat)
    normals, mask, depth = refine(refiner, ch, 0.5, cam.focal_px, VIEW_RADIUS)
    view = prepare(ch, refiner.spec, cam.focal_px, VIEW_RADIUS, max_pixels=MAX_WORKING_PIXELS,
                   upscale_below_px=UPSCALE_BELOW_PX)
    assert view.scale != 1.0, "the view must be resampled for the test to cover the way back"
    raw = resize_normals(refiner(view.inputs, view.fluid), mask.shape)
    fluid = ch[names.fluid] > 0
    want = refined_mask(raw, fluid, 0.5, REFINED_REACH_PX / view.scale)
    np.testing.assert_array_equal(mask, want)
    assert (mask & ~fluid).any(), "some refined pixels must reach past the splat"
    np.testing.assert_array_equal(normals[~mask], 0.0)
    np.testing.assert_array_equal(normals[mask], raw[mask] / np.linalg.norm(raw[mask], axis=-1, keepdims=True))
    np.testing.assert_array_equal(depth, extend_depth(ch[names.blurred], mask))


def test_refine_makes_the_input_on_the_device_as_numpy_does():
    """On a GPU the refiner's input is made in torch from the uploaded maps. The same code on CPU
    tensors must give numpy's refined normals, mask and depth to rounding: a wrong axis, a lost
    scale or a box filter of the wrong size would move them far more."""
    from pipeline.methods import refine
    from pipeline.model.data import input_channels, prepare

    refiner, ch, cam = _refine_view()
    host = refine(refiner, ch, 0.5, cam.focal_px, VIEW_RADIUS, on_device=False)
    dev = refine(refiner, ch, 0.5, cam.focal_px, VIEW_RADIUS, on_device=True)
    names = input_channels(refiner.splat)
    tensors = {c: torch.from_numpy(ch[c]) for c in refiner.spec.view_channels if c != names.fluid}
    a, b = (prepare(c, refiner.spec, cam.focal_px, VIEW_RADIUS) for c in (ch, tensors))
    assert isinstance(b.inputs, torch.Tensor) and b.scale == a.scale != 1.0
    np.testing.assert_array_equal(b.fluid.numpy(), a.fluid)
    np.testing.assert_allclose(b.inputs.numpy(), a.inputs, atol=5e-5)
    (n0, m0, z0), (n1, m1, z1) = host, dev
    assert m0.sum() > 100 and (m0 == m1).mean() > 0.999
    both = m0 & m1
    np.testing.assert_allclose(n1[both], n0[both], atol=1e-3)
    np.testing.assert_array_equal(z1[both], z0[both])


def test_the_refined_frame_kept_on_the_device_shades_as_the_host_frame():
    """On a GPU the refined method keeps its maps as torch tensors from the splat to the shader.
    Run that way on the CPU's tensors, the frame must carry the host frame's mask, depth and
    thickness exactly and its normals and colours to the rounding of the torch-made input."""
    import torch

    from pipeline.camera import Camera, look_at
    from pipeline.config import DatasetConfig, RenderConfig
    from pipeline.methods import normal_source, shade_frame
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner
    from pipeline.parallel import Launcher
    from pipeline.screen import ScreenSpace
    from pipeline.shading import Shader

    x = (np.random.default_rng(2).normal(size=(2500, 3)) * (0.06, 0.03, 0.05) + (0, 0, -0.5)).astype(np.float32)
    cam = Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, 128, 128)
    ss, launch, shader = ScreenSpace("cpu"), Launcher("cpu"), Shader("cpu")
    refiner = load_refiner(SHIPPED_WEIGHTS, precision="float32")  # the two ways, to float32 rounding
    bg, bg_depth = np.full((128, 128, 3), 0.5, np.float32), np.full((128, 128), 10.0, np.float32)
    frames, sources = {}, {}
    for on_device in (False, True):
        src = normal_source("refined", x, 0.004, cam, DatasetConfig(), ss, launch, refiner, on_device=on_device)
        sources[on_device] = src
        frames[on_device] = shade_frame(src, bg, bg_depth, cam, RenderConfig(width=128, height=128), shader)
    for closer in (ss, launch, shader):
        closer.close()
    if refiner.splat == "ellipsoid":  # the sphere refiner's maps are shared with other methods, on the host
        assert all(isinstance(sources[True][k], torch.Tensor) for k in ("normals", "mask", "depth", "thickness"))
    host, dev = frames[False], frames[True]
    assert host.mask.sum() > 500
    for name in ("mask", "depth", "thickness"):
        np.testing.assert_array_equal(getattr(dev, name), getattr(host, name), err_msg=name)
    fluid = host.mask > 0
    np.testing.assert_allclose(dev.normals[fluid], host.normals[fluid], atol=1e-4)
    # a specular highlight (HDR, up to about 40 here) multiplies the normals' rounding by its exponent
    np.testing.assert_allclose(dev.beauty, host.beauty, rtol=5e-3, atol=1e-3)


@pytest.mark.parametrize("height, scale", [(220, 1.0), (420, 0.5), (110, 2.0), (150, None)])
def test_refine_on_the_fluids_part_of_a_wide_view_gives_the_whole_views_numbers(height, scale, monkeypatch):
    """``refine`` prepares, resamples and masks only the fluid's part of a view (grown by all that
    reaches a fluid pixel, on the working scale's grid): bit for bit what the whole view gives, at a
    working scale of 1, 1/2 and 2. At 2^(1/2) no part is cut (its grid depends on the image's size).
    With ``UPSCALE_BELOW_PX`` lifted (whatever the shipped default) the upscaled scales are reached;
    below the particles' size, only a downscale is left."""
    import pipeline.methods as methods
    from pipeline.camera import Camera, look_at
    from pipeline.config import DatasetConfig
    from pipeline.methods import refine, refine_view, refine_window
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.data import input_channels
    from pipeline.model.inference import load_refiner
    from pipeline.model.scale import working_scale

    monkeypatch.setattr(methods, "UPSCALE_BELOW_PX", float("inf"))
    from pipeline.parallel import Launcher
    from pipeline.screen import ScreenSpace
    from pipeline.surface import particle_ellipsoids
    from pipeline.views import screen_space_inputs

    r = 0.004
    x = (np.random.default_rng(2).normal(size=(2500, 3)) * (0.06, 0.03, 0.05) + (0, 0, -0.5)).astype(np.float32)
    cam = Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, 3 * height, height)
    refiner = load_refiner(SHIPPED_WEIGHTS)
    launch, ss = Launcher("cpu"), ScreenSpace("cpu")
    ch = screen_space_inputs(x, r, cam, DatasetConfig(), ss, filters=("bilateral",))
    if refiner.splat != "sphere":
        ch.update(screen_space_inputs(x, r, cam, DatasetConfig(), ss, filters=None,
                                      ellipsoids=particle_ellipsoids(x, r, DatasetConfig(), launch, density=True),
                                      aniso_filters=("bilateral",)))
    launch.close()
    ss.close()
    names = input_channels(refiner.splat)
    raw, fluid = ch[names.raw], ch[names.fluid] > 0
    assert working_scale(raw, cam.focal_px, r, refiner.spec.working_radius_px, methods.MAX_WORKING_PIXELS) == \
        (scale or 2**0.5)
    # with an upscale limit below the particles' size, only a downscale is left
    no_up = working_scale(raw, cam.focal_px, r, refiner.spec.working_radius_px, upscale_below_px=0.0)
    assert no_up == min(scale or 2**0.5, 1.0)
    window = refine_window(refiner, raw, fluid, cam.focal_px, r)
    assert (window is None) == (scale is None)
    if window is not None:
        ys, xs = window
        assert (ys.stop - ys.start) * (xs.stop - xs.start) < 0.6 * raw.size, "a part, not the whole"
    part = refine(refiner, ch, 0.5, cam.focal_px, r)
    whole = refine_view(refiner, ch, 0.5, cam.focal_px, r)
    assert whole[1].sum() > 100
    for a, b in zip(part, whole, strict=True):
        np.testing.assert_array_equal(a, b)


def test_weights_that_are_not_the_ones_their_card_records_are_refused(tmp_path):
    """Random bytes inside a checkpoint can still load as numbers; the card's SHA-256 catches them."""
    import shutil

    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_weights

    pt, card = tmp_path / "refiner.pt", tmp_path / "refiner.json"
    shutil.copyfile(SHIPPED_WEIGHTS, pt)
    shutil.copyfile(SHIPPED_WEIGHTS.with_suffix(".json"), card)
    assert load_weights(pt)[1] == load_weights(SHIPPED_WEIGHTS)[1]
    data = bytearray(pt.read_bytes())
    data[len(data) // 2: len(data) // 2 + 64] = np.random.default_rng(0).integers(0, 256, 64, np.uint8).tobytes()
    pt.write_bytes(bytes(data))
    with pytest.raises(RuntimeError, match=r"refiner\.pt are not the ones their card refiner\.json records"):
        load_weights(pt)
    card.unlink()  # a checkpoint without a card (a trained one) is taken as it is
    load_weights(pt)


def test_bfloat16_refiner_stays_within_rounding_of_float32():
    """The bfloat16 network (``render.refiner_precision``) keeps float32 weights' answer up to
    rounding: the same mask but for a few edge pixels, normals a fraction of a degree apart, and
    float32 maps out. A wrong cast (weights left in float32, input in bfloat16, or the output left
    in bfloat16) fails or drifts by degrees."""
    from pipeline.methods import refine
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner

    refiner, ch, cam = _refine_view()
    out = {p: refine(load_refiner(SHIPPED_WEIGHTS, precision=p), ch, 0.5, cam.focal_px, VIEW_RADIUS)
           for p in ("float32", "bfloat16")}
    assert load_refiner(SHIPPED_WEIGHTS, precision="bfloat16").net.head.weight.dtype == torch.bfloat16
    (n32, m32, z32), (n16, m16, z16) = out["float32"], out["bfloat16"]
    assert n16.dtype == np.float32 and m32.sum() > 500
    assert (m32 != m16).mean() < 0.002
    both = m32 & m16
    angle = np.degrees(np.arccos(np.clip(np.sum(n32[both] * n16[both], -1), -1, 1)))
    assert np.median(angle) < 0.3 and angle.mean() < 0.6, (np.median(angle), angle.mean())
    assert angle.max() > 0, "bfloat16 must actually round"
    np.testing.assert_array_equal(z16[both], z32[both])


def test_the_coarse_upsampling_is_the_upsampled_convolution():
    """``NearestUpConv`` computes nearest 2x upsampling, a 3x3 convolution and its activation from
    the coarse image: the same numbers to float rounding for any weights and size, borders
    included, and the refiner's decoder has no upsampling left."""
    from torch import nn

    from pipeline.model.inference import NearestUpConv

    torch.manual_seed(3)
    conv, act = nn.Conv2d(6, 5, 3, 1, 1), nn.LeakyReLU(0.2)
    x = torch.randn(2, 6, 7, 10)
    want = act(conv(nn.functional.interpolate(x, scale_factor=2, mode="nearest")))
    with torch.no_grad():
        for layout in (torch.contiguous_format, torch.channels_last):
            got = NearestUpConv(conv, act)(x.contiguous(memory_format=layout))
            assert got.shape == want.shape and got.is_contiguous(memory_format=layout)
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    refiner = Refiner(_trained_looking_generator())
    assert not any(isinstance(m, nn.Upsample) for m in refiner.net.modules())
    assert sum(isinstance(m, NearestUpConv) for m in refiner.net.modules()) == 2
