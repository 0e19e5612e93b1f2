"""Rendered EXR frames as a compositor sees them: channel names, premultiplied alpha, depth of the
background, the camera in the header and motion vectors, read back with OpenEXR and OpenImageIO."""

from __future__ import annotations

import dataclasses
import logging
import threading

import numpy as np
import pytest

from pipeline.camera import Camera, look_at
from pipeline.config import Config, RenderConfig
from pipeline.exr import read_exr, read_exr_header, stack
from pipeline.methods import channel_names
from pipeline.renderer import SequenceRenderer
from pipeline.screen.motion import particle_motion
from pipeline.shading.background import Surroundings

SIZE = 64
FPS = 24.0
RADIUS = 0.08
L = "ViewLayer."
EXPECTED_CHANNELS = [f"{L}Combined.{c}" for c in "RGBA"] + [f"{L}Depth.Z"] + [f"{L}Fluid.{c}" for c in "RGBA"] + [
    f"{L}Thickness.X", f"{L}Mask.X"] + [f"{L}Normal.{c}" for c in "XYZ"] + [f"{L}ViewNormal.{c}" for c in "XYZ"] + [
    f"{L}Vector.{c}" for c in "XYZW"]


def _camera() -> Camera:
    return Camera(look_at((0.5, 0.6, 2.2), (0.5, 0.25, 0.5)), 40.0, SIZE, SIZE)


def _blob(centre=(0.5, 0.3, 0.5), single: bool = False) -> np.ndarray:
    """A small ball of particles (a fluid drop) around ``centre``, or one particle there."""
    if single:
        return np.asarray([centre], np.float32)
    g = np.linspace(-1.5, 1.5, 4) * RADIUS
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return (pts[np.linalg.norm(pts, axis=1) <= 2.2 * RADIUS] + centre).astype(np.float32)


def _render(tmp_path, velocity=(0.0, 0.0, 0.0), frames=(1, 2), cameras=None, single=False, **render):
    """Render a drop (or a ``single`` particle) moving at ``velocity`` (m/s) over the box 0..1
    with the bilateral method."""
    p = RenderConfig(width=SIZE, height=SIZE, method="bilateral", comparison=False, **render)
    config = dataclasses.replace(Config(scenes=()), render=p)
    v = None if velocity is None else np.asarray(velocity, np.float32)

    def load(frame: int):
        x = _blob(single=single) + (0 if v is None else v * (frame - 1) / FPS)
        return x, None if v is None else np.broadcast_to(v, x.shape).copy()

    cams = cameras or [_camera()] * len(frames)
    around = Surroundings((0.0, 0.0, 0.0), (1.0, 0.6, 1.0), walls=False)
    with SequenceRenderer(tmp_path, "drop", around, config, "cpu") as renderer:
        files = renderer.render(list(frames), load, RADIUS, lambda i: cams[i], fps=FPS)
    return files, [load(f)[0] for f in frames]


@pytest.fixture(scope="module")
def scene_frames(tmp_path_factory):
    """Two frames of a drop moving at a known velocity over a floor, the default background."""
    folder = tmp_path_factory.mktemp("scene")
    files, positions = _render(folder, velocity=(0.6, 0.3, 0.0))
    return folder, files, positions


def test_every_pass_is_one_named_layer_channel(scene_frames):
    folder, files, _ = scene_frames
    assert files[:2] == ["frames/frame_0001.exr", "frames/frame_0002.exr"]
    assert channel_names() == EXPECTED_CHANNELS
    ch = read_exr(folder / files[0])
    assert sorted(ch) == sorted(EXPECTED_CHANNELS)
    # Blender's split: the last token is the channel, the one before it the pass, the rest the layer
    assert {n.rsplit(".", 2)[0] for n in ch} == {"ViewLayer"}
    assert {n.rsplit(".", 2)[1] for n in ch} == {"Combined", "Depth", "Fluid", "Thickness", "Mask", "Normal",
                                                 "ViewNormal", "Vector"}
    # the default storage: half floats but for the depth, which half would round to millimetres here
    import OpenEXR

    stored = OpenEXR.File(str(folder / files[0]), separate_channels=True).channels()
    assert {n for n, c in stored.items() if c.pixels.dtype == np.float32} == {f"{L}Depth.Z"}


