"""Houdini BGEO v5 point files as Partio writes them (big-endian), gzip-compressed or plain.

Compression is detected by the gzip magic bytes, not the name (``.bgeo`` and ``.bgeo.gz`` both work).
Layout: ``Bgeo`` ``V`` version(5), then int32 counts (points, prims, point groups, prim groups,
point/vertex/prim/detail attributes); each point attribute: uint16 name length, name, uint16
component count, int32 Houdini type (0 float, 1 int, 5 vector), default values; then per point
x y z w (float32) followed by its attributes.
"""

from __future__ import annotations

import gzip
import struct
from pathlib import Path

import numpy as np

from pipeline.particles.frame import ParticleFormatError, ParticleFrame, frame_from_point_data

_TYPES = {0: ">f4", 1: ">i4", 5: ">f4"}


def read(path: Path) -> ParticleFrame:
    """Read positions and point attributes (velocity ``v``, radius ``pscale``)."""
    raw = Path(path).read_bytes()
    try:
        data = gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw
    except (EOFError, OSError) as exc:
        raise ParticleFormatError(f"{path}: corrupt or truncated gzip stream ({exc})") from None
    if data[:5] != b"BgeoV":
        raise ParticleFormatError(f"{path}: not a BGEO file (magic {data[:5]!r})")
    if len(data) < 41:
        raise ParticleFormatError(f"{path}: truncated header")
    version, n_points, n_prims, _, _, n_point_attr, _, _, _ = struct.unpack(">9i", data[5:41])
    if version != 5:
        raise ParticleFormatError(f"{path}: BGEO version {version}, only version 5 is supported")
    if n_prims:
        raise ParticleFormatError(f"{path}: has {n_prims} primitives; only point clouds are supported")
    pos = 41
    fields = [("P", ">f4", (4,))]
    for i in range(n_point_attr):
        try:
            (name_len,) = struct.unpack(">H", data[pos:pos + 2])
            name = data[pos + 2:pos + 2 + name_len].decode("ascii", "replace")
            pos += 2 + name_len
            size, htype = struct.unpack(">Hi", data[pos:pos + 6])
        except struct.error:
            raise ParticleFormatError(f"{path}: truncated: point attribute {i + 1} of {n_point_attr} is cut") from None
        pos += 6
        if htype not in _TYPES:
            raise ParticleFormatError(f"{path}: attribute {name!r} has unsupported Houdini type {htype}")
        pos += 4 * size  # defaults
        fields.append((name, _TYPES[htype], (size,)))
    dtype = np.dtype(fields)
    need = pos + n_points * dtype.itemsize
    if len(data) < need:
        raise ParticleFormatError(f"{path}: truncated: {n_points} points need {need} bytes, "
                                  f"file decodes to {len(data)}")
    rec = np.frombuffer(data, dtype=dtype, count=n_points, offset=pos)
    return frame_from_point_data(rec["P"][:, :3], {name: rec[name] for name in dtype.names[1:]})
