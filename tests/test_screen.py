"""Screen-space inputs: exact sphere splats, step edges under each filter, planes stay planar."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.camera import Camera, look_at
from pipeline.config import DatasetConfig
from pipeline.screen import ScreenSpace

R = 0.0125


def _camera(size=128, fov=40.0) -> Camera:
    return Camera(look_at((0, 0, 0), (0, 0, -1)), fov, size, size)


def test_single_particle_depth_is_the_analytic_sphere(ss):
    cam = _camera(96, 30.0)
    centre = np.array([0.013, -0.007, -0.45])
    out = ss.splat(centre[None].astype(np.float32), 0.03, cam)
    rays = cam.pixel_rays().astype(np.float64)
    a = (rays**2).sum(-1)
    b = rays @ centre
    disc = b * b - a * (centre @ centre - 0.03**2)
    hit = disc > 0
    t0 = (b - np.sqrt(np.where(hit, disc, 0))) / a
    covered = out.mask > 0
    assert covered.sum() > 100
    np.testing.assert_array_equal(covered, hit)
    # float32 arithmetic: micrometres, where a pixel here spans 2.5 mm
    np.testing.assert_allclose(out.depth[covered], t0[covered], atol=1e-5)
    chord = 2 * np.sqrt(np.where(hit, disc, 0)) / np.sqrt(a)
    np.testing.assert_allclose(out.thickness[covered], chord[covered], atol=1e-5)
    assert np.all(out.depth[~covered] == 0)


def _sheet(z: float, x_range, size: float = 0.4, spacing: float = R) -> np.ndarray:
    xs = np.arange(x_range[0], x_range[1], spacing)
    ys = np.arange(-size, size, spacing)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)


@pytest.mark.parametrize("mode", ["fast", "exact"])
def test_step_edge_bilateral_smears_narrow_range_keeps(ss, mode):
    """A near layer over the left half, a far layer 12 r behind it everywhere.

    Thresholds: on the far layer's pixels within 6 px of the step, the narrow-range filter moves
    the depth by less than 0.05 r on average (near samples in front by more than delta = 10.5 r
    get no weight), the bilateral filter pulls them forward by more than 0.3 r, the naive
    Gaussian by more than 2 r."""
    cam = _camera(128, 40.0)
    step = 12 * R
    near = _sheet(-1.0, (-0.5, 0.0))
    far = _sheet(-1.0 - step, (-0.5, 0.5))
    sp = ss.splat(np.concatenate([near, far]).astype(np.float32), R, cam)
    far_only = ss.splat(far.astype(np.float32), R, cam)
    p = DatasetConfig(filter_mode=mode)
    # reference: each filter applied to the far layer alone (what it would be without the step)
    filtered = {
        "bilateral": (ss.bilateral(sp.depth, cam, R, p), ss.bilateral(far_only.depth, cam, R, p)),
        "nrf": (ss.narrow_range(sp.depth, cam, R, p), ss.narrow_range(far_only.depth, cam, R, p)),
        "gaussian": (ss.gaussian(sp.depth, p.gaussian_sigma_px), ss.gaussian(far_only.depth, p.gaussian_sigma_px)),
    }
    is_far = sp.depth > 1.0 + 0.5 * step
    cols = np.where(is_far.any(0))[0]
    edge = cols.min()
    band = np.zeros_like(is_far)
    band[:, edge:edge + 6] = True
    band &= is_far
    band[:10] = band[-10:] = False
    assert band.sum() > 200
    shift = {k: float(np.mean(ref[band] - out[band])) / R for k, (out, ref) in filtered.items()}
    assert abs(shift["nrf"]) < 0.05, shift
    assert shift["bilateral"] > 0.3, shift
    assert shift["gaussian"] > 2.0, shift


@pytest.mark.parametrize("mode", ["fast", "exact"])
def test_tilted_plane_stays_planar_under_narrow_range(ss, mode):
    """A densely sampled plane seen at 60 degrees: the depth slope per pixel is about r, so a
    fixed range of delta = 10.5 r would cut it within a dozen pixels; the dynamic range follows
    it. Away from the silhouette (where empty pixels are clamped behind on purpose) the filtered
    surface is a plane to 0.05 r RMS, with its normal within 0.5 degrees of the true one."""
    from scipy.ndimage import binary_erosion

    cam = _camera(128, 40.0)
    angle = np.radians(60.0)
    u = np.array([1.0, 0.0, 0.0])
    v = np.array([0.0, np.cos(angle), np.sin(angle)])
    n = np.cross(u, v)
    s = np.arange(-0.8, 0.8, R)
    a, b = np.meshgrid(s, s)
    pts = np.array([0, 0, -1.0]) + a.ravel()[:, None] * u + b.ravel()[:, None] * v
    sp = ss.splat(pts.astype(np.float32), R, cam)
    # few taps, so that the fast passes really skip pixels (a radius of 9 px, every 3rd read)
    out = ss.narrow_range(sp.depth, cam, R, DatasetConfig(filter_mode=mode, nrf_max_taps=3))
    inner = binary_erosion(sp.mask > 0, iterations=12, border_value=0)
    assert inner.sum() > 5000
    pos = cam.unproject(out)[inner]
    centre = pos.mean(0)
    fitted = np.linalg.svd(pos - centre, full_matrices=False)[2][-1]
    assert np.degrees(np.arccos(abs(fitted @ n))) < 0.5
    assert ((pos - centre) @ fitted).std() < 0.05 * R
    normals = ss.normals(out, cam)[inner]
    assert np.degrees(np.arccos(np.clip(np.abs(normals @ n), 0, 1))).mean() < 2.0


@pytest.mark.parametrize("mode", ["fast", "exact"])
def test_filters_leave_background_empty(ss, mode):
    cam = _camera(64)
    sp = ss.splat(np.zeros((0, 3), np.float32), R, cam)
    p = DatasetConfig(filter_mode=mode)
    for d in (ss.bilateral(sp.depth, cam, R, p), ss.narrow_range(sp.depth, cam, R, p), ss.gaussian(sp.depth, 2.0)):
        assert not d.any()
    assert not ss.normals(sp.depth, cam).any()


def _bumpy_sheet_depth(ss, size=160):
    """Sphere splats of a jittered sheet, close enough that a particle spans several pixels."""
    cam = _camera(size, 40.0)
    pts = _sheet(-0.6, (-0.3, 0.3), size=0.3)
    pts += np.random.default_rng(0).normal(scale=0.2 * R, size=pts.shape)
    return cam, ss.splat(pts.astype(np.float32), R, cam)


def test_fast_narrow_range_with_enough_taps_is_the_exact_filter(ss):
    """With at least as many taps as the widest radius the stride is 1 and 'fast' reads every pixel:
    bit-identical to 'exact'. With few taps it differs (so the stride is really applied) but stays
    within a small fraction of a radius."""
    cam, sp = _bumpy_sheet_depth(ss)
    exact = ss.narrow_range(sp.depth, cam, R, DatasetConfig(filter_mode="exact"))
    wide = ss.narrow_range(sp.depth, cam, R, DatasetConfig(filter_mode="fast", nrf_max_taps=100))
    np.testing.assert_array_equal(wide, exact)
    strided = ss.narrow_range(sp.depth, cam, R, DatasetConfig(filter_mode="fast", nrf_max_taps=4))
    fluid = sp.mask > 0
    assert np.abs(strided - exact)[fluid].max() > 1e-6
    assert np.abs(strided - exact)[fluid].mean() < 0.05 * R


def test_wide_bilateral_taps_average_their_stretch_and_follow_the_full_filter(ss):
    """Past ``bilateral_max_taps`` a pass's taps stand for stretches of pixels: the depth moves
    (so the stride is applied) but its normals stay within a degree of reading every pixel, where
    the unfiltered splat is 18 degrees away; with taps enough for the radius it is the full filter."""
    from scipy.ndimage import binary_erosion

    from pipeline.metrics import angular_errors

    cam, sp = _bumpy_sheet_depth(ss)  # projected radius 4.6 px: a kernel radius of 14 px
    inner = binary_erosion(sp.mask > 0, iterations=8, border_value=0)
    full = ss.bilateral(sp.depth, cam, R, DatasetConfig(bilateral_max_taps=0))
    np.testing.assert_array_equal(ss.bilateral(sp.depth, cam, R, DatasetConfig(bilateral_max_taps=16)), full)
    strided = ss.bilateral(sp.depth, cam, R, DatasetConfig(bilateral_max_taps=4))
    assert np.abs(strided - full)[inner].max() > 1e-3 * R
    reference = ss.normals(full, cam)
    assert angular_errors(ss.normals(strided, cam), reference, inner).mean() < 1.0
    assert angular_errors(ss.normals(sp.depth, cam), reference, inner).mean() > 10.0


def test_bilateral_line_sums_only_where_a_line_has_wide_taps(ss):
    """The stretches' running sums are made only on lines whose nearest pixel's kernel is wider than
    ``bilateral_max_taps``: a sheet near in its top left quarter and four times as far elsewhere
    (particles of 4.6 and 1.2 px) filters alike with every sum poisoned beforehand (no skipped line
    is read), and the far quarter's lines, rows and columns alike, stay unmade."""
    import warp as wp

    cam, sp = _bumpy_sheet_depth(ss)
    h, w = sp.depth.shape
    depth = sp.depth.copy()
    depth[h // 2:] *= 4.0
    depth[: h // 2, w // 2:] *= 4.0
    p = DatasetConfig(bilateral_max_taps=6)
    fresh = ss.bilateral(depth, cam, R, p)
    sums = ss._buffer("line_sums", 3 * depth.size, wp.float64)
    sums.numpy()[:] = np.nan
    again = ss.bilateral(depth, cam, R, p)
    np.testing.assert_array_equal(again, fresh)
    assert np.isfinite(again).all()
    made = np.isfinite(sums.numpy().reshape(3, -1)).all(axis=0).reshape(depth.shape)
    assert made[: h // 2].all() and made[:, : w // 2].all() and not made[h // 2:, w // 2:].any()
    full = ss.bilateral(depth, cam, R, DatasetConfig(bilateral_max_taps=0))
    assert np.abs(again - full)[: h // 4, : w // 4].max() > 1e-3 * R  # the near quarter's stretches apply


@pytest.mark.parametrize("taps, near", [(0, 1.0), (4, 1.0), (16, 1.0), (20, 0.4)])
def test_the_cpus_vectorised_bilateral_is_the_warp_pass_to_rounding(ss, taps, near, monkeypatch):
    """On the CPU the bilateral's passes run sixteen pixels a vector with an ``exp`` of their own
    (``pipeline.screen.native``): they must give the depths of the Warp kernel that CUDA runs, to
    float rounding. A sheet near in one quarter and four times as far elsewhere, 150 px (rows of
    blocks that end short): kernels of 14 px and of 4, taps every pixel, stretches of 4 pixels (a
    depth step in a stretch sends it pixel by pixel) or none wider than 16, and the image's edges;
    brought 2.5x nearer, kernels of 33-34 px in 17 stretches a side (past the 16 a block's flags hold
    before the stretches that straddle a step are summed). The running sums are the Warp
    kernel's bit for bit."""
    import warp as wp

    from pipeline.screen import filters as F
    from pipeline.screen import native as N

    cam, sp = _bumpy_sheet_depth(ss, size=150)
    h, w = sp.depth.shape
    depth = sp.depth * near
    depth[h // 2:] *= 4.0
    depth[: h // 2, w // 2:] *= 4.0
    p = DatasetConfig(bilateral_max_taps=taps)
    native = ss.bilateral(depth, cam, R, p)
    for axis in (0, 1):  # the stretches' running sums, bit for bit
        sizes = [wp.array(depth.ravel()), w, h, axis, cam.focal_px, R, p.bilateral_sigma_px_scale,
                 p.bilateral_max_radius_px, taps]
        made = [wp.array(np.full(3 * h * w, np.nan)) for _ in range(2)]
        ss.launch(N.line_prefix_blocks, N.lines(w, h, axis), [*sizes, made[0]])
        ss.launch(F.line_prefix, h if axis == 0 else w, [*sizes, made[1]])
        np.testing.assert_array_equal(made[0].numpy(), made[1].numpy())
        assert np.isfinite(made[0].numpy()).any() == (taps in (4, 20))
    monkeypatch.setattr(ss.launch, "cpu", False)  # the Warp kernels' way, on the same CPU
    scalar = ss.bilateral(depth, cam, R, p)
    np.testing.assert_array_equal(native > 0, depth > 0)
    np.testing.assert_array_equal(scalar > 0, depth > 0)
    np.testing.assert_allclose(native, scalar, rtol=2e-6)
    assert np.abs(native - depth).max() > 0.1 * R  # it filtered


def test_the_vectorised_exp_is_the_c_librarys_to_two_ulp():
    """``native``'s own ``exp`` (Cephes' polynomial, which the compiler can vectorise) against
    float64 over the filters' range of arguments, and its clamp far below it."""
    import warp as wp

    from pipeline.screen.native import fast_exp

    @wp.kernel
    def exps(x: wp.array(dtype=float), out: wp.array(dtype=float)):
        i = wp.tid()
        out[i] = fast_exp(x[i])

    x = np.concatenate([np.linspace(-87.0, 0.0, 200001), np.linspace(0.0, 10.0, 1001)]).astype(np.float32)
    out = wp.zeros(len(x), dtype=float)
    wp.launch(exps, len(x), [wp.array(x), out], device="cpu")
    want = np.exp(x.astype(np.float64))
    np.testing.assert_allclose(out.numpy(), want, rtol=2.5e-7)
    wp.launch(exps, 2, [wp.array(np.array([-200.0, -87.0], np.float32)), out], device="cpu")
    assert 0.0 < out.numpy()[0] == out.numpy()[1] < 1e-37


def test_separable_bilateral_is_the_2d_filter_without_range_weights(ss):
    """With an enormous range sigma the bilateral filter is a Gaussian of the fluid pixels; on a
    fully covered image away from the borders the separable passes equal the 2D window (a Gaussian
    is separable), to float rounding."""
    cam, sp = _bumpy_sheet_depth(ss)
    p = {"bilateral_range_radii": 1e6, "bilateral_max_radius_px": 6}
    sep = ss.bilateral(sp.depth, cam, R, DatasetConfig(filter_mode="fast", **p))
    full = ss.bilateral(sp.depth, cam, R, DatasetConfig(filter_mode="exact", **p))
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(sp.mask > 0, iterations=8, border_value=0)
    assert inner.sum() > 2000
    # the spatial sigma follows each pixel's own depth, which differs by a fraction of a percent
    # between the passes' centres: agreement to 1e-3 r, against bumps of about 0.3 r
    assert np.abs(sep - full)[inner].max() < 1e-3 * R
    assert np.abs(sp.depth - full)[inner].max() > 0.1 * R


def test_splat_is_the_same_on_one_thread_and_in_row_bands(ss):
    cam, sp = _bumpy_sheet_depth(ss)
    one = ScreenSpace("cpu", threads=1)
    try:
        single = one.splat(_sheet(-0.6, (-0.3, 0.3), size=0.3).astype(np.float32), R, cam)
    finally:
        one.close()
    banded = ss.splat(_sheet(-0.6, (-0.3, 0.3), size=0.3).astype(np.float32), R, cam)
    for a, b in ((single.depth, banded.depth), (single.thickness, banded.thickness), (single.mask, banded.mask)):
        np.testing.assert_array_equal(a, b)
    assert single.mask.mean() > 0.3


def _rotation(seed: int = 0) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_single_stretched_particle_splat_is_the_analytic_ellipsoid(ss):
    """Depth, coverage, chord thickness and normal of one rotated ellipsoid (semi-axes 50, 20 and
    8 mm) against the closed-form ray-quadric intersection."""
    from pipeline.ellipsoids import Ellipsoids

    cam = _camera(128, 30.0)
    q = _rotation(1)
    semi = np.array([0.05, 0.02, 0.008])
    m = q @ np.diag(1 / semi) @ q.T
    centre = np.array([0.01, -0.012, -0.5])
    ell = Ellipsoids(centre[None].astype(np.float32), m[None].astype(np.float32),
                     np.array([semi.max()], np.float32))
    out = ss.splat_ellipsoids(ell, cam)
    rays = cam.pixel_rays().astype(np.float64)
    rays = rays / -rays[..., 2:3]  # z = -1: the ray parameter is the view depth
    md, mc = rays @ m.T, m @ centre
    a, b, cc = (md * md).sum(-1), md @ mc, mc @ mc - 1
    disc = b * b - a * cc
    hit = disc > 0
    t0 = (b - np.sqrt(np.where(hit, disc, 0))) / a
    covered = out.mask > 0
    assert covered.sum() > 150
    # pixels whose ray grazes the rim may differ in float32; nowhere else
    assert (covered != hit).sum() <= 0.01 * hit.sum()
    both = covered & hit
    # float32: tens of micrometres at the rim (where the depth is steep in disc), where a pixel spans 2 mm
    np.testing.assert_allclose(out.depth[both], t0[both], atol=5e-5)
    inner = both & (disc > 0.05 * disc.max())
    np.testing.assert_allclose(out.depth[inner], t0[inner], atol=1e-5)
    chord = 2 * np.sqrt(np.where(hit, disc, 0)) / a * np.linalg.norm(rays, axis=-1)
    np.testing.assert_allclose(out.thickness[inner], chord[inner], atol=1e-4)
    x = rays * t0[..., None] - centre
    n = x @ (m @ m).T
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cos = (out.normals[inner] * n[inner]).sum(-1)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    assert (n[inner][:, 2] > 0).all(), "front-facing normals point at the camera"


def test_two_overlapping_ellipsoids_keep_the_nearer_surface_and_its_normal(ss):
    from pipeline.ellipsoids import Ellipsoids

    cam = _camera(96, 30.0)
    flat = np.diag([1 / 0.04, 1 / 0.04, 1 / 0.01])   # a disc facing the camera
    tall = np.diag([1 / 0.01, 1 / 0.05, 1 / 0.01])   # a needle across it, behind
    ell = Ellipsoids(np.array([[0, 0, -0.5], [0, 0, -0.53]], np.float32), np.stack([flat, tall]).astype(np.float32),
                     np.array([0.04, 0.05], np.float32))
    out = ss.splat_ellipsoids(ell, cam)
    centre = out.depth.shape[0] // 2
    assert abs(out.depth[centre, centre] - 0.49) < 1e-4, "the disc's front face, 1 cm before its centre"
    np.testing.assert_allclose(out.normals[centre, centre], [0, 0, 1], atol=0.05)
    # the needle shows above and below the disc, at its own depth
    row = centre - int(0.045 / 0.53 * cam.focal_px)
    assert out.mask[row, centre] == 1 and abs(out.depth[row, centre] - 0.52) < 0.01


def test_the_splat_draws_the_largest_density_along_each_ray(ss):
    """Ellipsoids carrying their density: each pixel gets the largest of those its ray meets (the
    disc's 0.5 alone, the needle's 3 where it shows and where it lies behind the disc), 0 where
    none; without densities ``inputs`` has no such map."""
    from pipeline.ellipsoids import DENSITY_CHANNEL, Ellipsoids

    cam = _camera(96, 30.0)
    flat = np.diag([1 / 0.04, 1 / 0.04, 1 / 0.01])
    tall = np.diag([1 / 0.01, 1 / 0.05, 1 / 0.01])
    centres = np.array([[0, 0, -0.5], [0, 0, -0.53]], np.float32)
    shapes = np.stack([flat, tall]).astype(np.float32)
    bounds = np.array([0.04, 0.05], np.float32)
    p = DatasetConfig()
    ch = ss.inputs(centres, R, cam, p, filters=(), ellipsoids=Ellipsoids(centres, shapes, bounds,
                                                                           np.array([0.5, 3.0], np.float32)))
    density, fluid = ch[DENSITY_CHANNEL], ch["aniso.A"] > 0
    centre = density.shape[0] // 2
    assert density[centre, centre] == 3.0, "the needle behind the disc's centre"
    assert density[centre, centre + int(0.03 / 0.5 * cam.focal_px)] == 0.5, "the disc alone"
    assert density[centre - int(0.045 / 0.53 * cam.focal_px), centre] == 3.0, "the needle alone"
    assert (density[~fluid] == 0).all() and (density[fluid] > 0).all()
    assert DENSITY_CHANNEL not in ss.inputs(centres, R, cam, p, filters=(),
                                            ellipsoids=Ellipsoids(centres, shapes, bounds))


def test_ellipsoids_flatten_a_sheet(ss, launch):
    """Particles of a jittered two-layer sheet: an interior particle's ellipsoid stays a sphere of
    about the particle radius, and drawing ellipsoids instead of spheres makes the unfiltered
    surface much flatter (its normals closer to the sheet's)."""
    from pipeline.surface import particle_ellipsoids

    p = DatasetConfig()
    block = np.stack(np.meshgrid(*[np.arange(-6, 7) * 2 * R] * 3, indexing="ij"), -1).reshape(-1, 3)
    ell = particle_ellipsoids(block.astype(np.float32), R, p, launch)
    inner = np.argmin(np.linalg.norm(block, axis=1))
    semi = 1 / np.linalg.eigvalsh(ell.shapes[inner].astype(np.float64))
    np.testing.assert_allclose(semi, R, rtol=0.15)

    cam = _camera(160, 40.0)
    sheet = np.concatenate([_sheet(-0.6, (-0.25, 0.25), size=0.25), _sheet(-0.6 - 2 * R, (-0.25, 0.25), size=0.25)])
    sheet += np.random.default_rng(0).normal(scale=0.15 * R, size=sheet.shape)
    sheet = sheet.astype(np.float32)
    spheres = ss.inputs(sheet, R, cam, p, filters=())
    ellipsoids = ss.inputs(sheet, R, cam, p, filters=(), ellipsoids=particle_ellipsoids(sheet, R, p, launch))
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(spheres["A"] > 0, iterations=15, border_value=0)
    inner &= binary_erosion(ellipsoids["aniso.A"] > 0, iterations=15, border_value=0)
    assert inner.sum() > 3000
    tilt = {}
    for name, z in (("sphere", spheres["Z"]), ("ellipsoid", ellipsoids["aniso.Z"])):
        n = ss.normals(z, cam)[inner]
        tilt[name] = float(np.degrees(np.arccos(np.clip(n[:, 2], -1, 1))).mean())
    assert tilt["ellipsoid"] < 0.5 * tilt["sphere"], tilt
    np.testing.assert_allclose(ellipsoids["aniso.N"][inner], ss.normals(ellipsoids["aniso.Z"], cam)[inner])


def test_the_cpus_row_splat_of_ellipsoids_is_the_warp_kernels_bit_for_bit(ss, launch, monkeypatch):
    """On the CPU the ellipsoid splat's first pass runs each row of a box sixteen pixels a vector
    (``native.splat_ellipsoid_rows``): the same arithmetic as the Warp kernel CUDA runs, so the same
    depth, mask, chord thickness and largest density bit for bit, in row bands and on one band;
    the splat with normals (the Warp kernel's two passes) draws the same depth."""
    from pipeline.surface import particle_ellipsoids

    rng = np.random.default_rng(12)
    x = (rng.normal(size=(3000, 3)) * (0.06, 0.03, 0.05) + (0.01, -0.02, -0.55)).astype(np.float32)
    ell = particle_ellipsoids(x, R, DatasetConfig(), launch, density=True)
    cam = Camera(look_at((0.15, 0.1, -0.3), (0.01, -0.02, -0.55)), 40.0, 150, 130)  # rows of 150
    def maps(splat):  # depth, mask, thickness and density (not the normals)
        depth, mask, thickness, _, density = splat
        return [a.numpy().copy() for a in (depth, mask, thickness, density)]

    native = maps(ss._splat_ellipsoids(ell, cam))
    with_normals = ss._splat_ellipsoids(ell, cam, with_normals=True)[0].numpy().copy()
    monkeypatch.setattr(ss.launch, "cpu", False)  # the Warp kernel, one band
    scalar = maps(ss._splat_ellipsoids(ell, cam))
    assert native[1].sum() > 2000 and (native[3] > 0).any()
    for got, want in zip(native, scalar, strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(with_normals, native[0])


def test_ellipsoids_kept_on_the_device_splat_as_the_hosts(ss, launch):
    """``particle_ellipsoids(on_device=True)`` (a GPU's way; here on the CPU's Warp arrays) leaves
    the ellipsoids as arrays where the anisotropy made them: their shapes and bounds are the host's
    float32 numbers bit for bit, the centres move into view space on the device within a float32
    ulp of the host's ``to_view``, and the splat reading them in place draws the host's surface."""
    import warp as wp

    from pipeline.screen import kernels as K
    from pipeline.surface import particle_ellipsoids

    p = DatasetConfig()
    rng = np.random.default_rng(11)
    x = (rng.normal(size=(3000, 3)) * (0.06, 0.03, 0.05) + (0.01, -0.02, -0.55)).astype(np.float32)
    host = particle_ellipsoids(x, R, p, launch)
    kept = particle_ellipsoids(x, R, p, launch, on_device=True)
    assert all(isinstance(a, wp.array) for a in (kept.centres, kept.shapes, kept.bounds))
    np.testing.assert_array_equal(kept.centres.numpy(), host.centres)
    np.testing.assert_array_equal(kept.shapes.numpy(), host.shapes)
    np.testing.assert_array_equal(kept.bounds.numpy(), host.bounds)

    cam = Camera(look_at((0.15, 0.1, -0.3), (0.01, -0.02, -0.55)), 40.0, 128, 128)  # a turned camera
    out = wp.empty(len(x), dtype=wp.vec3, device="cpu")
    launch(K.view_centres, len(x), [kept.centres, wp.mat33d(*cam.view[:3, :3].ravel()),
                                    wp.vec3d(*cam.view[:3, 3]), out])
    expected = cam.to_view(host.centres.astype(np.float64)).astype(np.float32)
    assert np.all(np.abs(out.numpy() - expected) <= np.spacing(np.abs(expected)))

    a, b = ss.splat_ellipsoids(host, cam), ss.splat_ellipsoids(kept, cam)
    assert a.mask.sum() > 2000
    assert (a.mask != b.mask).sum() <= 2  # a centre an ulp away may move a pixel on the rim
    both = (a.mask > 0) & (b.mask > 0)
    np.testing.assert_allclose(b.depth[both], a.depth[both], atol=1e-6)
    np.testing.assert_allclose(b.thickness[both], a.thickness[both], atol=1e-5)
    np.testing.assert_allclose(b.normals[both], a.normals[both], atol=1e-4)


def test_ellipsoid_inputs_without_raw_normals_leave_out_only_those(ss, launch):
    """``raw_normals=False`` (every method but ``aniso``) skips the unfiltered ellipsoid depth's
    normals; every other map is the same, bit for bit."""
    from pipeline.surface import particle_ellipsoids

    p = DatasetConfig()
    rng = np.random.default_rng(13)
    x = (rng.normal(size=(2000, 3)) * (0.06, 0.03, 0.05) + (0.01, -0.02, -0.55)).astype(np.float32)
    cam = Camera(look_at((0.15, 0.1, -0.3), (0.01, -0.02, -0.55)), 40.0, 96, 96)
    ell = particle_ellipsoids(x, R, p, launch)
    full = ss.inputs(x, R, cam, p, ("bilateral",), ellipsoids=ell)
    lean = ss.inputs(x, R, cam, p, ("bilateral",), ellipsoids=ell, raw_normals=False)
    assert set(full) - set(lean) == {"aniso.N"} and full["aniso.A"].sum() > 500
    for key in lean:
        np.testing.assert_array_equal(lean[key], full[key], err_msg=key)


def test_the_frame_shares_one_sphere_splat_between_its_filter_methods(ss, launch):
    """With ``SPHERE_FILTERS`` set for the frame, the first filter method splats once for the
    others; each method's maps must be those it makes alone, and the later ones must splat nothing."""
    from pipeline.methods import SPHERE_FILTERS, normal_source, sphere_filters_of
    from pipeline.timing import Timings

    rng = np.random.default_rng(5)
    x = (rng.random((1500, 3)) * [0.3, 0.2, 0.3]).astype(np.float32)
    cam = Camera(look_at((0.15, 0.35, 0.7), (0.15, 0.05, 0.15)), 40.0, 96, 96)
    p = DatasetConfig()
    methods = ["bilateral", "nrf", "gaussian"]
    shared = {SPHERE_FILTERS: sphere_filters_of(["refined", *methods, "mesh"])}
    assert shared[SPHERE_FILTERS] == tuple(methods)
    for k, method in enumerate(methods):
        t = Timings()
        together = normal_source(method, x, 0.01, cam, p, ss, launch, timings=t, frame_cache=shared)
        alone = normal_source(method, x, 0.01, cam, p, ss, launch, frame_cache={})
        for key in ("normals", "depth", "mask", "thickness"):
            np.testing.assert_array_equal(together[key], alone[key], err_msg=f"{method} {key}")
        assert ("splat" in t.as_dict()) == (k == 0), f"{method}: {t.as_dict()}"


def test_ellipsoid_shapes_turn_into_view_space_as_numpy_did(ss):
    """The splat turns each world-space shape matrix into view space on the device (``view_shapes``);
    it must give the float32 matrices the host's float64 einsum gave, bit for bit."""
    import warp as wp

    from pipeline.screen import kernels as K

    rng = np.random.default_rng(8)
    a = rng.normal(size=(4000, 3, 3))
    shapes = ((a @ a.transpose(0, 2, 1)) * rng.uniform(10, 500, size=(4000, 1, 1))).astype(np.float32)
    cam = Camera(look_at((0.3, 0.8, 1.1), (0.05, 0.1, -0.2)), 40.0, 64, 64)
    rot = cam.view[:3, :3]
    want = np.einsum("ij,njk,lk->nil", rot, shapes.astype(np.float64), rot).astype(np.float32)
    out = wp.zeros(len(shapes), dtype=wp.mat33, device="cpu")
    ss.launch(K.view_shapes, len(shapes), [wp.array(shapes, dtype=wp.mat33, device="cpu"),
                                           wp.mat33d(*rot.astype(np.float64).ravel()), out])
    np.testing.assert_array_equal(out.numpy(), want)


def test_inputs_on_the_device_are_the_host_maps_as_tensors_that_later_views_leave_alone(ss, launch):
    """``on_device`` gives each map as a torch tensor holding a copy of the device buffer: the same
    values as the host arrays, sphere and ellipsoid splats alike, and untouched by the next view,
    which reuses every buffer (a tensor viewing a buffer would change with it)."""
    import torch

    from pipeline.surface import particle_ellipsoids

    rng = np.random.default_rng(6)
    x = (rng.normal(size=(1200, 3)) * 0.05 + (0.0, 0.0, -0.6)).astype(np.float32)
    p = DatasetConfig()
    ell = particle_ellipsoids(x, R, p, launch)
    cam, other = _camera(96), Camera(look_at((0.1, 0.1, 0.0), (0, 0, -0.6)), 40.0, 96, 96)
    for kw in ({"filters": ("bilateral", "nrf")}, {"filters": ("bilateral",), "ellipsoids": ell}):
        want = ss.inputs(x, R, cam, p, **kw)
        got = ss.inputs(x, R, cam, p, on_device=True, **kw)
        later = ss.inputs(x, R, other, p, on_device=True, **kw)
        assert set(got) == set(want) and len(want) >= 6
        for key, value in want.items():
            assert isinstance(got[key], torch.Tensor) and got[key].shape == value.shape, key
            np.testing.assert_array_equal(got[key].numpy(), value, err_msg=key)
        assert not np.array_equal(later[next(iter(later))].numpy(), got[next(iter(got))].numpy())


def test_host_maps_hold_their_own_memory_that_later_views_leave_alone(ss, launch):
    """On the CPU each host map is the device buffer it was made in, handed over rather than copied:
    the next views (every buffer name again, the same sizes) must write new buffers, not it."""
    from pipeline.surface import particle_ellipsoids

    rng = np.random.default_rng(7)
    x = (rng.normal(size=(1200, 3)) * 0.05 + (0.0, 0.0, -0.6)).astype(np.float32)
    p = DatasetConfig()
    ell = particle_ellipsoids(x, R, p, launch)
    cam, other = _camera(96), Camera(look_at((0.1, 0.1, 0.0), (0, 0, -0.6)), 40.0, 96, 96)
    motion = np.ones((len(x), 4), np.float32)
    first = {**ss.inputs(x, R, cam, p, filters=("bilateral", "nrf")),
             **ss.inputs(x, R, cam, p, filters=("bilateral",), ellipsoids=ell)}
    moved, covered = ss.motion(x, motion, R, cam)
    kept = {key: value.copy() for key, value in first.items()}
    kept_motion = moved.copy()
    assert covered.any() and all(value.any() for value in kept.values())
    ss.inputs(x, R, other, p, filters=("bilateral", "nrf"))
    ss.inputs(x, R, other, p, filters=("bilateral",), ellipsoids=ell)
    ss.motion(x, 2 * motion, R, other)
    ss.splat_ellipsoids(ell, other)
    for key, value in kept.items():
        np.testing.assert_array_equal(first[key], value, err_msg=key)
    np.testing.assert_array_equal(moved, kept_motion)


def test_buffers_are_reused_while_their_size_stays_and_replaced_when_it_changes(ss, launch):
    """One device array a name: frames of one size reuse it, and a growing particle count (an
    emitter) or a new image size (the dataset's random views) replaces it instead of keeping one
    array a size for as long as the ScreenSpace lives. The maps are those of a fresh ScreenSpace."""
    from pipeline.surface import particle_ellipsoids

    p = DatasetConfig()
    rng = np.random.default_rng(3)
    x = (rng.normal(size=(1200, 3)) * (0.05, 0.03, 0.04) + (0.0, 0.0, -0.5)).astype(np.float32)
    ss.inputs(x[:1000], R, _camera(64), p, filters=("bilateral",))
    names = set(ss._buffers)
    kept = {name: a for name, (_, a) in ss._buffers.items()}
    ss.inputs(x[:1000], R, _camera(64), p, filters=("bilateral",))
    assert all(ss._buffers[name][1] is kept[name] for name in names), "the same size reuses its arrays"
    for k, n in enumerate((1000, 1100, 1200)):  # growing particle counts at growing image sizes
        cam = _camera(64 + 32 * k)
        got = ss.inputs(x[:n], R, cam, p, filters=("bilateral",),
                        ellipsoids=particle_ellipsoids(x[:n], R, p, launch))
        fresh = ScreenSpace("cpu")
        want = fresh.inputs(x[:n], R, cam, p, filters=("bilateral",),
                            ellipsoids=particle_ellipsoids(x[:n], R, p, launch))
        fresh.close()
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)
    assert len(ss._buffers) <= len(names) + 3  # plus the ellipsoid splat's normals and shapes, no more
    assert ss._buffers["view_shapes"][1].shape[0] == 1200


def test_positions_on_the_device_splat_as_host_positions(ss):
    """A GPU's dataset uploads a frame's positions once for all its views: the sphere splat then
    moves them into view space on the device (``view_centres``). On the CPU's Warp arrays every
    map equals the host way's to a float32 ulp of the centres (here: exactly)."""
    import warp as wp

    rng = np.random.default_rng(12)
    x = (rng.normal(size=(4000, 3)) * (0.06, 0.03, 0.05) + (0.01, -0.02, -0.55)).astype(np.float32)
    cam = Camera(look_at((0.15, 0.1, -0.3), (0.01, -0.02, -0.55)), 40.0, 96, 96)
    host = ss.inputs(x, R, cam, DatasetConfig(), filters=("bilateral", "nrf"))
    kept = ss.inputs(wp.array(x, dtype=wp.vec3, device="cpu"), R, cam, DatasetConfig(), filters=("bilateral", "nrf"))
    assert host["A"].sum() > 1000
    assert (kept["A"] != host["A"]).sum() <= 2  # a centre an ulp away may move a pixel on the rim
    both = (kept["A"] > 0) & (host["A"] > 0)
    for key in host:
        np.testing.assert_allclose(kept[key][both], host[key][both], atol=1e-5, err_msg=key)


def test_splat_boxes_hold_exactly_the_pixels_a_sphere_covers():
    """``splat_bounds``: every pixel centre whose ray meets the sphere (float64 geometry) lies in the
    box, and the plane through the eye and each edge column (row) of pixel centres meets the sphere.
    An off-axis sphere's silhouette is an
    ellipse longer than its on-axis circle: for the large ones here it reaches past that circle
    grown by a pixel, the box this one replaced."""
    import warp as wp

    import pipeline.screen.kernels as K

    @wp.kernel
    def boxes(centres: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float), focal: float, width: int,
              height: int, out: wp.array(dtype=wp.vec4i)):
        i = wp.tid()
        out[i] = K.splat_bounds(centres[i], radii[i], focal, width, height, 0, height)

    w, h, focal = 160, 120, 100.0
    rng = np.random.default_rng(4)
    n = 300
    depth = rng.uniform(1.0, 3.0, n)
    centres = np.stack([rng.uniform(-0.8, 0.8, n) * depth, rng.uniform(-0.6, 0.6, n) * depth, -depth], 1)
    radii = np.where(np.arange(n) % 3 == 0, rng.uniform(0.2, 0.5, n), rng.uniform(0.003, 0.03, n))
    got = wp.zeros(n, dtype=wp.vec4i, device="cpu")
    wp.launch(boxes, n, [wp.array(centres.astype(np.float32), dtype=wp.vec3, device="cpu"),
                         wp.array(radii.astype(np.float32), dtype=float, device="cpu"), focal, w, h, got],
              device="cpu")
    px, py = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(px + 0.5 - w / 2) / focal, -(py + 0.5 - h / 2) / focal, -np.ones_like(px, float)], -1)
    clipped_before = 0
    for c, r, (x0, x1, y0, y1) in zip(centres, radii, got.numpy(), strict=True):
        # distance from the centre to each pixel's ray line
        along = rays @ c / (rays * rays).sum(-1)
        covered = np.linalg.norm(c - along[..., None] * rays, axis=-1) <= r
        ys, xs = np.nonzero(covered)
        if not len(xs):
            continue
        assert x0 <= xs.min() and xs.max() <= x1 and y0 <= ys.min() and ys.max() <= y1
        # and no wider: the plane through the eye and each edge column's (row's) centres meets the sphere
        for x in (x0, x1):
            u = (x + 0.5 - w / 2) / focal
            assert abs(c[0] + u * c[2]) / np.hypot(1.0, u) <= r + 0.02 / focal * -c[2]  # the box's slack: 0.01 px
        for y in (y0, y1):
            v = -(y + 0.5 - h / 2) / focal
            assert abs(c[1] + v * c[2]) / np.hypot(1.0, v) <= r + 0.02 / focal * -c[2]  # the box's slack: 0.01 px
        d = -c[2]
        circle = focal * r / np.sqrt(d * d - r * r) + 1.0
        cx, cy = w / 2 + focal * c[0] / d, h / 2 - focal * c[1] / d
        clipped_before += (xs < np.floor(cx - circle)).any() or (xs > np.ceil(cx + circle)).any() \
            or (ys < np.floor(cy - circle)).any() or (ys > np.ceil(cy + circle)).any()
    assert clipped_before > 0


def test_millimetre_spheres_metres_away_cover_exactly_their_silhouettes():
    """Particles of 4 mm at 6-7 m (a million-particle frame's, about a pixel wide): the splat covers
    the pixels whose centre rays pass within the radius (float64 geometry), but for those within a
    thousandth of it. The discriminant b^2 - a (|c|^2 - r^2) cancelled to a part in 10^5 there and
    moved the rim by several percent of the radius at random."""
    rng = np.random.default_rng(5)
    w, h = 320, 240
    cam = Camera(look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0)), 10.0, w, h)
    r = 0.004
    x = np.stack([rng.uniform(-0.25, 0.25, 600), rng.uniform(-0.2, 0.2, 600), -rng.uniform(6.0, 7.0, 600)], 1)
    x = x.astype(np.float32)
    _, mask, _ = ScreenSpace("cpu")._splat(x, r, cam)
    got = mask.numpy().reshape(h, w) > 0
    f = cam.focal_px
    nearest = np.full((h, w), np.inf)
    for centre in cam.to_view(x.astype(np.float64)):
        d = -centre[2]
        cx, cy = int(w / 2 + f * centre[0] / d), int(h / 2 - f * centre[1] / d)
        ys, xs = np.mgrid[max(cy - 4, 0):min(cy + 5, h), max(cx - 4, 0):min(cx + 5, w)]
        rays = np.stack([(xs + 0.5 - w / 2) / f, -(ys + 0.5 - h / 2) / f, -np.ones(xs.shape)], -1)
        along = rays @ centre / (rays * rays).sum(-1)
        dist = np.linalg.norm(centre - along[..., None] * rays, axis=-1)
        nearest[ys, xs] = np.minimum(nearest[ys, xs], dist)
    sure = np.abs(nearest - r) > 1e-3 * r
    assert (nearest < r).sum() > 1000  # pixels covered: about three a sphere
    np.testing.assert_array_equal(got[sure], (nearest < r)[sure])
