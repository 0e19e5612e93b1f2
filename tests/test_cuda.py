"""The CUDA paths against the CPU ones (``pytest -m cuda`` on a GPU machine; skipped elsewhere)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import warp as wp

from pipeline.camera import Camera, look_at
from pipeline.config import Cameras, FluidShape, SceneConfig, SimulateConfig, from_dict
from pipeline.exr import read_exr, stack
from pipeline.screen import ScreenSpace
from stages import cli
from tests.conftest import CAMERAS

pytestmark = pytest.mark.cuda


@wp.kernel
def hold_the_gpu(loops: int, out: wp.array(dtype=float)):
    """One thread counting for a while: the work queued after it waits (tens of milliseconds)."""
    x = wp.float32(0.0)
    for _ in range(loops):
        x = x * 0.999 + 1.0
    out[0] = x


@wp.kernel
def fill_with(value: float, out: wp.array(dtype=float)):
    out[wp.tid()] = value


def _busy_gpu(loops: int = 20_000_000) -> None:
    """Keep the current stream busy (tens of milliseconds by default), so that a download which does
    not wait returns before its data lands."""
    wp.launch(hold_the_gpu, 1, [loops, wp.zeros(1, dtype=float, device="cuda:0")], device="cuda:0")


class _EmptyVideo:
    """``pipeline.media.VideoWriter`` without ffmpeg: an empty file for each video."""

    def __init__(self, path, fps):
        self.path = Path(path)

    def __enter__(self):
        return self

    def send(self, image):
        pass

    def __exit__(self, kind, *exc):
        if kind is None:
            self.path.write_bytes(b"")


def _hold_every_launch(monkeypatch) -> None:
    """Hold the GPU for a few milliseconds before every Warp launch through a ``Launcher`` on CUDA."""
    from pipeline.parallel import Launcher

    launch = Launcher.__call__

    def held_launch(self, kernel, n, inputs):
        if not self.cpu:
            _busy_gpu(2_000_000)
        return launch(self, kernel, n, inputs)

    monkeypatch.setattr(Launcher, "__call__", held_launch)


def _blob(n: int = 3000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, 3)) * 0.05 + (0.0, 0.0, -0.6)).astype(np.float32)


def test_screen_space_inputs_on_the_gpu_equal_the_cpu():
    from pipeline.config import DatasetConfig

    cam = Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, 96, 96)
    x = _blob()
    out = {}
    for device in ("cpu", "cuda:0"):
        ss = ScreenSpace(device)
        out[device] = ss.inputs(x, 0.01, cam, DatasetConfig(), ("bilateral", "nrf"))
        ss.close()
    cpu, gpu = out["cpu"], out["cuda:0"]
    assert set(cpu) == set(gpu)
    import torch

    assert all(torch.from_numpy(a).is_pinned() for a in gpu.values()), "downloaded into page-locked memory"
    np.testing.assert_array_equal(cpu["A"], gpu["A"])
    for key in ("Z", "bilateral.Z", "nrf.Z"):
        np.testing.assert_allclose(gpu[key], cpu[key], atol=1e-5, err_msg=key)
    fluid = cpu["A"] > 0
    dots = np.sum(cpu["nrf.N"][fluid] * gpu["nrf.N"][fluid], axis=-1)
    assert np.degrees(np.arccos(np.clip(dots, -1, 1))).mean() < 0.1


def test_ellipsoids_stay_on_the_gpu_and_splat_as_the_cpus():
    """On a GPU ``particle_ellipsoids`` leaves the ellipsoids as device arrays and the splat reads
    them in place; the surface is the CPU's host way's (the anisotropy's sums may round otherwise)."""
    import warp as wp

    from pipeline.config import DatasetConfig
    from pipeline.parallel import Launcher
    from pipeline.surface import particle_ellipsoids

    x = (np.random.default_rng(3).normal(size=(3000, 3)) * (0.06, 0.03, 0.05) + (0, 0, -0.5)).astype(np.float32)
    cam = Camera(look_at((0.15, 0.1, -0.25), (0, 0, -0.5)), 40.0, 128, 128)
    out = {}
    for device in ("cpu", "cuda:0"):
        ss, launch = ScreenSpace(device), Launcher(device)
        ellipsoids = particle_ellipsoids(x, 0.0125, DatasetConfig(), launch)
        assert isinstance(ellipsoids.centres, wp.array) == (device != "cpu")
        out[device] = ss.splat_ellipsoids(ellipsoids, cam)
        ss.close()
        launch.close()
    cpu, gpu = out["cpu"], out["cuda:0"]
    assert cpu.mask.sum() > 2000 and (cpu.mask != gpu.mask).mean() < 1e-3
    both = (cpu.mask > 0) & (gpu.mask > 0)
    np.testing.assert_allclose(gpu.depth[both], cpu.depth[both], atol=1e-5)
    dots = np.sum(cpu.normals[both] * gpu.normals[both], axis=-1)
    assert np.degrees(np.arccos(np.clip(dots, -1, 1))).mean() < 0.1


def test_pbf_frame_on_the_gpu_matches_the_cpu_to_rounding():
    from pipeline.sim.pbf import PBFSolver

    scene = SceneConfig(name="t", cameras=from_dict(Cameras, CAMERAS), domain_lo=(0, 0, 0), domain_hi=(0.4, 0.6, 0.3),
                        fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.3, 0.3)),))
    params = SimulateConfig(particle_radius=0.0125, frames=1)
    states = {}
    for device in ("cpu", "cuda:0"):
        solver = PBFSolver(scene, params, device, seed=0)
        solver.advance_frame(1)
        states[device] = solver.state()
        solver.close()
    (xc, vc), (xg, vg) = states["cpu"], states["cuda:0"]
    assert xc.shape == xg.shape
    # the GPU gathers over full lists, the CPU scatters over half lists: sums in another order,
    # agreement to rounding, not bits
    np.testing.assert_allclose(xg, xc, atol=1e-4)
    np.testing.assert_allclose(vg, vc, atol=1e-2)


