"""PLY point clouds (ascii, binary little- or big-endian): the ``vertex`` element's x y z."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.particles import ParticleFormatError, ParticleFrame

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read(path: Path) -> ParticleFrame:
    """Read vertex positions (and vx vy vz when present)."""
    raw = Path(path).read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply") or end < 0:
        raise ParticleFormatError(f"{path}: not a PLY file or header incomplete")
    header = raw[:end].decode("ascii", "replace").splitlines()
    body = raw[end + len(b"end_header\n"):]
    fmt, elements = None, []
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if parts[1] == "list":
                raise ParticleFormatError(f"{path}: list properties (faces) are not supported")
            elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    if not elements or elements[0][0] != "vertex":
        raise ParticleFormatError(f"{path}: the first element must be 'vertex'")
    _, count, props = elements[0]
    names = [p[0] for p in props]
    if fmt == "ascii":
        rows = body.decode("ascii").split("\n")[:count]
        if len(rows) < count:
            raise ParticleFormatError(f"{path}: truncated: {count} vertices declared, {len(rows)} found")
        table = np.array([r.split()[: len(props)] for r in rows], dtype=np.float64)
        col = {n: table[:, i] for i, n in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(body) < count * dtype.itemsize:
            raise ParticleFormatError(f"{path}: truncated: {count} vertices need {count * dtype.itemsize} "
                                      f"bytes, {len(body)} present")
        rec = np.frombuffer(body, dtype=dtype, count=count)
        col = {n: rec[n] for n in names}
    if not {"x", "y", "z"} <= set(col):
        raise ParticleFormatError(f"{path}: vertex element lacks x, y, z")
    positions = np.stack([col["x"], col["y"], col["z"]], axis=1).astype(np.float32)
    velocities = None
    if {"vx", "vy", "vz"} <= set(col):
        velocities = np.stack([col["vx"], col["vy"], col["vz"]], axis=1).astype(np.float32)
    return ParticleFrame(positions, velocities)


def write(path: Path, frame: ParticleFrame) -> None:
    """Binary little-endian PLY with x y z (and vx vy vz)."""
    n = len(frame.positions)
    names = ["x", "y", "z"] + (["vx", "vy", "vz"] if frame.velocities is not None else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {c}" for c in names] + ["end_header"]
    cols = [frame.positions] + ([frame.velocities] if frame.velocities is not None else [])
    body = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4").tobytes()
    Path(path).write_bytes(("\n".join(header) + "\n").encode() + body)