def test_scene_background_is_opaque_and_the_fluid_layer_is_premultiplied(scene_frames):
    folder, files, _ = scene_frames
    ch = read_exr(folder / files[0])
    np.testing.assert_array_equal(ch[f"{L}Combined.A"], 1.0)
    fluid = stack(ch, f"{L}Fluid.", "RGBA")
    covered = fluid[..., 3] > 0
    assert 0 < covered.sum() < SIZE * SIZE
    assert not fluid[~covered].any(), "premultiplied: no colour where the fluid's alpha is 0"
    beauty = stack(ch, f"{L}Combined.", "RGB")
    np.testing.assert_allclose(beauty[covered], fluid[covered][:, :3], rtol=2e-3, atol=1e-4)  # half floats


def test_depth_is_the_backgrounds_outside_the_fluid_and_infinite_in_the_sky(scene_frames):
    folder, files, _ = scene_frames
    ch = read_exr(folder / files[0])
    z, fluid = ch[f"{L}Depth.Z"], ch[f"{L}Fluid.A"] > 0
    assert (z > 0).all(), "no zeros in the depth pass"
    cam = _camera()
    floor = np.isfinite(z) & ~fluid
    assert np.isinf(z[0]).all(), "the top row sees the sky"
    assert floor.any()
    # the floor lies at y = 0: unprojected floor pixels land there (to the rasteriser's depth precision)
    world = (cam.unproject(np.where(floor, z, 0))[floor] - cam.view[:3, 3]) @ cam.view[:3, :3]
    assert (np.abs(world[:, 1]) < 0.01 * z[floor]).all()
    # the drop (1.73 m away, 0.28 m in radius) is in front of the floor
    assert 1.73 - 0.3 < z[fluid].min() < z[fluid].max() < 1.73 + 0.3


def test_header_holds_the_pipeline_camera(scene_frames):
    folder, files, positions = scene_frames
    cam = _camera()
    header = read_exr_header(folder / files[0])
    flip = np.diag([1.0, 1.0, -1.0, 1.0])
    np.testing.assert_allclose(header["worldToCamera"], (flip @ cam.view).T, atol=1e-6)
    # worldToNDC (row vectors, projective) sends the drop's centre to its pixel / image size
    centre = np.append(positions[0].mean(0), 1.0)
    ndc = centre @ header["worldToNDC"]
    col, row, d = cam.project(cam.to_view(positions[0].mean(0)[None].astype(np.float64)))
    np.testing.assert_allclose(ndc[:2] / ndc[3], [col[0] / SIZE, row[0] / SIZE], atol=1e-5)
    np.testing.assert_allclose(ndc[2] / ndc[3], 1 / d[0], rtol=1e-5)
    # 40 degrees vertical on a square 36 mm sensor: f = 18 / tan(20 degrees)
    assert header["pinholeFocalLength"] == pytest.approx(18 / np.tan(np.radians(20)), rel=1e-6)
    np.testing.assert_allclose(header["sensorOverallDimensions"], [36.0, 36.0])
    assert float(header["framesPerSecond"]) == FPS and header["imageCounter"] == 1