def test_pbf_on_the_gpu_repeats_bit_for_bit_and_its_scatter_way_agrees():
    """The GPU's default gather passes sum each particle's pairs in list order, so two runs are
    bit-identical (the scatter way's float atomics are not); the scatter way there still gives the
    same flow to rounding."""
    from pipeline.sim.pbf import PBFSolver

    scene = SceneConfig(name="t", cameras=from_dict(Cameras, CAMERAS), domain_lo=(0, 0, 0), domain_hi=(0.4, 0.6, 0.3),
                        fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.3, 0.3)),))
    states = []
    for passes in ("auto", "auto", "scatter"):
        params = SimulateConfig(particle_radius=0.0125, frames=2, pair_passes=passes)
        solver = PBFSolver(scene, params, "cuda:0", seed=0)
        assert solver.gather == (passes == "auto")
        for f in (1, 2):
            solver.advance_frame(f)
        states.append(solver.state())
        solver.close()
    for a, b in zip(states[0], states[1], strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(states[2][0], states[0][0], atol=1e-3)


def test_pipelined_frames_on_the_gpu_arrive_in_order(tmp_path):
    """The simulate loop queues frame k + 1 before it reads frame k back through pinned memory: each
    saved frame is its own frame (a frame apart differs by centimetres, the CPU agrees to rounding)."""
    from pipeline.frames import frame_name, load_frame
    from pipeline.sim.pbf import PBFSolver
    from pipeline.sim.runner import simulate_sequence

    scene = SceneConfig(name="t", cameras=from_dict(Cameras, CAMERAS), domain_lo=(0, 0, 0), domain_hi=(0.4, 0.6, 0.3),
                        fluid=(FluidShape(shape="box", lo=(0, 0.2, 0), hi=(0.12, 0.5, 0.3)),))
    params = SimulateConfig(particle_radius=0.0125, frames=3)
    simulate_sequence(tmp_path, scene, params, "cuda:0", seed=0)
    solver = PBFSolver(scene, params, "cpu", seed=0)
    for f in range(1, 4):
        solver.advance_frame(f)
        x, v = load_frame(tmp_path / frame_name(f))
        np.testing.assert_allclose(x, solver.state()[0], atol=1e-3, err_msg=f"frame {f}")
    solver.close()


@pytest.mark.parametrize("method, camera, held", [("nrf", "static", False), ("refined", "static", False),
                                                  ("refined", "orbit", False), ("refined", "orbit", True)])
def test_render_stage_on_the_gpu_writes_what_the_cpu_does(tmp_path, monkeypatch, method, camera, held):
    """The render stage on the GPU (the refined frame and its motion pass kept on the device there)
    writes the normals and motion vectors the CPU does, to the rounding of two simulations; with a
    turning camera too (its motion made on the device). No scene background: the GPU machine's
    image has no pyrender (nor EGL) for it; and no videos: imageio-ffmpeg's wheel (68 MB) cannot
    travel there, so an empty file stands in for each (the frames are what is compared).

    ``held``: the GPU is held for a while before every Warp launch of the render, so any host read
    of device output that does not wait for it (a download, a hand-over between streams) would
    read memory not yet written, and the frames would differ."""
    from tests.conftest import write_config

    monkeypatch.setattr("pipeline.renderer.write_video", lambda path, frames, fps: Path(path).write_bytes(b""))
    monkeypatch.setattr("pipeline.renderer.VideoWriter", _EmptyVideo)
    if held:
        _hold_every_launch(monkeypatch)

    scene = {"name": "tiny_dam", "domain_lo": [0, 0, 0], "domain_hi": [0.6, 0.5, 0.3],
             "fluid": [{"shape": "box", "lo": [0, 0, 0], "hi": [0.2, 0.3, 0.3]}], "cameras": CAMERAS}
    config = write_config(tmp_path, {"scenes": ["tiny_dam"], "seed": 3,
                                     "simulate": {"particle_radius": 0.0125, "frames": 2},
                                     "render": {"width": 64, "height": 64, "method": method, "comparison": False,
                                                "camera": camera, "background": "none"}},
                          {"tiny_dam": scene})
    frames = {}
    for device in ("cuda", "cpu"):
        monkeypatch.setenv("DEEP_SSFR_DEVICE", device)
        assert cli.main(["render", "--config", str(config)]) == 0
        (entry,) = [e for e in (tmp_path / "data" / "render").iterdir() if e.name not in frames.values()]
        frames[device] = entry.name
    ch = {d: read_exr(tmp_path / "data" / "render" / name / "frames" / "frame_0002.exr") for d, name in frames.items()}
    fluid = (ch["cpu"]["ViewLayer.Mask.X"] > 0) & (ch["cuda"]["ViewLayer.Mask.X"] > 0)
    assert fluid.sum() > 50
    n_cpu, n_gpu = stack(ch["cpu"], "ViewLayer.ViewNormal.")[fluid], stack(ch["cuda"], "ViewLayer.ViewNormal.")[fluid]
    angle = np.degrees(np.arccos(np.clip(np.sum(n_cpu * n_gpu, -1), -1, 1)))
    assert np.median(angle) < 1.0
    shown = (ch["cpu"]["ViewLayer.Fluid.A"] > 0) & (ch["cuda"]["ViewLayer.Fluid.A"] > 0)
    v_cpu, v_gpu = (stack(ch[d], "ViewLayer.Vector.", "XYZW")[shown] for d in ("cpu", "cuda"))
    assert np.abs(v_cpu).max() > 0.1
    assert np.median(np.abs(v_gpu - v_cpu)) < 0.05


@pytest.mark.parametrize("held", [False, True])
def test_dataset_stage_on_the_gpu_matches_the_cpu(tmp_path, monkeypatch, held):
    """Inputs and mesh targets (Warp's marching cubes on CUDA, scikit-image on the CPU) agree.
    ``held``: the GPU is held before every Warp launch (``_hold_every_launch``), so a view that the
    writer took before its copies landed would differ."""
    from tests.conftest import write_config

    if held:
        _hold_every_launch(monkeypatch)

    scene = {"name": "tiny_dam", "domain_lo": [0, 0, 0], "domain_hi": [0.6, 0.5, 0.3],
             "fluid": [{"shape": "box", "lo": [0, 0, 0], "hi": [0.2, 0.3, 0.3]}], "cameras": CAMERAS}
    config = write_config(tmp_path, {"scenes": ["tiny_dam"], "seed": 3,
                                     "simulate": {"particle_radius": 0.0125, "frames": 2},
                                     "dataset": {"width": 64, "height": 64, "frame_stride": 1}}, {"tiny_dam": scene})
    entries = {}
    for device in ("cuda", "cpu"):
        monkeypatch.setenv("DEEP_SSFR_DEVICE", device)
        assert cli.main(["dataset", "--config", str(config)]) == 0
        (entries[device],) = [e for e in (tmp_path / "data" / "dataset").iterdir() if e not in entries.values()]
    for view in ("static/frame_0002.exr", "orbit/frame_0002.exr"):
        a, b = read_exr(entries["cpu"] / view), read_exr(entries["cuda"] / view)
        both = (a["target.A"] > 0) & (b["target.A"] > 0)
        assert both.sum() > 0.97 * max((a["target.A"] > 0).sum(), (b["target.A"] > 0).sum())
        dots = np.sum(stack(a, "target.N.")[both] * stack(b, "target.N.")[both], -1)
        assert np.degrees(np.arccos(np.clip(dots, -1, 1))).mean() < 0.5
        np.testing.assert_allclose(b["target.Z"][both], a["target.Z"][both], atol=1e-4)
        # the inputs: the sphere splat and a filter of it, the ellipsoid splat (kept on the GPU) and its own
        for raw, filtered in (("", "bilateral.Z"), ("aniso.", "aniso_bilateral.Z")):
            both = (a[f"{raw}A"] > 0) & (b[f"{raw}A"] > 0)
            assert both.sum() > 0.97 * max((a[f"{raw}A"] > 0).sum(), (b[f"{raw}A"] > 0).sum()) > 0, raw
            for key in (f"{raw}Z", filtered):
                np.testing.assert_allclose(b[key][both], a[key][both], atol=1e-4, err_msg=key)


def test_refine_on_the_gpu_keeps_its_post_processing_there_and_matches_the_cpu():
    """The refiner's output stays on the GPU for resizing, lengths, the mask and normalisation
    (``Refiner.run``); the result agrees with the CPU's (convolutions may round differently)."""
    from pipeline.config import DatasetConfig
    from pipeline.methods import refine
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner
    from pipeline.parallel import Launcher
    from pipeline.surface import particle_ellipsoids
    from pipeline.views import screen_space_inputs

    x = (np.random.default_rng(2).normal(size=(2500, 3)) * (0.06, 0.03, 0.05) + (0, 0, -0.5)).astype(np.float32)
    cam = Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, 160, 160)
    ss, launch = ScreenSpace("cpu"), Launcher("cpu")
    ch = screen_space_inputs(x, 0.004, cam, DatasetConfig(), ss, filters=("bilateral",),
                             ellipsoids=particle_ellipsoids(x, 0.004, DatasetConfig(), launch, density=True),
                             aniso_filters=("bilateral",))
    ss.close()
    launch.close()
    out = {d: refine(load_refiner(SHIPPED_WEIGHTS, d, precision="float32"), ch, 0.5, cam.focal_px, 0.004)
           for d in ("cpu", "cuda")}
    (n_cpu, m_cpu, z_cpu), (n_gpu, m_gpu, z_gpu) = out["cpu"], out["cuda"]
    assert isinstance(n_gpu, np.ndarray) and n_gpu.dtype == np.float32
    assert (m_cpu == m_gpu).mean() > 0.995 and m_cpu.sum() > 100
    both = m_cpu & m_gpu
    angle = np.degrees(np.arccos(np.clip(np.sum(n_cpu[both] * n_gpu[both], -1), -1, 1)))
    assert np.median(angle) < 0.5
    np.testing.assert_array_equal(z_gpu[both], z_cpu[both])


