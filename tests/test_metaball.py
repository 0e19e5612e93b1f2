"""Metaballs (Horvath 2019): the ray-marched targets against closed forms of the field, the circle
input's outlines and depth test, the encodings, and the pix2pix networks' shapes, sizes and losses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.camera import Camera, look_at
from pipeline.exr import read_exr, write_exr
from pipeline.metaball import (
    MetaballParams,
    circle_input,
    decode_gbuffers,
    encode_targets,
    metaball_targets,
    minimal_radius,
    paper_camera,
    view_channels,
)
from pipeline.metaball.networks import (
    PAPER_DISCRIMINATOR,
    PAPER_GENERATOR,
    PatchDiscriminator,
    UNetGenerator,
    count_parameters,
    discriminator_loss,
    generator_loss,
    patch_map_size,
)

F32 = float(np.finfo(np.float32).eps)


def _world_rays(camera: Camera) -> np.ndarray:
    """World ray per pixel (H x W x 3) scaled so that the view depth is the ray parameter."""
    return camera.pixel_rays().astype(np.float64) @ camera.cam_to_world[:3, :3].T


def _depth_tolerance(p: MetaballParams, depth: np.ndarray) -> np.ndarray:
    """The crossing is placed mid-bracket after the bisections (half the final bracket), plus float32
    rounding of the sample positions and field sums (a few ulps of the depth)."""
    return p.step / 2 ** (p.bisections + 1) + 8 * F32 * depth


def _reference_field(x: np.ndarray, centres: np.ndarray, radii: np.ndarray, k: float) -> tuple[np.ndarray, ...]:
    """Float64 (f, grad f, per-ball weights) of the tapered field at points x (... x 3): r^2 / d^2 times
    s(u) = 1 - u^2 (3 - 2u) for u = (d - R / 2) / (R / 2) between R / 2 and R = k r (no taper at k = 0)."""
    v = x[..., None, :] - centres  # ... x N x 3, X - P
    d = np.linalg.norm(v, axis=-1)
    w = radii**2 / d**2
    s, ds = np.ones_like(d), np.zeros_like(d)
    if k > 0:
        half = 0.5 * k * radii
        u = np.clip((d - half) / half, 0.0, 1.0)
        s = 1.0 - u * u * (3.0 - 2.0 * u)
        ds = -6.0 * u * (1.0 - u) / half
    weights = w * s
    grad = (v * (w * (ds - 2.0 * s / d) / d)[..., None]).sum(-2)
    return weights.sum(-1), grad, weights


# ---- targets: the ray marcher -----------------------------------------------------------------


@pytest.mark.parametrize("iso, k", [(1.0, 4.0), (2.0, 4.0), (1.0, 0.0)])
def test_one_ball_is_the_sphere_of_radius_r_over_sqrt_iso(launch, iso, k):
    p = MetaballParams(iso_level=iso, kernel_radius_radii=k)
    centre, r = np.array([0.4, -0.2, 0.3]), 1.3
    cam = Camera(look_at((3.0, 2.5, 14.0), centre), 18.0, 72, 56)
    out = metaball_targets(centre[None], r, cam, p, launch, colours=np.array([[0.2, 0.6, 0.9]]))

    rho = r / math.sqrt(iso)
    rays = _world_rays(cam)
    o = cam.eye - centre
    a, b = (rays * rays).sum(-1), rays @ o
    disc = b * b - a * (o @ o - rho * rho)
    hit = disc > 0
    t = (-b - np.sqrt(np.where(hit, disc, 0.0))) / a
    chord = 2.0 * np.sqrt(np.where(hit, disc, 0.0)) / a  # in view depth, the march's unit
    mask = out["mask"] > 0
    # a chord longer than a step holds a sample; shorter (grazing) ones may be stepped over
    assert mask[hit & (chord > 1.5 * p.step)].all()
    assert not mask[~hit].any()
    assert hit[mask].all() and mask.sum() > 0.95 * hit.sum() > 300

    err = np.abs(out["depth"] - t)[mask]
    assert (err <= _depth_tolerance(p, t[mask])).all(), err.max()
    # the normal at a point displaced by e along the ray turns by at most e |ray| / rho
    x = cam.eye + rays * t[..., None]
    n_ref = ((x - centre) / rho) @ cam.view[:3, :3].T
    bound = _depth_tolerance(p, t) * np.linalg.norm(rays, axis=-1) / rho + 1e-5
    assert (np.linalg.norm(out["normals"] - n_ref, axis=-1)[mask] <= bound[mask]).all()
    assert np.allclose(np.linalg.norm(out["normals"][mask], axis=-1), 1.0, atol=1e-5)
    assert (out["normals"][mask][:, 2] > 0).all(), "normals face the camera"
    assert np.allclose(out["colour"][mask], [0.2, 0.6, 0.9], atol=1e-6)
    assert not out["depth"][~mask].any() and not out["normals"][~mask].any() and not out["colour"][~mask].any()


@pytest.mark.parametrize("iso, k", [(1.0, 4.0), (2.0, 0.0)])
def test_one_ellipsoidal_ball_is_its_ellipsoid_scaled_by_one_over_sqrt_iso(launch, iso, k):
    """A ball with a shape map A (the anisotropic metaballs' term 1 / |A (X - P)|^2) is the ellipsoid
    |A (X - P)| = 1 / sqrt(iso): depth and normal A^T A (X - P) as the closed form gives them; and
    A = I / r is the sphere of radius r to float rounding."""
    p = MetaballParams(iso_level=iso, kernel_radius_radii=k)
    centre = np.array([0.4, -0.2, 0.3])
    turn = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))[0]
    semi = np.array([1.6, 0.5, 1.0])
    a = np.diag(1.0 / semi) @ turn.T  # maps the ellipsoid of those semi-axes along turn's columns onto the unit ball
    cam = Camera(look_at((3.0, 2.5, 14.0), centre), 18.0, 72, 56)
    out = metaball_targets(centre[None], semi.max(), cam, p, launch, shapes=a[None])

    rays = _world_rays(cam)
    o, d = a @ (cam.eye - centre), rays @ a.T
    qa, qb = (d * d).sum(-1), d @ o
    disc = qb * qb - qa * (o @ o - 1.0 / iso)
    hit = disc > 0
    t = (-qb - np.sqrt(np.where(hit, disc, 0.0))) / qa
    mask = out["mask"] > 0
    assert hit[mask].all() and mask.sum() > 0.95 * hit.sum() > 200
    assert (np.abs(out["depth"] - t)[mask] <= 4 * _depth_tolerance(p, t[mask])).all()
    x = cam.eye + rays * t[..., None]
    n = (x - centre) @ (a.T @ a).T
    n_ref = (n / np.linalg.norm(n, axis=-1, keepdims=True)) @ cam.view[:3, :3].T
    assert np.degrees(np.arccos(np.clip((out["normals"] * n_ref).sum(-1)[mask], -1, 1))).max() < 0.05

    sphere = metaball_targets(centre[None], 1.3, cam, p, launch)
    shaped = metaball_targets(centre[None], 1.3, cam, p, launch, shapes=(np.eye(3) / 1.3)[None])
    assert (sphere["mask"] == shaped["mask"]).all() and sphere["mask"].sum() > 300
    np.testing.assert_allclose(shaped["depth"], sphere["depth"], atol=1e-4)
    np.testing.assert_allclose(shaped["normals"], sphere["normals"], atol=1e-4)


@pytest.mark.parametrize("k", [4.0, 0.0])
def test_two_balls_merge_where_the_summed_field_reaches_the_iso_level(launch, k):
    p = MetaballParams(kernel_radius_radii=k)
    r, s, z = 1.0, 2.5, -12.0
    centres = np.array([[-s / 2, 0.0, z], [s / 2, 0.0, z]])
    radii = np.array([r, r])
    colours = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    cam = paper_camera(63, 47)  # odd sizes: the middle pixel's ray is the optical axis
    out = metaball_targets(centres, radii, cam, p, launch, colours)

    # on the axis, in the plane between the balls: f = 2 r^2 / (s^2 / 4 + y^2) = iso
    y = math.sqrt(2 * r * r / p.iso_level - s * s / 4)
    assert abs(out["depth"][23, 31] - (-z - y)) <= _depth_tolerance(p, -z)
    assert np.allclose(out["normals"][23, 31], [0.0, 0.0, 1.0], atol=1e-5)
    assert np.allclose(out["colour"][23, 31], [0.5, 0.0, 0.5], atol=1e-5)

    # every hit lies on f = iso, with -grad f as its normal and the weighted blend as its colour
    rays = _world_rays(cam)
    mask = out["mask"] > 0
    x = cam.eye + rays[mask] * out["depth"][mask, None].astype(np.float64)
    f, grad, weights = _reference_field(x, centres, radii, k)
    slope = np.abs((grad * rays[mask]).sum(-1))  # df/dt along the ray
    assert (np.abs(f - p.iso_level) <= slope * _depth_tolerance(p, out["depth"][mask]) + 1e-5).all()
    n_ref = -grad / np.linalg.norm(grad, axis=-1, keepdims=True)
    assert np.abs(out["normals"][mask] - n_ref @ cam.view[:3, :3].T).max() < 1e-3
    assert np.abs(out["colour"][mask] - weights @ colours / weights.sum(-1, keepdims=True)).max() < 1e-4

    # silhouette and first crossing against a dense float64 sampling of each ray (step 0.002)
    ts = np.arange(p.depth_near, 16.0, 0.002)
    f_rays = np.stack([_reference_field(cam.eye + rays * t, centres, radii, k)[0] for t in ts])
    peak = f_rays.max(0)
    assert mask[peak > 1.05 * p.iso_level].all() and not mask[peak < 0.95 * p.iso_level].any()
    first = ts[np.argmax(f_rays >= p.iso_level, axis=0)]
    assert (np.abs(out["depth"] - first)[mask] <= 0.002 + 1e-4).all()


def test_two_balls_on_the_line_of_sight_meet_the_ray_at_the_root_of_the_summed_field(launch):
    p = MetaballParams(kernel_radius_radii=0.0)
    r, s, z = 1.0, 2.5, -12.0
    cam = paper_camera(31, 31)
    out = metaball_targets(np.array([[0.0, 0.0, z], [0.0, 0.0, z - s]]), r, cam, p, launch)
    # in front of the near ball at distance x: r^2 / x^2 + r^2 / (x + s)^2 = iso, a quartic in x:
    # iso x^2 (x + s)^2 - r^2 ((x + s)^2 + x^2) = 0
    iso = p.iso_level
    quartic = np.polysub(iso * np.polymul([1, 0, 0], np.polymul([1, s], [1, s])),
                         r * r * np.polyadd(np.polymul([1, s], [1, s]), [1, 0, 0]))
    roots = np.roots(quartic)
    x = max(q.real for q in roots if abs(q.imag) < 1e-9 and q.real > 0)
    assert abs(out["depth"][15, 15] - (-z - x)) <= _depth_tolerance(p, -z)
    assert np.allclose(out["normals"][15, 15], [0.0, 0.0, 1.0], atol=1e-5)


def test_field_normals_sum_the_wide_balls_from_their_own_grid(launch):
    """The field's normals at given ray depths are the brute-force sum's over every ball, also near
    the few balls wider than the 99th percentile, which come from a grid of their own."""
    import warp as wp

    from pipeline.metaball import field_normals

    rng = np.random.default_rng(3)
    n, k = 400, 4.0
    centres = np.column_stack([rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(-3.2, -2.8, n)])
    radii = np.full(n, 0.05)
    radii[:3] = 0.15  # 0.75% of the balls, three times as wide
    cam = Camera(np.eye(4), 20.0, 64, 64)
    t = 3.0
    t_front = wp.full(64 * 64, t, dtype=float, device="cpu")
    normals = wp.zeros(64 * 64, dtype=wp.vec3, device="cpu")
    field_normals(centres, radii, cam, MetaballParams(kernel_radius_radii=k), launch, t_front, 0, normals)
    got = normals.numpy().reshape(64, 64, 3)
    x = cam.pixel_rays().astype(np.float64) * t
    grad = _reference_field(x, centres, radii, k)[1]
    narrow_only = _reference_field(x, centres[3:], radii[3:], k)[1]
    some = np.linalg.norm(grad, axis=-1) > 1e-6
    want = -grad / np.maximum(np.linalg.norm(grad, axis=-1, keepdims=True), 1e-30)
    without = -narrow_only / np.maximum(np.linalg.norm(narrow_only, axis=-1, keepdims=True), 1e-30)
    error = np.degrees(np.arccos(np.clip((got * want).sum(-1), -1.0, 1.0)))[some]
    assert some.mean() > 0.8 and error.max() < 0.05, error.max()
    assert np.degrees(np.arccos(np.clip((without * want).sum(-1), -1.0, 1.0)))[some].max() > 5.0


def test_balls_outside_the_depth_range_or_behind_the_camera_leave_the_image_empty(launch):
    p = MetaballParams()
    cam = paper_camera(24, 24)
    for centres in (np.zeros((0, 3)), np.array([[0.0, 0.0, 5.0]]), np.array([[0.0, 0.0, -30.0]])):
        out = metaball_targets(centres, 1.0, cam, p, launch)
        assert not any(a.any() for a in out.values())
        assert out["normals"].shape == (24, 24, 3) and out["depth"].shape == (24, 24)


def test_a_camera_inside_a_support_marches_from_the_near_plane(launch):
    cam = paper_camera(48, 48)
    centre = np.array([[0.3, 0.0, -9.0]])
    wide = metaball_targets(centre, 1.5, cam, MetaballParams(kernel_radius_radii=8.0), launch)
    narrow = metaball_targets(centre, 1.5, cam, MetaballParams(), launch)
    assert wide["mask"].sum() > 100 and np.array_equal(wide["mask"], narrow["mask"])
    assert np.abs(wide["depth"] - narrow["depth"]).max() <= 2 * _depth_tolerance(MetaballParams(), 9.0)


@pytest.mark.parametrize("k", [4.0, 0.0])
def test_empty_space_skipping_finds_the_surfaces_of_the_fixed_step(launch, k):
    """Sixty random balls: the adaptive march (safe steps where the field provably stays below the
    iso-level) meets the same surface as the thesis' fixed step, pixel for pixel but for rays that
    graze it, at the same depth, with the same normals, in far fewer samples."""
    import time

    rng = np.random.default_rng(4)
    centres = np.column_stack([rng.uniform(-4, 4, 60), rng.uniform(-4, 4, 60), rng.uniform(-20, -9, 60)])
    radii = rng.uniform(0.3, 0.9, 60)
    cam = paper_camera(64, 64)
    out, seconds = {}, {}
    for adaptive in (False, True):
        p = MetaballParams(kernel_radius_radii=k, adaptive_step=adaptive)
        metaball_targets(centres, radii, cam, p, launch)  # compiled and warm
        start = time.perf_counter()
        out[adaptive] = metaball_targets(centres, radii, cam, p, launch)
        seconds[adaptive] = time.perf_counter() - start
    fixed, fast = out[False], out[True]
    both = (fixed["mask"] > 0) & (fast["mask"] > 0)
    assert fixed["mask"].mean() > 0.2
    assert np.mean(fixed["mask"] != fast["mask"]) < 0.005
    tol = _depth_tolerance(MetaballParams(), fixed["depth"][both])
    assert np.all(np.abs(fixed["depth"][both] - fast["depth"][both]) <= 2 * tol + 1e-6)
    cos = (fixed["normals"][both] * fast["normals"][both]).sum(-1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    assert seconds[True] < seconds[False]


def test_parameters_out_of_range_are_named():
    with pytest.raises(ValueError, match="depth_near"):
        MetaballParams(depth_near=30.0)
    with pytest.raises(ValueError, match="kernel_radius_radii=1.5 tapers"):
        MetaballParams(kernel_radius_radii=1.5)


# ---- the circle input -------------------------------------------------------------------------


def _ring(cam: Camera, centre: np.ndarray, radius: float, p: MetaballParams) -> tuple[np.ndarray, np.ndarray, float]:
    """(pixels strictly inside the outline, pixels within 1e-3 px of its edges, centre depth) in float64."""
    col, row, d = cam.project(cam.to_view(centre[None]))
    outer = cam.focal_px * minimal_radius(radius, p.iso_level) / d[0]
    inner = max(outer - max(2 * p.outline_width * outer, p.outline_min_px), 0.0)
    jj, ii = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
    rho = np.hypot(ii - col[0], jj - row[0])
    edge = (np.abs(rho - outer) < 1e-3) | (np.abs(rho - inner) < 1e-3)
    return (rho > inner) & (rho < outer), edge, float(d[0])


def test_a_ball_is_an_outline_at_its_projected_minimal_radius_with_its_centre_depth(launch):
    p = MetaballParams(iso_level=1.5, outline_min_px=0.0)
    cam = Camera(look_at((1.0, 2.0, 15.0), (0.0, 0.0, 0.0)), 25.0, 96, 80)
    centre, colour = np.array([0.3, -0.4, 0.2]), np.array([[0.9, 0.5, 0.1]])
    image = circle_input(centre[None], 2.0, cam, p, launch, colour)
    ring, edge, d = _ring(cam, centre, 2.0, p)
    assert image.shape == (4, 80, 96) and image.dtype == np.float32
    drawn = image[3] > 0
    assert np.array_equal(drawn & ~edge, ring & ~edge) and ring.sum() > 100
    assert np.allclose(image[:3, drawn].T, colour, atol=0)
    assert np.allclose(image[3, drawn], (d - p.depth_near) / (p.depth_far - p.depth_near), atol=1e-6)
    assert not image[:, ~drawn].any(), "the background and the disc inside the outline stay empty"


def test_a_hidden_ball_still_shows_its_outline_and_the_nearest_wins_where_they_cross(launch):
    p = MetaballParams(outline_min_px=0.0)
    cam = paper_camera(160, 160)
    # A near ball whose disc would cover a far one entirely (same axis, larger projected radius),
    # and a third ball at the far one's depth whose outline crosses A's
    centres = np.array([[0.0, 0.0, -20.0], [0.0, 0.0, -10.0], [2.0, 0.0, -10.5]])
    radii = np.array([2.0, 1.5, 1.0])
    colours = np.eye(3)
    image = circle_input(centres, radii, cam, p, launch, colours)
    rings = [_ring(cam, centres[k], radii[k], p) for k in range(3)]
    far, far_edge, far_d = rings[0]
    visible = far & ~far_edge & ~(rings[1][0] | rings[2][0])
    assert visible.sum() > 0.8 * far.sum() > 40
    assert np.allclose(image[:3, visible].T, colours[0])
    assert np.allclose(image[3, visible], (far_d - p.depth_near) / (p.depth_far - p.depth_near), atol=1e-6)
    crossing = rings[1][0] & rings[2][0] & ~rings[1][1] & ~rings[2][1]
    assert crossing.sum() > 0
    assert np.allclose(image[:3, crossing].T, colours[1]), "the nearer centre wins the depth test"


def test_at_equal_depth_the_first_ball_drawn_wins_and_depth_codes_clamp(launch):
    p = MetaballParams(outline_min_px=0.0)
    cam = paper_camera(64, 64)
    centres = np.array([[0.0, 0.0, -30.0], [0.0, 0.0, -30.0]])
    image = circle_input(centres, 6.0, cam, p, launch, np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    drawn = image[3] > 0
    assert drawn.sum() > 20 and np.allclose(image[:3, drawn].T, [0.0, 1.0, 0.0])
    assert np.all(image[3, drawn] == 1.0), "beyond depth_far the code clamps to 1"


def test_thin_outlines_keep_a_pixel_of_width(launch):
    cam = paper_camera(64, 64)
    centre = np.array([[0.0, 0.0, -20.0]])
    thin = circle_input(centre, 0.6, cam, MetaballParams(outline_min_px=0.0), launch)[3] > 0
    kept = circle_input(centre, 0.6, cam, MetaballParams(), launch)[3] > 0
    assert (thin <= kept).all() and kept.sum() > thin.sum()


# ---- encodings --------------------------------------------------------------------------------


def test_the_encoded_buffers_decode_back_and_write_as_exr(launch, tmp_path):
    p = MetaballParams()
    cam = paper_camera(40, 32)
    centres = np.array([[-0.8, 0.2, -11.0], [0.9, -0.1, -12.5]])
    colours = np.array([[0.8, 0.3, 0.1], [0.1, 0.4, 0.9]])
    targets = metaball_targets(centres, 0.9, cam, p, launch, colours)
    encoded = encode_targets(targets, p)
    assert encoded.shape == (7, 32, 40) and encoded.min() >= 0.0 and encoded.max() <= 1.0
    empty = targets["mask"] == 0
    assert empty.any() and (encoded[3, empty] == 1.0).all() and not encoded[4:, empty].any()
    back = decode_gbuffers(encoded, p)
    assert np.array_equal(back["mask"], targets["mask"])
    for name in ("depth", "normals", "colour"):
        assert np.abs(back[name] - targets[name]).max() < 1e-5, name

    circles = circle_input(centres, 0.9, cam, p, launch, colours)
    channels = view_channels(targets, circles)
    write_exr(tmp_path / "view.exr", channels)
    read = read_exr(tmp_path / "view.exr")
    assert sorted(read) == sorted(channels)
    assert np.array_equal(read["metaball.Z"], targets["depth"]) and np.array_equal(read["circles.Z"], circles[3])


# ---- networks ---------------------------------------------------------------------------------


@pytest.mark.parametrize("upsample", ["transpose", "resize"])
@pytest.mark.parametrize("size", [256, 512])
def test_generator_maps_4_to_7_channels_at_the_input_size(size, upsample):
    g = UNetGenerator(base_channels=2, upsample=upsample).eval()
    with torch.no_grad():
        assert g(torch.zeros(1, 4, size, size)).shape == (1, 7, size, size)
    with pytest.raises(ValueError, match="multiple"):
        g(torch.zeros(1, 4, size + 8, size))


@pytest.mark.parametrize("size, side", [(512, 50), (256, 18)])
def test_discriminator_patch_map_is_50x50_at_512(size, side):
    d = PatchDiscriminator(base_channels=2).eval()
    with torch.no_grad():
        out = d(torch.zeros(2, 4, size, size), torch.zeros(2, 7, size, size))
    assert out.shape == (2, 1, side, side) and patch_map_size(size) == side


def test_paper_sizes_and_the_default_generator_fits_the_weight_limit():
    g, d = UNetGenerator(**PAPER_GENERATOR), PatchDiscriminator(**PAPER_DISCRIMINATOR)
    # the thesis' 24,706,760 counts a batch norm (scale and shift of 256 channels) on the innermost encoder
    assert count_parameters(g) + count_parameters(d) == 24_706_760 - 2 * 256
    assert count_parameters(g) == 13_615_623
    small = count_parameters(UNetGenerator())
    assert small == 3_408_135 and 4 * small < 20 * 2**20


def test_losses_use_the_stated_weights():
    half = torch.full((1, 1, 4, 4), 0.5)
    assert discriminator_loss(torch.ones(1, 1, 4, 4), torch.zeros(1, 1, 4, 4)).item() < 1e-9
    assert discriminator_loss(half, half).item() == pytest.approx(2 * math.log(2), rel=1e-6)
    total, gan, l1 = generator_loss(half, torch.zeros(1, 7, 8, 8), torch.full((1, 7, 8, 8), 0.25))
    assert gan.item() == pytest.approx(math.log(2), rel=1e-6) and l1.item() == pytest.approx(0.25)
    assert total.item() == pytest.approx(500 * math.log(2) + 0.5 * 0.25, rel=1e-6)


def test_one_training_step_on_a_rendered_pair(launch):
    """pix2pix smoke test: a circle image and its targets at 256 x 256, two rounds of a discriminator
    and a generator Adam step (lr 0.0002, beta1 0.5). With pix2pix's weights (GAN 1, L1 100) the L1
    term leads, so the generator's L1 to the target must drop; under the thesis' 500 and 0.5 the
    adversarial term leads and two steps promise nothing about L1."""
    torch.manual_seed(0)
    p = MetaballParams(step=0.05, bisections=4)
    cam = paper_camera(256, 256)
    rng = np.random.default_rng(1)
    centres = np.column_stack([rng.uniform(-3, 3, 6), rng.uniform(-3, 3, 6), rng.uniform(-16, -12, 6)])
    colours = rng.uniform(0, 1, (6, 3))
    x = torch.from_numpy(circle_input(centres, 0.8, cam, p, launch, colours))[None] * 2 - 1
    y = torch.from_numpy(encode_targets(metaball_targets(centres, 0.8, cam, p, launch, colours), p))[None] * 2 - 1
    g, d = UNetGenerator(base_channels=4), PatchDiscriminator(base_channels=4)
    opt_g = torch.optim.Adam(g.parameters(), 2e-4, betas=(0.5, 0.999))
    opt_d = torch.optim.Adam(d.parameters(), 2e-4, betas=(0.5, 0.999))
    l1_before = None
    for _ in range(2):
        out = g(x)
        loss_d = discriminator_loss(d(x, y), d(x, out.detach()))
        opt_d.zero_grad()
        loss_d.backward()
        opt_d.step()
        total, _, l1 = generator_loss(d(x, out), out, y, gan_weight=1.0, l1_weight=100.0)
        opt_g.zero_grad()
        total.backward()
        opt_g.step()
        l1_before = l1_before if l1_before is not None else l1.item()
    assert torch.isfinite(total) and torch.isfinite(loss_d)
    assert l1.item() < l1_before