def _analytic_motion(cam: Camera, x: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(Z, W) of Blender's Vector pass for a point at x moving at v: now minus one frame later, +Y up."""
    col0, row0, _ = cam.project(cam.to_view(x[None].astype(np.float64)))
    col1, row1, _ = cam.project(cam.to_view((x + v / FPS)[None].astype(np.float64)))
    return np.array([col0[0] - col1[0], row1[0] - row0[0]])


def test_motion_vectors_of_a_particle_at_a_known_speed(tmp_path):
    v = np.array([0.9, 0.3, -0.4])
    files, positions = _render(tmp_path, velocity=v, single=True, exr_half="none")  # float32: the motion's own error
    ch = read_exr(tmp_path / files[0])
    vec, fluid = stack(ch, f"{L}Vector.", "XYZW"), ch[f"{L}Fluid.A"] > 0
    assert fluid.sum() > 20
    ahead = _analytic_motion(_camera(), positions[0][0], v)
    assert np.abs(ahead).max() > 1.0, "the test needs a visible motion"
    np.testing.assert_allclose(vec[fluid][:, 2:], np.broadcast_to(ahead, (fluid.sum(), 2)), rtol=1e-5, atol=1e-5)
    # at constant velocity it came from as far behind: (X, Y) = then - now equals (Z, W) = now - next to
    # first order (perspective makes them differ slightly)
    np.testing.assert_allclose(vec[fluid][:, :2], vec[fluid][:, 2:], rtol=0.03)
    assert not vec[~fluid].any(), "a still camera and floor: no motion outside the fluid"


def test_motion_vectors_of_a_drop_follow_its_velocity(scene_frames):
    folder, files, positions = scene_frames
    ch = read_exr(folder / files[0])
    vec, fluid = stack(ch, f"{L}Vector.", "XYZW"), ch[f"{L}Fluid.A"] > 0
    ahead = _analytic_motion(_camera(), positions[0].mean(0), np.array([0.6, 0.3, 0.0]))
    # the front particles are nearer and move more pixels: within 12 % over a drop 0.28 m across at 1.7 m
    np.testing.assert_allclose(vec[fluid][:, 2:], np.broadcast_to(ahead, (fluid.sum(), 2)), rtol=0.12)


def test_second_reader_openimageio_sees_the_same_file(scene_frames):
    oiio = pytest.importorskip("OpenImageIO")
    folder, files, _ = scene_frames
    path = str(folder / files[1])
    inp = oiio.ImageInput.open(path)
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    pixels = inp.read_image(oiio.FLOAT)
    inp.close()
    assert sorted(spec.channelnames) == sorted(EXPECTED_CHANNELS)
    ours = read_exr(path)
    for k, name in enumerate(spec.channelnames):
        np.testing.assert_array_equal(pixels[..., k], ours[name], err_msg=name)
    np.testing.assert_allclose(np.asarray(spec.getattribute("worldToCamera")).reshape(4, 4),
                               read_exr_header(path)["worldToCamera"])
    assert spec.getattribute("compression") == "zip"
    assert [str(f) for f in spec.channelformats][:4] == ["half"] * 4


def test_transparent_background_is_premultiplied_with_infinite_depth(tmp_path):
    files, _ = _render(tmp_path, background="none", frames=(1,))
    ch = read_exr(tmp_path / files[0])
    beauty = stack(ch, f"{L}Combined.", "RGBA")
    empty = beauty[..., 3] == 0
    assert 0 < (~empty).sum() < SIZE * SIZE
    assert not beauty[empty].any(), "RGB is 0 where A is 0"
    np.testing.assert_array_equal(beauty, stack(ch, f"{L}Fluid.", "RGBA"))
    z = ch[f"{L}Depth.Z"]
    assert np.isinf(z[empty]).all() and np.isfinite(z[~empty]).all()
    assert (beauty[~empty][:, :3] > 0).all(), "the fluid still shows what it reflects and refracts"


def test_frames_without_velocities_get_zero_vectors_and_one_warning(tmp_path, caplog):
    caplog.set_level(logging.WARNING)
    files, _ = _render(tmp_path, velocity=None, frames=(1, 2, 3))
    assert caplog.text.count("no particle velocities") == 1
    for f in files[:3]:
        assert not stack(read_exr(tmp_path / f), f"{L}Vector.", "XYZW").any()


def test_a_moving_camera_moves_the_background(tmp_path):
    """An orbiting camera: the floor's vectors are its reprojection into the neighbouring frames."""
    cams = [Camera(look_at((0.5 + 2 * np.sin(a), 0.6, 0.5 + 2 * np.cos(a)), (0.5, 0.25, 0.5)), 40.0, SIZE, SIZE)
            for a in np.radians([-3.0, 0.0, 3.0])]
    files, _ = _render(tmp_path, frames=(1, 2, 3), cameras=cams)
    ch = read_exr(tmp_path / files[1])
    vec, z = stack(ch, f"{L}Vector.", "XYZW"), ch[f"{L}Depth.Z"]
    floor = np.isfinite(z) & (ch[f"{L}Fluid.A"] == 0)
    r, c = np.argwhere(floor)[len(np.argwhere(floor)) // 2]
    now = cams[1]
    world = (now.unproject(z)[r, c] - now.view[:3, 3]) @ now.view[:3, :3]
    col_n, row_n, _ = cams[2].project(cams[2].to_view(world[None]))
    col_p, row_p, _ = cams[0].project(cams[0].to_view(world[None]))
    centre = (c + 0.5, r + 0.5)
    np.testing.assert_allclose(vec[r, c], [col_p[0] - centre[0], centre[1] - row_p[0], centre[0] - col_n[0],
                                           row_n[0] - centre[1]], atol=1e-3)
    assert np.abs(vec[r, c]).max() > 0.5


def _numpy_camera_motion(depth, camera, prev, nxt):
    """The reference: static points unprojected, taken to the world and projected into each
    neighbouring camera with numpy (float64), as the renderer did before its Warp pass."""
    out = np.zeros((*depth.shape, 4), np.float32)
    solid = np.isfinite(depth) & (depth > 0)
    points = (camera.unproject(np.where(solid, depth, 0.0))[solid].astype(np.float64) - camera.view[:3, 3]) \
        @ camera.view[:3, :3]
    col, row, _ = camera.project(camera.to_view(points))
    for k, (other, sign) in enumerate(((prev, 1.0), (nxt, -1.0))):
        if other is None:
            continue
        c, r, d = other[0].project(other[0].to_view(points))
        delta = np.stack([c - col, -(r - row)], -1) * sign / other[1]
        out[solid, 2 * k:2 * k + 2] = np.where((d > 1e-6)[:, None], delta, 0.0)
    return out


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda:0", marks=pytest.mark.cuda)])
def test_the_camera_motion_pass_reprojects_static_surfaces(device):
    """The camera's motion of static surfaces (a Warp pass on the frame's device) is numpy's
    reprojection into the neighbouring cameras to rounding: frame gaps of 1 and 3, one neighbour
    or two, surfaces behind the next camera, empty (0) and infinite depths; on the CPU's tensors
    it gives the same; a camera at rest gives None."""
    import torch

    from pipeline.parallel import Launcher
    from pipeline.screen.motion import camera_motion

    rng = np.random.default_rng(4)
    size = (48, 64)
    cams = [Camera(look_at((0.3 * k, 0.5, 2.0 - 0.8 * k), (0.0, 0.0, 0.0)), 45.0, size[1], size[0]) for k in range(2)]
    cams.append(Camera(look_at((0.3, 0.4, 0.5), (-3.0, 0.0, -3.0)), 45.0, size[1], size[0]))  # turned: much behind
    depth = rng.uniform(0.5, 6.0, size).astype(np.float32)
    depth[:5] = 0.0
    depth[-4:, :10] = np.inf
    launch = Launcher(device)
    try:
        assert camera_motion(depth, cams[1], (cams[1], 1), None, launch) is None
        for prev, nxt in (((cams[0], 1), (cams[2], 3)), (None, (cams[2], 1)), ((cams[0], 3), None)):
            want = _numpy_camera_motion(depth, cams[1], prev, nxt)
            got = camera_motion(depth, cams[1], prev, nxt, launch)
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-4)
            assert (got == want).mean() > 0.95 and np.abs(got).max() > 1.0
            on_device = camera_motion(torch.from_numpy(depth).to(device), cams[1], prev, nxt, launch, on_device=True)
            assert isinstance(on_device, torch.Tensor)
            np.testing.assert_array_equal(on_device.cpu().numpy(), got)
        behind = _numpy_camera_motion(depth, cams[1], None, (cams[2], 1))[..., 2:]
        assert (np.isfinite(depth) & (depth > 0) & (behind == 0).all(-1)).sum() > 10, "some points behind"
    finally:
        launch.close()


def test_the_motion_splat_takes_the_front_particle(ss):
    """Two particles on one line of sight: pixels show the nearer one's motion; a reference depth
    (the frame's filtered surface) gives the same answer as the splat's own nearest depth."""
    cam = _camera()
    near, far = np.array([0.5, 0.3, 0.9]), np.array([0.5, 0.3, 0.2])
    positions = np.stack([near, far]).astype(np.float32)
    motion = np.array([[1.0, 2.0, 3.0, 4.0], [-5.0, -6.0, -7.0, -8.0]], np.float32)
    out, covered = ss.motion(positions, motion, RADIUS, cam)
    col, row, d = cam.project(cam.to_view(near[None]))
    assert covered[int(row[0]), int(col[0])]
    np.testing.assert_array_equal(out[int(row[0]), int(col[0])], motion[0])
    assert (out[covered] == motion[0]).all(1).sum() > (out[covered] == motion[1]).all(1).sum() > 0
    surface = np.where(covered, d[0], 0.0)  # a flat stand-in for the frame's surface at the near particle
    again, _ = ss.motion(positions, motion, RADIUS, cam, depth=surface)
    np.testing.assert_array_equal(again[int(row[0]), int(col[0])], motion[0])
    empty, none = ss.motion(np.zeros((0, 3), np.float32), np.zeros((0, 4), np.float32), RADIUS, cam)
    assert not empty.any() and not none.any()


def test_motion_pass_fills_uncovered_rims_and_keeps_the_background():
    """A visible disc wider than the splatted one (an ellipsoid's or the mesh's rim) takes the
    motion of the covered pixels next to it; the background keeps its camera motion."""
    from pipeline.methods import motion_pass

    yy, xx = np.mgrid[:32, :32]
    r = np.hypot(yy - 16, xx - 16)
    visible, covered = (r < 10).astype(np.float32), r < 6
    fluid = np.zeros((32, 32, 4), np.float32)
    fluid[covered] = [1.0, -2.0, 3.0, -4.0]
    background = np.full((32, 32, 4), 0.5, np.float32)
    out = motion_pass(visible, fluid, covered, background)
    np.testing.assert_array_equal(out[visible > 0], np.broadcast_to([1.0, -2.0, 3.0, -4.0], ((visible > 0).sum(), 4)))
    np.testing.assert_array_equal(out[visible == 0], 0.5)


@pytest.mark.parametrize("corner", [False, True])
def test_the_motion_pass_on_the_fluids_box_is_the_whole_images(corner):
    """The host pass works on the visible pixels' box grown by a pixel: the same values as filling
    the rims over the whole image, with covered pixels outside that box (a splat wider than what
    shows) and with the fluid touching the image's edge."""
    from pipeline.methods import fill_rims, motion_pass

    rng = np.random.default_rng(3)
    h, w = 48, 64
    yy, xx = np.mgrid[:h, :w]
    cy, cx = (4, 5) if corner else (24, 40)
    r = np.hypot(yy - cy, xx - cx)
    visible = ((r < 12) & (rng.random((h, w)) < 0.9)).astype(np.float32)
    covered = (r < 16) & (rng.random((h, w)) < 0.5)
    fluid = rng.normal(size=(h, w, 4)).astype(np.float32)
    background = rng.normal(size=(h, w, 4)).astype(np.float32)
    want = background.copy()
    whole = fill_rims(fluid, covered, visible > 0)
    want[visible > 0] = whole[visible > 0]
    np.testing.assert_array_equal(motion_pass(visible, fluid, covered, background), want)
    assert (want[visible > 0] != fluid[visible > 0]).any()  # some rims were filled


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
def test_particle_motion_of_tensors_is_the_host_motion(device):
    """On a GPU each particle's motion is made by torch from the uploaded positions and velocities:
    the same float64 arithmetic as numpy's, so on the CPU's tensors the same numbers, with moving
    cameras, frame gaps, particles behind a camera and particles at rest."""
    import torch

    rng = np.random.default_rng(5)
    x = (rng.random((3000, 3)) * [2.0, 1.0, 4.5] - [1.0, 0.0, 2.5]).astype(np.float32)
    v = rng.normal(size=(3000, 3)).astype(np.float32)
    cams = [Camera(look_at((0.1 * k, 0.4, 1.0 - 0.05 * k), (0.0, 0.2, -0.5)), 50.0, 96, 64) for k in range(3)]
    assert (cams[1].to_view(x.astype(np.float64))[:, 2] > 0).sum() > 100, "some particles behind the camera"
    for velocities, prev, nxt in ((v, (cams[0], 1), (cams[2], 2)), (None, None, None), (v, None, (cams[2], 1))):
        want = particle_motion(x, velocities, cams[1], FPS, prev, nxt)
        got = particle_motion(torch.from_numpy(x).to(device),
                              None if velocities is None else torch.from_numpy(velocities).to(device),
                              cams[1], FPS, prev, nxt)
        assert isinstance(got, torch.Tensor) and got.dtype == torch.float32 and got.device.type == device
        np.testing.assert_allclose(got.cpu().numpy(), want, rtol=1e-6, atol=1e-5)
        assert (got.cpu().numpy() == want).mean() > 0.999


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)])
@pytest.mark.parametrize("steps", [None, 1, 3, 5])
def test_rim_fill_of_tensors_is_the_pixel_lists(steps, device):
    """On tensors the rim fill runs as whole-image steps (a GPU would otherwise wait at every boolean
    index): the same values as the pixel-list fill on numpy, bit for bit, for one-channel and
    four-channel maps, holes at the border, fluid out of reach, and rings cut short by ``steps``."""
    import torch
    from scipy.ndimage import binary_dilation

    from pipeline.methods import fill_rims

    rng = np.random.default_rng(8)
    covered = rng.random((40, 56)) < 0.04
    covered = binary_dilation(covered, iterations=2) & (rng.random(covered.shape) < 0.8)
    wanted = binary_dilation(covered, iterations=6)
    wanted[:, :2] = True  # a strip at the border, partly out of reach
    wanted[30:34, 50:54] = True
    assert (wanted & ~covered).sum() > 300
    for values in (rng.normal(size=covered.shape).astype(np.float32),
                   rng.normal(size=(*covered.shape, 4)).astype(np.float32)):
        want = fill_rims(values, covered, wanted, steps)
        got = fill_rims(*(torch.from_numpy(a).to(device) for a in (values, covered, wanted)), steps)
        assert isinstance(got, torch.Tensor)
        np.testing.assert_array_equal(got.cpu().numpy(), want)
        changed = (want != values).reshape(*covered.shape, -1).any(-1)
        assert changed.sum() > 50 and not changed[covered].any()
        if steps == 1:
            assert (wanted & ~covered & ~changed).sum() > 100, "one ring leaves the far holes"