def test_the_refined_frame_stays_on_the_gpu_and_shades_as_the_host_frame():
    """On the GPU the refined method's maps stay torch tensors from the splat to the shader, across
    Warp's stream and torch's. Several frames in a row (buffers reused, nothing synchronising the
    host in between but what the code does) must shade as the host way does on the same GPU: a
    missing stream hand-over reads half-written maps."""
    import torch

    from pipeline.config import DatasetConfig, RenderConfig
    from pipeline.methods import normal_source, shade_frame
    from pipeline.model import SHIPPED_WEIGHTS
    from pipeline.model.inference import load_refiner
    from pipeline.parallel import Launcher
    from pipeline.shading import Shader

    size = 512
    ss, launch, shader = ScreenSpace("cuda:0"), Launcher("cuda:0"), Shader("cuda:0")
    refiner = load_refiner(SHIPPED_WEIGHTS, "cuda", precision="float32")
    bg, bg_depth = np.full((size, size, 3), 0.5, np.float32), np.full((size, size), 10.0, np.float32)
    rp = RenderConfig(width=size, height=size)
    for seed in range(3):
        x = _blob(20000, seed)
        cam = Camera(look_at((0.05 * seed, 0, 0), (0, 0, -0.6)), 40.0, size, size)
        frames = {}
        for on_device in (True, False):
            src = normal_source("refined", x, 0.004, cam, DatasetConfig(), ss, launch, refiner, on_device=on_device)
            if on_device and refiner.splat == "ellipsoid":
                assert all(isinstance(src[k], torch.Tensor) and src[k].is_cuda for k in ("normals", "mask", "depth"))
            frames[on_device] = shade_frame(src, bg, bg_depth, cam, rp, shader)
        dev, host = frames[True], frames[False]
        assert host.mask.sum() > 1000
        assert (dev.mask == host.mask).mean() > 0.999
        both = (dev.mask > 0) & (host.mask > 0)
        np.testing.assert_array_equal(dev.thickness, host.thickness)
        np.testing.assert_array_equal(dev.depth[both], host.depth[both])
        shown = both & (host.fluid[..., 3] > 0)  # the shaded normals are 0 where the fluid shows nothing
        angle = np.degrees(np.arccos(np.clip(np.sum(dev.normals[shown] * host.normals[shown], -1), -1, 1)))
        assert np.percentile(angle, 99) < 0.5, seed
    for closer in (ss, launch, shader):
        closer.close()


