"""OpenEXR frames: multi-channel float32 (or half) images with Blender/Nuke-style channel names,
and the camera written as the format's standard header attributes.

Channels are given as ``{"ViewLayer.Normal.X": array, "Z": array, "target.N.X": array, ...}``.
Writes go through a temporary file and a rename. ZIP and PIZ are lossless; DWAA and DWAB apply a
lossy DCT to every channel whose name ends in R, G, B or Y (also data passes such as ``Normal.Y``)
and are only offered for review copies.

Camera attributes (OpenEXR "Standard Attributes"): ``worldToCamera`` and ``worldToNDC`` are Imath
M44f matrices, which multiply row vectors (``p' = p M``), so each is the transpose of the
column-vector matrix. The camera space is RenderMan's: left-handed, +X right, +Y up, +Z along the
view (``pipeline.camera``'s view space with Z negated). NDC has (0, 0) at the top-left corner of
the image and (1, 1) at the bottom-right; ``worldToNDC`` is projective (divide by w), and its z is
1 / depth.
"""

from __future__ import annotations

import math
import os
from fractions import Fraction
from pathlib import Path

import numpy as np
import OpenEXR

from pipeline.cache import CacheError, atomic_path, redo_hint, write_failure
from pipeline.camera import Camera, lens_of

# OpenEXR compresses and decompresses a file's line blocks on a thread pool of its own when it has
# one (it has none by default): the same bytes (tested), and a 25-channel 512 x 512 ZIP view
# written in 136 instead of 229 ms and read in 37 instead of 65 on this 2-core machine; the
# dataset stage on a GPU and the render's writer thread write on the host while the device works.
# ``DEEP_SSFR_EXR_THREADS`` sets the pool's size (0: none), e.g. for many Ray workers on one node.


def exr_threads() -> int:
    """The size of OpenEXR's thread pool: ``DEEP_SSFR_EXR_THREADS``, else one per core."""
    value = os.environ.get("DEEP_SSFR_EXR_THREADS", "").strip()
    if not value:
        return os.cpu_count() or 1
    if not value.isdigit():
        raise ValueError(f"DEEP_SSFR_EXR_THREADS must be a whole number of threads (0: none), got {value!r}")
    return int(value)


EXR_THREADS = exr_threads()


def _stop_pool() -> None:
    OpenEXR.set_global_thread_count(0)  # its threads finish the queued blocks first, then exit


def _start_pool() -> None:
    OpenEXR.set_global_thread_count(EXR_THREADS)


# A forked child (a DataLoader worker) would inherit the pool's bookkeeping but not its threads, and
# wait forever on its first EXR: the pool stops before a fork and starts again on both sides.
_start_pool()
os.register_at_fork(before=_stop_pool, after_in_parent=_start_pool, after_in_child=_start_pool)

COMPRESSIONS = {"none": OpenEXR.NO_COMPRESSION, "zip": OpenEXR.ZIP_COMPRESSION, "zstd": OpenEXR.ZSTD_COMPRESSION,
                "piz": OpenEXR.PIZ_COMPRESSION, "dwaa": OpenEXR.DWAA_COMPRESSION, "dwab": OpenEXR.DWAB_COMPRESSION}
"""Compression names of ``RenderConfig.exr_compression`` and their OpenEXR codes."""

FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])
"""The pipeline's right-handed view space (looking down -Z) to OpenEXR's camera space (+Z ahead)."""


def world_to_camera(camera: Camera) -> np.ndarray:
    """Column-vector 4x4 from world to OpenEXR camera space (left-handed, +Z along the view)."""
    return FLIP_Z @ camera.view


def camera_to_ndc(camera: Camera) -> np.ndarray:
    """Projective column-vector 4x4 from OpenEXR camera space to NDC: x, y in [0, 1] over the image
    (y down) after dividing by w = depth, and z = 1 / depth (an invertible matrix)."""
    f = camera.focal_px
    return np.array([[f / camera.width, 0.0, 0.5, 0.0],
                     [0.0, -f / camera.height, 0.5, 0.0],
                     [0.0, 0.0, 0.0, 1.0],
                     [0.0, 0.0, 1.0, 0.0]])


def sensor_size_mm(camera: Camera, sensor_width_mm: float = 36.0) -> tuple[float, float]:
    """Sensor width and height (mm) whose longer side is ``sensor_width_mm`` (Blender's auto fit)."""
    if camera.width >= camera.height:
        return sensor_width_mm, sensor_width_mm * camera.height / camera.width
    return sensor_width_mm * camera.width / camera.height, sensor_width_mm


