"""Legacy VTK files (``# vtk DataFile``, versions 3.0 to 5.1), ASCII or BINARY (big-endian), as
SPlisHSPlasH (4.2) and meshio (5.1, whose CELLS come as OFFSETS and CONNECTIVITY arrays) write them.

Reads POINTS and a 3-component point array named ``velocity``/``v`` (SCALARS, VECTORS or FIELD);
skips CELLS, CELL_TYPES and other arrays by their declared sizes. Writes an UNSTRUCTURED_GRID of
vertex cells so ParaView shows the points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.particles import ParticleFormatError, ParticleFrame

_VTK_TYPES = {"float": "f4", "double": "f8", "int": "i4", "unsigned_int": "u4", "short": "i2",
              "unsigned_short": "u2", "char": "i1", "unsigned_char": "u1", "long": "i8",
              "unsigned_long": "u8", "vtktypeint64": "i8", "vtktypeuint64": "u8"}


class _Reader:
    def __init__(self, path: Path, data: bytes):
        self.path, self.data, self.pos = path, data, 0
        self.binary = False

    def line(self) -> str | None:
        while self.pos < len(self.data):
            end = self.data.find(b"\n", self.pos)
            end = len(self.data) if end < 0 else end
            text = self.data[self.pos:end].decode("ascii", "replace").strip()
            self.pos = end + 1
            if text:
                return text
        return None

    def values(self, count: int, vtk_type: str) -> np.ndarray:
        if vtk_type not in _VTK_TYPES:
            raise ParticleFormatError(f"{self.path}: unsupported VTK data type {vtk_type!r}")
        t = _VTK_TYPES[vtk_type]
        if self.binary:
            nbytes = count * np.dtype(t).itemsize
            if self.pos + nbytes > len(self.data):
                raise ParticleFormatError(f"{self.path}: truncated: {count} {vtk_type} values need {nbytes} "
                                          f"bytes at offset {self.pos}, file has {len(self.data)}")
            out = np.frombuffer(self.data, dtype=">" + t, count=count, offset=self.pos)
            self.pos += nbytes
            return out
        vals: list[str] = []
        while len(vals) < count:
            text = self.line()
            if text is None:
                raise ParticleFormatError(f"{self.path}: truncated: expected {count} values, got {len(vals)}")
            vals.extend(text.split())
        return np.array(vals[:count], dtype=t)


def read(path: Path) -> ParticleFrame:
    """Read positions and velocities."""
    r = _Reader(path, Path(path).read_bytes())
    header = r.line() or ""
    if not header.startswith("# vtk DataFile"):
        raise ParticleFormatError(f"{path}: not a legacy VTK file")
    try:
        version = float(header.split("Version")[-1])
    except ValueError:
        version = 3.0
    if version >= 6:
        raise ParticleFormatError(f"{path}: legacy VTK version {version:g} is not supported (3.0 to 5.1)")
    r.line()  # title
    r.binary = (r.line() or "").upper() == "BINARY"
    positions, velocities, n_points = None, None, 0
    while (text := r.line()) is not None:
        key, *args = text.split()
        key = key.upper()
        if key == "DATASET":
            continue
        if key == "POINTS":
            n_points = int(args[0])
            positions = r.values(3 * n_points, args[1]).reshape(-1, 3).astype(np.float32)
        elif key in ("CELLS", "POLYGONS", "VERTICES", "LINES") and version >= 5:
            # 5.x: "CELLS <offsets> <connectivity>", then OFFSETS and CONNECTIVITY arrays
            for expected, count in (("OFFSETS", int(args[0])), ("CONNECTIVITY", int(args[1]))):
                head = (r.line() or "").split()
                if len(head) != 2 or head[0].upper() != expected:
                    raise ParticleFormatError(f"{path}: VTK {version:g} {key} lacks its {expected} array")
                r.values(count, head[1])
        elif key in ("CELLS", "POLYGONS", "VERTICES", "LINES"):
            r.values(int(args[1]), "int")
        elif key == "CELL_TYPES":
            r.values(int(args[0]), "int")
        elif key in ("POINT_DATA", "CELL_DATA"):
            continue
        elif key == "SCALARS":
            ncomp = int(args[2]) if len(args) > 2 else 1
            nxt = r.line() or ""
            if not nxt.upper().startswith("LOOKUP_TABLE"):
                raise ParticleFormatError(f"{path}: SCALARS {args[0]} lacks LOOKUP_TABLE")
            arr = r.values(n_points * ncomp, args[1])
            if args[0] in ("velocity", "v") and ncomp == 3:
                velocities = arr.reshape(-1, 3).astype(np.float32)
        elif key in ("VECTORS", "NORMALS"):
            arr = r.values(3 * n_points, args[1])
            if args[0] in ("velocity", "v"):
                velocities = arr.reshape(-1, 3).astype(np.float32)
        elif key == "FIELD":
            for _ in range(int(args[1])):
                head = (r.line() or "").split()
                if len(head) < 4:
                    raise ParticleFormatError(f"{path}: truncated FIELD array header")
                name, ncomp, ntup, vtype = head[0], int(head[1]), int(head[2]), head[3]
                arr = r.values(ncomp * ntup, vtype)
                if name in ("velocity", "v") and ncomp == 3:
                    velocities = arr.reshape(-1, 3).astype(np.float32)
        elif key == "METADATA":
            while (text := r.line()) is not None and text:
                if text.upper().startswith("INFORMATION") or text.upper().startswith("COMPONENT"):
                    continue
                r.pos -= len(text) + 1
                break
        else:
            raise ParticleFormatError(f"{path}: unexpected section {key!r} at byte {r.pos}")
    if positions is None:
        raise ParticleFormatError(f"{path}: no POINTS section")
    if velocities is not None and len(velocities) != len(positions):
        velocities = None
    return ParticleFrame(positions, velocities)


def write(path: Path, frame: ParticleFrame) -> None:
    """Binary legacy VTK unstructured grid of vertex cells, with a ``velocity`` vector array."""
    n = len(frame.positions)
    out = [b"# vtk DataFile Version 3.0\ndeep-ssfr particles\nBINARY\nDATASET UNSTRUCTURED_GRID\n",
           f"POINTS {n} float\n".encode(), np.ascontiguousarray(frame.positions, ">f4").tobytes(), b"\n",
           f"CELLS {n} {2 * n}\n".encode()]
    cells = np.stack([np.ones(n, np.int64), np.arange(n)], axis=1).astype(">i4")
    out += [cells.tobytes(), b"\n", f"CELL_TYPES {n}\n".encode(), np.ones(n, ">i4").tobytes(), b"\n"]
    if frame.velocities is not None:
        out += [f"POINT_DATA {n}\nVECTORS velocity float\n".encode(),
                np.ascontiguousarray(frame.velocities, ">f4").tobytes(), b"\n"]
    Path(path).write_bytes(b"".join(out))