def test_a_gpu_frames_downloads_land_in_page_locked_memory():
    """What a GPU frame brings to the host (the shaded passes, the sky, a tensor through ``host``)
    comes down into page-locked memory, the copy at the bus's speed, holding what the device made:
    the sky as the CPU's to rounding, the tensor exactly."""
    import torch

    from pipeline.config import RenderConfig
    from pipeline.shading import Shader
    from pipeline.vectors import host

    t = torch.arange(24, dtype=torch.float32, device="cuda").reshape(4, 6)
    a = host(t)
    assert torch.from_numpy(a).is_pinned()
    np.testing.assert_array_equal(a, np.arange(24, dtype=np.float32).reshape(4, 6))
    cam = Camera(look_at((0.0, 0.3, 1.0), (0.0, 0.0, 0.0)), 45.0, 48, 32)
    bg, bg_depth = np.full((32, 48, 3), 0.25, np.float32), np.zeros((32, 48), np.float32)
    bg_depth[16:] = 2.0
    p = RenderConfig(width=48, height=32)
    skies = {}
    for device in ("cuda:0", "cpu"):
        shader = Shader(device)
        skies[device] = shader.fill_sky(bg, bg_depth, cam, p)
        if device != "cpu":
            assert torch.from_numpy(skies[device]).is_pinned()
            n = np.zeros((32, 48, 3), np.float32)
            n[..., 2] = 1.0
            d, m = np.full((32, 48), 1.5, np.float32), np.ones((32, 48), np.float32)
            out = shader.shade(n, d, np.full((32, 48), 0.01, np.float32), m, skies[device], bg_depth, cam, p)
            assert all(torch.from_numpy(x).is_pinned() for x in (out.beauty, out.fluid, out.depth, out.normals_view))
            assert out.fluid[..., 3].min() > 0
        shader.close()
    np.testing.assert_allclose(skies["cuda:0"], skies["cpu"], atol=1e-5)


