"""OpenEXR frames: multi-channel float32 images with Blender/Nuke-style channel names.

Channels are given as ``{"N.X": array, "Z": array, "target.N.X": array, ...}``. Writes go
through a temporary file and a rename. ZIP compression is lossless for float32 (DWAA is lossy even
on float channels named R/G/B: never used here).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from pipeline.cache import CacheError, atomic_path, redo_hint, write_failure


def write_exr(path: str | Path, channels: dict[str, np.ndarray], half: tuple[str, ...] = ()) -> None:
    """Write H x W arrays as float32 channels (float16 for names in ``half``), ZIP-compressed."""
    if not channels:
        raise ValueError("no channels to write")
    shapes = {a.shape for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"channels must share one H x W shape, got {shapes}")
    # OpenEXR.File replaces the arrays of the dict it is given: hand it fresh copies.
    data = {name: np.ascontiguousarray(a, dtype=np.float16 if name in half else np.float32)
            for name, a in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
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


def stack(channels: dict[str, np.ndarray], prefix: str, suffixes=("X", "Y", "Z")) -> np.ndarray:
    """H x W x k array of ``prefix + suffix`` channels (e.g. ``stack(c, "target.N.")``)."""
    return np.stack([channels[prefix + s] for s in suffixes], axis=-1)