def test_the_motion_pass_on_the_device_is_the_host_pass(ss):
    """On a GPU the motion splat's maps stay torch tensors and the rim fill runs on them. On the
    CPU's tensors it must give the host pass bit for bit: rims several rings wide, holes at the
    image border (where the neighbours are clipped), fluid out of reach of any covered pixel, with
    and without the camera's motion behind."""
    import torch

    from pipeline.methods import motion_pass

    rng = np.random.default_rng(11)
    cam = _camera()
    x = (rng.random((400, 3)) * [0.6, 0.6, 0.3] + [0.2, 0.0, 0.3]).astype(np.float32)
    per_particle = rng.normal(size=(400, 4)).astype(np.float32)
    want_motion, want_covered = ss.motion(x, per_particle, RADIUS, cam)
    got_motion, got_covered = ss.motion(x, per_particle, RADIUS, cam, on_device=True)
    assert isinstance(got_motion, torch.Tensor) and isinstance(got_covered, torch.Tensor)
    np.testing.assert_array_equal(got_motion.numpy(), want_motion)
    np.testing.assert_array_equal(got_covered.numpy(), want_covered)
    # the particles and their motion as tensors too (a GPU's frame): Warp reads them in place
    from_tensors = ss.motion(torch.from_numpy(x), torch.from_numpy(per_particle), RADIUS, cam, on_device=True)
    np.testing.assert_array_equal(from_tensors[0].numpy(), want_motion)
    np.testing.assert_array_equal(from_tensors[1].numpy(), want_covered)
    from scipy.ndimage import binary_dilation

    visible = binary_dilation(want_covered, iterations=5).astype(np.float32)
    visible[:, :3] = 1.0  # a strip at the border, partly out of reach
    visible[40:44, 40:44] = 1.0
    assert (visible.astype(bool) & ~want_covered).sum() > 200
    for background in (None, rng.normal(size=want_motion.shape).astype(np.float32)):
        want = motion_pass(visible, want_motion, want_covered, background)
        got = motion_pass(visible, got_motion, got_covered, background)
        assert isinstance(got, torch.Tensor)
        np.testing.assert_array_equal(got.numpy(), want)
    np.testing.assert_array_equal(got_motion.numpy(), want_motion)  # the inputs are left as they were