def _held(fn, first: bool = False):
    """``fn`` with the GPU held right after it has queued its work (``hold_the_gpu``), or with
    ``first`` right before: the host uploads (which wait for the GPU) are behind, the downloads that
    follow queue behind the hold."""
    def held(*args, **kwargs):
        if first:
            _busy_gpu()
        out = fn(*args, **kwargs)
        if not first:
            _busy_gpu()
        return out
    return held


def test_downloads_land_before_the_host_reads_them():
    """A copy into page-locked memory returns as soon as it is queued: each download the host reads
    (one map, a view's screen-space maps, the shaded passes, the sky) waits for its copies. The GPU
    is held just before each is queued, so one that did not wait would hand the host memory the
    copy had not yet written."""
    from pipeline.config import DatasetConfig, RenderConfig
    from pipeline.device import download
    from pipeline.shading import Shader

    value = float(np.random.default_rng().uniform(1.0, 2.0))
    values = wp.zeros(1 << 20, dtype=float, device="cuda:0")
    _busy_gpu()
    wp.launch(fill_with, values.shape, [value, values], device="cuda:0")
    assert np.all(download(values, (1024, 1024)) == np.float32(value))

    cam = Camera(look_at((0, 0, 0), (0, 0, -1)), 40.0, 256, 256)
    x = _blob(20000, seed=4)
    per_particle = np.random.default_rng(5).normal(size=(len(x), 4)).astype(np.float32)
    maps = {}
    for device in ("cpu", "cuda:0"):
        ss = ScreenSpace(device)
        if device != "cpu":  # between the splat (its upload) and the maps' downloads
            ss._splat, ss._filter = _held(ss._splat), _held(ss._filter)
        maps[device] = ss.inputs(x, 0.01, cam, DatasetConfig(), ("bilateral",))
        maps[device]["splat"] = ss.splat(x, 0.01, cam).mask
        if device != "cpu":  # before each of the motion pass's two downloads
            ss._take = _held(ss._take, first=True)
        maps[device]["motion"], maps[device]["moved"] = ss.motion(x, per_particle, 0.01, cam)
        ss.close()
    for key in ("A", "splat", "moved"):
        np.testing.assert_array_equal(maps["cuda:0"][key], maps["cpu"][key], err_msg=key)
    np.testing.assert_allclose(maps["cuda:0"]["motion"], maps["cpu"]["motion"], atol=1e-4)
    np.testing.assert_allclose(maps["cuda:0"]["bilateral.Z"], maps["cpu"]["bilateral.Z"], atol=1e-5)

    p = RenderConfig(width=256, height=256)
    bg, bg_depth = np.full((256, 256, 3), 0.25, np.float32), np.zeros((256, 256), np.float32)
    passes = {}
    for device in ("cpu", "cuda:0"):
        shader = Shader(device)
        launch = shader.launch
        if device != "cpu":  # between the inputs' uploads and the passes' downloads
            shader.launch = _held(launch)
        sky = shader.fill_sky(bg, bg_depth, cam, p)
        out = shader.shade(maps["cpu"]["bilateral.N"], maps["cpu"]["bilateral.Z"], maps["cpu"]["thickness"],
                           maps["cpu"]["A"], sky, bg_depth, cam, p)
        passes[device] = (sky, out.beauty, out.depth)
        shader.launch = launch
        shader.close()
    assert passes["cpu"][1][..., 3].sum() > 1000
    for name, gpu, cpu in zip(("sky", "beauty", "depth"), passes["cuda:0"], passes["cpu"], strict=True):
        np.testing.assert_allclose(gpu, cpu, rtol=1e-3, atol=1e-3, err_msg=name)  # the GPU rounds exp, pow otherwise