def camera_attributes(camera: Camera, fps: float | None = None, sensor_width_mm: float = 36.0,
                      frame: int | None = None) -> dict:
    """Standard OpenEXR header attributes of a camera: ``worldToCamera``, ``worldToNDC`` (Imath row-
    vector matrices), ``pinholeFocalLength`` (mm), ``sensorOverallDimensions`` (mm), and with ``fps``
    ``framesPerSecond``, with ``frame`` ``imageCounter``."""
    attrs = {
        "worldToCamera": np.ascontiguousarray(world_to_camera(camera).T, np.float32),
        "worldToNDC": np.ascontiguousarray((camera_to_ndc(camera) @ world_to_camera(camera)).T, np.float32),
        "pinholeFocalLength": float(lens_of(camera, sensor_width_mm)),
        "sensorOverallDimensions": np.asarray(sensor_size_mm(camera, sensor_width_mm), np.float32),
    }
    if fps is not None:
        attrs["framesPerSecond"] = Fraction(fps).limit_denominator(1001) if math.isfinite(fps) else Fraction(24)
    if frame is not None:
        attrs["imageCounter"] = int(frame)
    return attrs


def header_focal_px(header: dict) -> float | None:
    """The focal length in pixels of a frame whose header has ``camera_attributes``' lens (the inverse
    of ``pinholeFocalLength`` on a sensor spanning the image's longer side); None without them."""
    focal_mm, sensor = header.get("pinholeFocalLength"), header.get("sensorOverallDimensions")
    window = header.get("dataWindow")
    if focal_mm is None or sensor is None or window is None:
        return None
    (x0, y0), (x1, y1) = (np.asarray(v).ravel() for v in window)
    return float(focal_mm) * max(x1 - x0 + 1, y1 - y0 + 1) / float(max(sensor))


def write_exr(path: str | Path, channels: dict[str, np.ndarray], half: tuple[str, ...] = (),
              compression: str = "zip", attributes: dict | None = None) -> None:
    """Write H x W arrays as float32 channels (float16 for names in ``half``) with ``compression``
    (a key of ``COMPRESSIONS``) and extra header ``attributes`` (e.g. ``camera_attributes``)."""
    if not channels:
        raise ValueError("no channels to write")
    if compression not in COMPRESSIONS:
        raise ValueError(f"unknown EXR compression {compression!r} (one of {', '.join(COMPRESSIONS)})")
    shapes = {a.shape for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"channels must share one H x W shape, got {shapes}")
    # OpenEXR.File replaces the arrays of the dict it is given: hand it fresh copies.
    data = {name: np.ascontiguousarray(a, dtype=np.float16 if name in half else np.float32)
            for name, a in channels.items()}
    header = {**(attributes or {}), "compression": COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    with atomic_path(Path(path)) as tmp:
        try:
            OpenEXR.File(header, data).write(str(tmp))
        except OSError:
            raise
        except Exception as exc:  # OpenEXR raises a bare error whose text names the temporary file
            raise OSError(*write_failure(Path(tmp).parent, f"cannot write the EXR ({exc})"), str(path)) from None


def read_exr(path: str | Path, names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Read channels (all, or ``names``) as float32 arrays; a damaged file raises CacheError."""
    path = Path(path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            chans = f.channels()
            wanted = names if names is not None else list(chans)
            missing = [n for n in wanted if n not in chans]
            if missing:
                raise CacheError(f"{path}: missing channels {missing} (has {sorted(chans)})")
            return {n: np.asarray(chans[n].pixels, dtype=np.float32) for n in wanted}
    except CacheError:
        raise
    except FileNotFoundError:
        raise CacheError(f"missing file {path}") from None
    except Exception as exc:
        raise CacheError(f"corrupt EXR file {path} ({exc}); {redo_hint(path)}") from None


def read_exr_header(path: str | Path) -> dict:
    """The header attributes of an EXR file (matrices as 4x4 float32 arrays); a damaged file raises
    CacheError."""
    path = Path(path)
    try:
        with OpenEXR.File(str(path), header_only=True) as f:
            return dict(f.header())
    except FileNotFoundError:
        raise CacheError(f"missing file {path}") from None
    except Exception as exc:
        raise CacheError(f"corrupt EXR file {path} ({exc}); {redo_hint(path)}") from None


def stack(channels: dict[str, np.ndarray], prefix: str, suffixes=("X", "Y", "Z")) -> np.ndarray:
    """H x W x k array of ``prefix + suffix`` channels (e.g. ``stack(c, "target.N.")``)."""
    return np.stack([channels[prefix + s] for s in suffixes], axis=-1)