def test_the_render_loop_kept_on_the_device_writes_the_host_loops_frames(tmp_path):
    """The render loop's GPU way (the sky, the refined maps and the motion splat kept as tensors
    between the steps) run on the CPU's tensors: every frame's EXR carries the host way's mask,
    depth, thickness and motion vectors, and its normals and colours to the rounding of the
    refiner's torch-made input."""
    from pipeline.frames import frame_name
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner

    size = 128
    p = RenderConfig(width=size, height=size, method="refined", comparison=False, exr_half="none")
    config = dataclasses.replace(Config(scenes=()), render=p)
    camera = Camera(look_at((0.5, 0.6, 1.6), (0.5, 0.3, 0.5)), 40.0, size, size)
    v = np.asarray((0.6, 0.3, 0.0), np.float32)
    r = 0.02  # a jittered lattice ball of small particles: fluid the refiner keeps
    g = np.arange(-0.2, 0.2 + 1e-9, 2 * r)
    ball = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    ball = ball[np.linalg.norm(ball, axis=1) <= 0.2] + np.random.default_rng(4).uniform(-0.3, 0.3, (1, 3)) * r
    ball = (ball + np.random.default_rng(5).uniform(-0.3, 0.3, ball.shape) * r + (0.5, 0.3, 0.5)).astype(np.float32)

    def load(frame: int):
        x = ball + v * (frame - 1) / FPS
        return x, np.broadcast_to(v, x.shape).copy()

    around = Surroundings((0.0, 0.0, 0.0), (1.0, 0.6, 1.0), walls=False)
    # float32: bfloat16 would round the two ways' float32 inputs, a rounding apart, further apart
    refiner = load_refiner(SHIPPED_WEIGHTS, precision="float32")
    frames = {}
    for on_device in (False, True):
        with SequenceRenderer(tmp_path / str(on_device), "drop", around, config, "cpu", refiner,
                              on_device=on_device) as renderer:
            renderer.render([1, 2], load, r, lambda i: camera, fps=FPS, videos=False)
        frames[on_device] = [read_exr(tmp_path / str(on_device) / "frames" / frame_name(f, "exr")) for f in (1, 2)]
    for host, dev in zip(frames[False], frames[True], strict=True):
        assert host[f"{L}Mask.X"].sum() > 300 and np.abs(stack(host, f"{L}Vector.", "XYZW")).max() > 0.1
        for name in (f"{L}Mask.X", f"{L}Depth.Z", f"{L}Thickness.X", *(f"{L}Vector.{c}" for c in "XYZW")):
            np.testing.assert_array_equal(dev[name], host[name], err_msg=name)
        # colour to 2e-3, relative where a specular highlight (HDR, up to about 9) magnifies the
        # normals' rounding
        for prefix, tol, rel in (("ViewNormal.", 1e-4, 0.0), ("Combined.", 2e-3, 2e-3)):
            for name in [n for n in host if n.startswith(L + prefix)]:
                np.testing.assert_allclose(dev[name], host[name], atol=tol, rtol=rel, err_msg=name)


