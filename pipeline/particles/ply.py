"""PLY point clouds (ascii, binary little- or big-endian; header lines ending in LF or CRLF).

Reads the ``vertex`` element, which must come first: x y z, and its other scalar properties as point
attributes, where ``<name>x <name>y <name>z`` or ``<name>_x <name>_y <name>_z`` form a 3-vector named
``<name>`` (so ``vx vy vz`` are the velocity ``v``). Later elements (faces, edges) are ignored.

This own reader is kept instead of meshio's: meshio's never returns on a header cut before
``end_header`` and returns too few vertices from a cut body without an error.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pipeline.particles.frame import ParticleFormatError, ParticleFrame, frame_from_point_data

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_END_HEADER = re.compile(rb"end_header[ \t]*\r?\n")


def _group_vectors(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Scalar columns plus 3-vectors from ``<name>x/y/z`` or ``<name>_x/_y/_z`` triplets."""
    out = dict(columns)
    for name in columns:
        stem = name[:-2] if name.endswith("_x") else name[:-1] if name.endswith("x") else ""
        triplet = [name[:-1] + axis for axis in "xyz"]  # vx vy vz, or velocity_x velocity_y velocity_z
        if stem and all(c in columns for c in triplet):
            out.setdefault(stem, np.stack([columns[c] for c in triplet], axis=1))
    return out


def read(path: Path) -> ParticleFrame:
    """Read vertex positions and point attributes."""
    raw = Path(path).read_bytes()
    end = _END_HEADER.search(raw)
    if not raw.startswith(b"ply") or end is None:
        raise ParticleFormatError(f"{path}: not a PLY file or header incomplete (no end_header line)")
    header = raw[:end.start()].decode("ascii", "replace").splitlines()
    body = raw[end.end():]
    fmt, elements = None, []
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ParticleFormatError(f"{path}: element line needs a name and a count of 0 or more: {line!r}")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ParticleFormatError(f"{path}: property line before any element: {line!r}")
            if parts[1] == "list":
                if len(elements) == 1:
                    raise ParticleFormatError(f"{path}: list properties in the vertex element are not supported")
                continue
            if parts[1] not in _PLY_TYPES:
                raise ParticleFormatError(f"{path}: unknown PLY property type {parts[1]!r}")
            elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise ParticleFormatError(f"{path}: unknown PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise ParticleFormatError(f"{path}: the first element must be 'vertex'")
    _, count, props = elements[0]
    names = [p[0] for p in props]
    if fmt == "ascii":
        tokens = body.split(maxsplit=count * len(props))[: count * len(props)]
        if len(tokens) < count * len(props):
            raise ParticleFormatError(f"{path}: truncated: {count} vertices of {len(props)} values declared, "
                                      f"{len(tokens)} values found")
        table = np.array(tokens, dtype=np.float64).reshape(count, len(props))
        columns = {n: table[:, i] for i, n in enumerate(names)}
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(body) < count * dtype.itemsize:
            raise ParticleFormatError(f"{path}: truncated: {count} vertices need {count * dtype.itemsize} "
                                      f"bytes, {len(body)} present")
        rec = np.frombuffer(body, dtype=dtype, count=count)
        columns = {n: rec[n] for n in names}
    if not {"x", "y", "z"} <= set(columns):
        raise ParticleFormatError(f"{path}: vertex element lacks x, y, z")
    positions = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
    return frame_from_point_data(positions, _group_vectors(columns))


def write(path: Path, frame: ParticleFrame) -> None:
    """Binary little-endian PLY with x y z (and vx vy vz, radius)."""
    n = len(frame.positions)
    names, cols = ["x", "y", "z"], [frame.positions]
    if frame.velocities is not None:
        names, cols = names + ["vx", "vy", "vz"], cols + [frame.velocities]
    if frame.radii is not None:
        names, cols = names + ["radius"], cols + [frame.radii.reshape(-1, 1)]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property float {c}" for c in names] + ["end_header"]
    body = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4").tobytes()
    Path(path).write_bytes(("\n".join(header) + "\n").encode() + body)
