"""Latitude-longitude environment maps from OpenEXR (``.exr``) or Radiance RGBE (``.hdr``) files.

The Radiance reader follows Greg Ward's format: a ``#?RADIANCE`` (or ``#?RGBE``) header ending in
an empty line, a resolution line ``-Y H +X W`` (rows top to bottom), then per scanline either
flat RGBE pixels or the "new" run-length encoding (each of the four byte planes on its own, runs
marked by a count above 128). A pixel is (R, G, B) * 2^(E - 136), black when E is 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def read_environment(path: str | Path) -> np.ndarray:
    """An environment map as H x W x 3 linear float32 (row 0 looks up); errors name the file."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        from pipeline.exr import read_exr, stack

        rgb = stack(read_exr(path, ["R", "G", "B"]), "", ("R", "G", "B"))
    elif suffix in (".hdr", ".pic", ".rgbe"):
        rgb = read_hdr(path)
    else:
        raise ValueError(f"environment map {path}: unknown format {suffix!r} (use .exr or .hdr)")
    if not np.isfinite(rgb).all():
        raise ValueError(f"environment map {path}: has non-finite pixels")
    return np.ascontiguousarray(rgb, np.float32)


def _scanline(buf: memoryview, pos: int, width: int, path: Path) -> tuple[np.ndarray, int]:
    """One RGBE scanline (width x 4 bytes) starting at ``pos``; returns it and the next position."""
    if width < 8 or width > 0x7FFF or pos + 4 > len(buf) or buf[pos] != 2 or buf[pos + 1] != 2 or buf[pos + 2] & 0x80:
        flat = np.frombuffer(buf[pos:pos + 4 * width], np.uint8)
        if flat.size != 4 * width:
            raise ValueError(f"environment map {path}: truncated pixel data")
        return flat.reshape(width, 4), pos + 4 * width
    if (buf[pos + 2] << 8 | buf[pos + 3]) != width:
        raise ValueError(f"environment map {path}: scanline width does not match the header")
    pos += 4
    line = np.empty((4, width), np.uint8)
    for plane in range(4):
        x = 0
        while x < width:
            if pos >= len(buf):
                raise ValueError(f"environment map {path}: truncated run-length data")
            count = buf[pos]
            pos += 1
            if count > 128:
                count -= 128
                if x + count > width or pos >= len(buf):
                    raise ValueError(f"environment map {path}: bad run-length data")
                line[plane, x:x + count] = buf[pos]
                pos += 1
            else:
                if count == 0 or x + count > width or pos + count > len(buf):
                    raise ValueError(f"environment map {path}: bad run-length data")
                line[plane, x:x + count] = np.frombuffer(buf[pos:pos + count], np.uint8)
                pos += count
            x += count
    return line.T, pos


def read_hdr(path: str | Path) -> np.ndarray:
    """A Radiance RGBE (``.hdr``) image as H x W x 3 float32 (row 0 at the top)."""
    path = Path(path)
    data = path.read_bytes()
    if not data.startswith((b"#?RADIANCE", b"#?RGBE")):
        raise ValueError(f"environment map {path}: not a Radiance .hdr file (no #?RADIANCE header)")
    end = data.find(b"\n\n")
    if end < 0:
        raise ValueError(f"environment map {path}: header without an end")
    header = data[:end].decode("ascii", "replace")
    if "FORMAT=" in header and "FORMAT=32-bit_rle_rgbe" not in header:
        raise ValueError(f"environment map {path}: only 32-bit_rle_rgbe is supported")
    line_end = data.find(b"\n", end + 2)
    size = data[end + 2:line_end].split()
    if len(size) != 4 or size[0] != b"-Y" or size[2] != b"+X":
        raise ValueError(f"environment map {path}: unsupported orientation {b' '.join(size).decode()!r} "
                         "(only -Y H +X W)")
    height, width = int(size[1]), int(size[3])
    buf, pos = memoryview(data), line_end + 1
    rgbe = np.empty((height, width, 4), np.uint8)
    for row in range(height):
        rgbe[row], pos = _scanline(buf, pos, width, path)
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0).astype(np.float32)
    return rgbe[..., :3].astype(np.float32) * scale[..., None]