def test_the_motion_pass_of_the_seen_particles_is_every_particles(tmp_path):
    """The ellipsoid methods find the particles in front (``seen_kernels``); the motion splat then
    reads only those, and its pass is the one every particle gives but at a few pixels of steep
    edges, where a particle under the surface along its normal lies within the splat's depth band."""
    size = 96
    p = RenderConfig(width=size, height=size, method="aniso_nrf", comparison=False)
    config = dataclasses.replace(Config(scenes=()), render=p)
    camera = Camera(look_at((1.0, 0.9, 1.6), (0.5, 0.3, 0.5)), 40.0, size, size)
    r = 0.01
    g = np.arange(-0.15, 0.15 + 1e-9, 2 * r)
    block = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + (0.5, 0.3, 0.5)
    x = (block + np.random.default_rng(6).uniform(-0.2, 0.2, block.shape) * r).astype(np.float32)
    v = np.random.default_rng(7).normal(0.0, 0.5, x.shape).astype(np.float32)  # every particle its own
    around = Surroundings((0.0, 0.0, 0.0), (1.0, 0.6, 1.0), walls=False)
    with SequenceRenderer(tmp_path, "block", around, config, "cpu") as renderer:
        frame = renderer.shade(x, r, camera)["aniso_nrf"]
        assert renderer._seen is not None and len(renderer._seen[1]) < 0.8 * len(x)
        renderer.motion(frame, x, v, r, camera, FPS, None, None)
        seen_only = frame.motion.copy()
        renderer._seen = None
        renderer.motion(frame, x, v, r, camera, FPS, None, None)
    assert np.abs(seen_only).max() > 0.1
    changed = np.any(seen_only != frame.motion, axis=-1)
    assert changed.mean() < 1e-3, changed.mean()


