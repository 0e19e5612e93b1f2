"""EXR frames round-trip exactly with their names; damaged files are named in the error."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from pipeline.cache import CacheError
from pipeline.exr import read_exr, write_exr


def test_float32_round_trip_is_exact_with_names(tmp_path):
    rng = np.random.default_rng(0)
    names = ["R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z", "target.N.X", "bilateral.Z", "thickness"]
    channels = {n: rng.normal(size=(33, 47)).astype(np.float32) * 1e3 for n in names}
    channels["Z"][0, 0] = np.float32(1e-30)
    write_exr(tmp_path / "frame_0001.exr", channels)
    back = read_exr(tmp_path / "frame_0001.exr")
    assert sorted(back) == sorted(names)
    for n in names:
        np.testing.assert_array_equal(back[n], channels[n])
        assert back[n].dtype == np.float32


def test_truncated_exr_is_named(tmp_path):
    write_exr(tmp_path / "f.exr", {"Z": np.ones((16, 16), np.float32)})
    raw = (tmp_path / "f.exr").read_bytes()
    (tmp_path / "f.exr").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CacheError, match="f.exr"):
        read_exr(tmp_path / "f.exr")


def test_missing_channel_is_named(tmp_path):
    write_exr(tmp_path / "f.exr", {"Z": np.ones((4, 4), np.float32)})
    with pytest.raises(CacheError, match="N.X"):
        read_exr(tmp_path / "f.exr", ["N.X"])


def test_half_channels_and_lossless_compressions(tmp_path):
    rng = np.random.default_rng(1)
    channels = {n: rng.normal(size=(20, 30)).astype(np.float32) for n in ("L.C.R", "L.C.A", "L.D.Z", "L.N.Y")}
    for compression in ("zip", "zstd", "piz", "none"):
        write_exr(tmp_path / f"{compression}.exr", channels, half=("L.C.R", "L.C.A"), compression=compression)
        back = read_exr(tmp_path / f"{compression}.exr")
        for n in ("L.D.Z", "L.N.Y"):
            np.testing.assert_array_equal(back[n], channels[n])
        np.testing.assert_array_equal(back["L.C.R"], channels["L.C.R"].astype(np.float16))
    with pytest.raises(ValueError, match="jpeg"):
        write_exr(tmp_path / "x.exr", channels, compression="jpeg")


def test_dwaa_is_lossy_only_on_colour_and_y_named_channels(tmp_path):
    """Why ``render.exr_compression: dwaa`` is for review copies: the Y of a data pass loses precision."""
    rng = np.random.default_rng(2)
    smooth = np.cumsum(rng.normal(size=(64, 64)), axis=1).astype(np.float32) / 8
    channels = {"L.N.X": smooth, "L.N.Y": smooth, "L.C.R": smooth, "L.C.A": smooth}
    write_exr(tmp_path / "dwaa.exr", channels, compression="dwaa")
    back = read_exr(tmp_path / "dwaa.exr")
    np.testing.assert_array_equal(back["L.N.X"], smooth)
    np.testing.assert_array_equal(back["L.C.A"], smooth)
    assert np.abs(back["L.N.Y"] - smooth).max() > 1e-4 and np.abs(back["L.C.R"] - smooth).max() > 1e-4


def test_camera_header_attributes_round_trip(tmp_path):
    from pipeline.camera import Camera, look_at
    from pipeline.exr import camera_attributes, read_exr_header

    cam = Camera(look_at((1.0, 2.0, 3.0), (0.2, 0.1, -0.5)), 35.0, 48, 32)
    write_exr(tmp_path / "f.exr", {"Z": np.ones((32, 48), np.float32)},
              attributes=camera_attributes(cam, 29.97, sensor_width_mm=36.0, frame=12))
    header = read_exr_header(tmp_path / "f.exr")
    # Imath multiplies row vectors: p' = p M; camera space +Z looks ahead (RenderMan)
    point = np.array([0.3, 0.4, -0.2])
    in_camera = np.append(point, 1.0) @ header["worldToCamera"]
    np.testing.assert_allclose(in_camera[:3], cam.to_view(point[None])[0] * [1, 1, -1], atol=1e-5)
    ndc = np.append(point, 1.0) @ header["worldToNDC"]
    col, row, d = cam.project(cam.to_view(point[None]))
    np.testing.assert_allclose(ndc[:3] / ndc[3], [col[0] / 48, row[0] / 32, 1 / d[0]], rtol=1e-5)
    # landscape: the 36 mm spans the width; 35 degrees vertical over 24 mm
    np.testing.assert_allclose(header["sensorOverallDimensions"], [36.0, 24.0])
    assert header["pinholeFocalLength"] == pytest.approx(12.0 / np.tan(np.radians(17.5)), rel=1e-6)
    assert header["framesPerSecond"] == Fraction(2997, 100) and header["imageCounter"] == 12


def test_openimageio_reads_names_values_and_camera(tmp_path):
    """A second, independent reader: OpenImageIO (PyPI wheel) sees the same channels and matrices."""
    oiio = pytest.importorskip("OpenImageIO")
    from pipeline.camera import Camera, look_at
    from pipeline.exr import camera_attributes

    rng = np.random.default_rng(3)
    names = ["ViewLayer.Combined.R", "ViewLayer.Combined.A", "ViewLayer.Depth.Z", "ViewLayer.Vector.W"]
    channels = {n: rng.normal(size=(8, 12)).astype(np.float32) for n in names}
    channels["ViewLayer.Depth.Z"][0, 0] = np.inf
    cam = Camera(look_at((0.0, 1.0, 4.0), (0.0, 0.0, 0.0)), 50.0, 12, 8)
    write_exr(tmp_path / "f.exr", channels, half=("ViewLayer.Combined.R",), attributes=camera_attributes(cam))
    buf = oiio.ImageBuf(str(tmp_path / "f.exr"))
    spec = buf.spec()
    pixels = buf.get_pixels(oiio.FLOAT)
    for k, name in enumerate(spec.channelnames):
        expected = channels[name].astype(np.float16) if name.endswith("R") else channels[name]
        np.testing.assert_array_equal(pixels[..., k], expected.astype(np.float32), err_msg=name)
    assert sorted(spec.channelnames) == sorted(names)
    np.testing.assert_allclose(np.asarray(spec.getattribute("worldToCamera")).reshape(4, 4),
                               (np.diag([1.0, 1.0, -1.0, 1.0]) @ cam.view).T, atol=1e-6)


def test_the_focal_length_in_pixels_comes_back_from_the_header(tmp_path):
    from pipeline.camera import Camera, look_at
    from pipeline.exr import camera_attributes, header_focal_px, read_exr_header, write_exr

    for w, h in ((64, 40), (30, 50)):
        cam = Camera(look_at((0, 1, 3), (0, 0, 0)), 35.0, w, h)
        write_exr(tmp_path / "f.exr", {"Z": np.zeros((h, w), np.float32)}, attributes=camera_attributes(cam))
        assert header_focal_px(read_exr_header(tmp_path / "f.exr")) == pytest.approx(cam.focal_px, rel=1e-5)
    assert header_focal_px({}) is None


def test_openexr_threads_write_the_same_bytes(tmp_path):
    """pipeline.exr gives OpenEXR a thread pool (one thread per core) to compress line blocks in
    parallel; a file must come out byte for byte as without one, for each lossless and lossy codec."""
    import OpenEXR

    from pipeline.exr import EXR_THREADS

    rng = np.random.default_rng(4)
    channels = {f"c{k}": rng.normal(size=(181, 203)).astype(np.float32) for k in range(7)}
    before = OpenEXR.global_thread_count()
    assert before == EXR_THREADS >= 1
    try:
        for compression in ("zip", "zstd", "piz", "dwaa"):
            files = []
            for threads in (0, 3):
                OpenEXR.set_global_thread_count(threads)
                path = tmp_path / f"{compression}_{threads}.exr"
                write_exr(path, channels, half=("c1",), compression=compression)
                files.append(path.read_bytes())
            assert files[0] == files[1], compression
    finally:
        OpenEXR.set_global_thread_count(before)


def test_a_bad_exr_thread_count_is_named(monkeypatch):
    from pipeline.exr import exr_threads

    monkeypatch.setenv("DEEP_SSFR_EXR_THREADS", "many")
    with pytest.raises(ValueError, match="DEEP_SSFR_EXR_THREADS must be a whole number"):
        exr_threads()
    monkeypatch.setenv("DEEP_SSFR_EXR_THREADS", "0")
    assert exr_threads() == 0


def test_a_forked_child_reads_and_writes_exrs(tmp_path):
    """OpenEXR's thread pool does not survive a fork (a DataLoader worker hung on its first view):
    pipeline.exr stops it before a fork and starts it again, so a child reads and writes."""
    import multiprocessing

    import OpenEXR

    from pipeline.exr import EXR_THREADS

    rng = np.random.default_rng(6)
    channels = {f"c{k}": rng.normal(size=(256, 256)).astype(np.float32) for k in range(6)}
    write_exr(tmp_path / "parent.exr", channels)
    ctx = multiprocessing.get_context("fork")
    child = ctx.Process(target=_copy_exr, args=(tmp_path / "parent.exr", tmp_path / "child.exr"))
    child.start()
    child.join(60)
    if child.is_alive():
        child.kill()
        pytest.fail("the forked child hung on an EXR")
    assert child.exitcode == 0
    assert OpenEXR.global_thread_count() == EXR_THREADS
    for name, a in read_exr(tmp_path / "child.exr").items():
        np.testing.assert_array_equal(a, channels[name])


def _copy_exr(source, target) -> None:
    write_exr(target, read_exr(source))