def test_half_channels_are_the_bits_numpy_would_write():
    """The EXR's half passes, converted by torch for speed, hold numpy's float16 bits: rounding,
    overflow to inf, subnormals, NaN and negative zero alike; the full-float depth is untouched."""
    from pipeline.methods import RenderedFrame

    rng = np.random.default_rng(3)
    h, w = 17, 23
    odd = np.array([np.nan, np.inf, -np.inf, -0.0, 7e4, 65519.0, 65520.0, 1e-8, 6e-5, 1 / 3], np.float32)

    def values(*shape):
        a = (rng.standard_normal(shape) * 10.0 ** rng.integers(-7, 5, shape)).astype(np.float32)
        a.reshape(-1)[: odd.size] = odd
        return a

    frame = RenderedFrame(values(h, w, 4), values(h, w, 4), values(h, w), values(h, w, 3), values(h, w, 3),
                          values(h, w), values(h, w), values(h, w, 4))
    half = RenderedFrame.half_channels("all_but_depth")
    fast, plain = frame.channels(half), frame.channels()
    assert list(fast) == list(plain) == channel_names()
    for name in fast:
        if name in half:
            assert fast[name].dtype == np.float16 and fast[name].flags.c_contiguous
            with np.errstate(over="ignore"):
                want = plain[name].astype(np.float16)
            np.testing.assert_array_equal(fast[name].view(np.uint16), want.view(np.uint16))
        else:
            assert fast[name].dtype == np.float32
            np.testing.assert_array_equal(fast[name], plain[name])


def test_frames_are_read_ahead_and_a_damaged_one_fails_in_its_turn(tmp_path):
    """The renderer reads each frame's particles while the frame before renders. A frame that
    cannot be read must still stop the run when its turn comes: the frames before it written, none
    after it read or written; a resumed run reads only the frames it has left."""
    from pipeline.cache import CacheError
    from pipeline.frames import frame_name

    p = RenderConfig(width=SIZE, height=SIZE, method="bilateral", comparison=False, background="none")
    config = dataclasses.replace(Config(scenes=()), render=p)
    read, broken, second_read = [], {3}, threading.Event()

    def load(frame: int):
        read.append(frame)
        if frame == 2:
            second_read.set()
        if frame in broken:
            raise CacheError(f"corrupt cache file {frame_name(frame)}")
        return _blob((0.5, 0.3 + 0.01 * frame, 0.5)), None

    around = Surroundings((0.0, 0.0, 0.0), (1.0, 0.6, 1.0), walls=False)
    with SequenceRenderer(tmp_path, "drop", around, config, "cpu") as renderer:
        shade = renderer.shade

        def shade_once_frame_2_is_read(*args):  # the first frame renders only once the next is read
            assert second_read.wait(timeout=30), "frame 2 was not read while frame 1 rendered"
            return shade(*args)

        renderer.shade = shade_once_frame_2_is_read
        with pytest.raises(CacheError, match="frame_0003"):
            renderer.render([1, 2, 3, 4], load, RADIUS, lambda i: _camera(), fps=FPS, videos=False)
        assert read == [1, 2, 3]
        assert [renderer.done(f) for f in (1, 2, 3, 4)] == [True, True, False, False]
        broken.clear()
        read.clear()
        renderer.render([1, 2, 3, 4], load, RADIUS, lambda i: _camera(), fps=FPS, videos=False)
        assert read == [3, 4] and all(renderer.done(f) for f in (1, 2, 3, 4))


def test_a_moving_cameras_background_is_rasterised_beside_the_frames_work(tmp_path, monkeypatch):
    """pyrender draws each new camera's background on a thread of its own while the frame's
    normals are computed: the normals here wait until that drawing has begun (in the same thread
    they would wait for ever), and each frame shows the background of its own camera."""
    import pipeline.renderer as renderer_module
    from pipeline.shading.background import BackgroundRenderer

    drawing, threads = threading.Event(), set()
    draw = BackgroundRenderer.render

    def draw_and_tell(self, camera):
        threads.add(threading.current_thread().name)
        drawing.set()
        return draw(self, camera)

    source = renderer_module.normal_source

    def source_once_drawing(*args, **kwargs):
        assert drawing.wait(timeout=30), "the background was not drawn beside the frame's work"
        drawing.clear()
        return source(*args, **kwargs)

    orbit = [_camera(), Camera(look_at((0.9, 0.6, 2.0), (0.5, 0.25, 0.5)), 40.0, SIZE, SIZE)]
    here = BackgroundRenderer(Surroundings((0.0, 0.0, 0.0), (1.0, 0.6, 1.0), walls=False),
                              RenderConfig(width=SIZE, height=SIZE), SIZE, SIZE)
    want = [here.render(camera)[1] for camera in orbit]  # drawn on this thread
    here.close()
    monkeypatch.setattr(BackgroundRenderer, "render", draw_and_tell)
    monkeypatch.setattr(renderer_module, "normal_source", source_once_drawing)
    files, _ = _render(tmp_path, frames=(1, 2), cameras=orbit)
    assert threads and threading.main_thread().name not in threads
    assert not np.array_equal(want[0], want[1])
    for f, depth in zip(files[:2], want, strict=True):
        ch = read_exr(tmp_path / f)
        floor = (ch[f"{L}Fluid.A"] == 0) & (depth > 0)
        assert floor.mean() > 0.3
        np.testing.assert_array_equal(ch[f"{L}Depth.Z"][floor], depth[floor])
