"""Legacy VTK files (``# vtk DataFile``, versions 3.0 to 5.1), ASCII or BINARY (big-endian), as
SPlisHSPlasH (4.x) and meshio (4.2, and 5.1 whose CELLS come as OFFSETS and CONNECTIVITY arrays) write them.

Reads POINTS and the POINT_DATA arrays (SCALARS, VECTORS, NORMALS or FIELD), from which velocities and
radii are picked by name; skips cells, CELL_DATA and other sections by their declared sizes, so a file
cut short is reported as truncated. Writes an UNSTRUCTURED_GRID of vertex cells so ParaView shows the
points.

This own reader is kept instead of meshio's: on damaged files meshio mostly raises an empty ``ReadError``
(or a ``KeyError``), and drops point arrays silently more often.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.particles.frame import ParticleFormatError, ParticleFrame, frame_from_point_data

_VTK_TYPES = {"float": "f4", "double": "f8", "int": "i4", "unsigned_int": "u4", "short": "i2",
              "unsigned_short": "u2", "char": "i1", "unsigned_char": "u1", "long": "i8",
              "unsigned_long": "u8", "vtktypeint64": "i8", "vtktypeuint64": "u8"}


class _Reader:
    def __init__(self, path: Path, data: bytes):
        self.path, self.data, self.pos = path, data, 0
        self.binary, self.last = False, ""

    def line(self) -> str | None:
        while self.pos < len(self.data):
            end = self.data.find(b"\n", self.pos)
            end = len(self.data) if end < 0 else end
            text = self.data[self.pos:end].decode("ascii", "replace").strip()
            self.pos = end + 1
            if text:
                self.last = text
                return text
        return None

    def values(self, count: int, vtk_type: str) -> np.ndarray:
        t = _VTK_TYPES.get(vtk_type.lower())
        if t is None:
            raise ParticleFormatError(f"{self.path}: unsupported VTK data type {vtk_type!r}")
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
    """Read positions, and velocities and radii from the point data."""
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
    try:
        positions, point_data = _read_sections(r, version)
    except ParticleFormatError:
        raise
    except (IndexError, ValueError):  # a section line cut short, or a count that is not a number
        where = "truncated: the file ends in" if r.pos >= len(r.data) else "malformed"
        raise ParticleFormatError(f"{path}: {where} section line {r.last!r}") from None
    if positions is None:
        raise ParticleFormatError(f"{path}: no POINTS section")
    return frame_from_point_data(positions, point_data)


def _read_sections(r: _Reader, version: float) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    """Positions and point data arrays from the sections after the header."""
    path = r.path
    positions, n_points = None, 0
    point_data: dict[str, np.ndarray] = {}
    section, n_values = "", 0  # the current data section (POINT_DATA or CELL_DATA) and its tuple count
    seen: list[str] = []  # section keys in file order

    def keep(name: str, values: np.ndarray, ncomp: int) -> None:
        if section == "POINT_DATA":
            point_data[name] = values.reshape(n_values, ncomp)

    while (text := r.line()) is not None:
        key, *args = text.split()
        key = key.upper()
        seen.append(key)
        if key == "DATASET":
            continue
        if key == "POINTS":
            n_points = int(args[0])
            positions = r.values(3 * n_points, args[1]).reshape(-1, 3)
        elif key in ("CELLS", "POLYGONS", "VERTICES", "LINES", "TRIANGLE_STRIPS") and version >= 5:
            # 5.x: "CELLS <offsets> <connectivity>", then OFFSETS and CONNECTIVITY arrays
            for expected, count in (("OFFSETS", int(args[0])), ("CONNECTIVITY", int(args[1]))):
                head = (r.line() or "").split()
                if len(head) != 2 or head[0].upper() != expected:
                    raise ParticleFormatError(f"{path}: VTK {version:g} {key} lacks its {expected} array")
                r.values(count, head[1])
        elif key in ("CELLS", "POLYGONS", "VERTICES", "LINES", "TRIANGLE_STRIPS"):
            r.values(int(args[1]), "int")
        elif key == "CELL_TYPES":
            r.values(int(args[0]), "int")
        elif key in ("POINT_DATA", "CELL_DATA"):
            section, n_values = key, int(args[0])
            if key == "POINT_DATA" and n_values != n_points:
                raise ParticleFormatError(f"{path}: POINT_DATA declares {n_values} values for {n_points} points")
        elif key == "SCALARS":
            ncomp = int(args[2]) if len(args) > 2 else 1
            if not (r.line() or "").upper().startswith("LOOKUP_TABLE"):
                raise ParticleFormatError(f"{path}: SCALARS {args[0]} lacks LOOKUP_TABLE")
            keep(args[0], r.values(n_values * ncomp, args[1]), ncomp)
        elif key in ("VECTORS", "NORMALS"):
            keep(args[0], r.values(3 * n_values, args[1]), 3)
        elif key == "TEXTURE_COORDINATES":
            r.values(int(args[1]) * n_values, args[2])
        elif key == "TENSORS":
            r.values(9 * n_values, args[1])
        elif key == "COLOR_SCALARS":  # bytes when binary, floats in [0, 1] when ASCII
            r.values(int(args[1]) * n_values, "unsigned_char" if r.binary else "float")
        elif key == "LOOKUP_TABLE":
            r.values(4 * int(args[1]), "unsigned_char" if r.binary else "float")
        elif key == "FIELD":
            for _ in range(int(args[1])):
                head = (r.line() or "").split()
                if len(head) < 4:
                    raise ParticleFormatError(f"{path}: truncated FIELD array header")
                name, ncomp, ntup, vtype = head[0], int(head[1]), int(head[2]), head[3]
                values = r.values(ncomp * ntup, vtype)
                if ntup == n_values:
                    keep(name, values, ncomp)
        elif key == "METADATA":
            while (text := r.line()) is not None and text:
                if text.upper().startswith("INFORMATION") or text.upper().startswith("COMPONENT"):
                    continue
                r.pos -= len(text) + 1
                break
        else:
            raise ParticleFormatError(f"{path}: unexpected section {key!r} at byte {r.pos}")
    if "CELLS" in seen and "CELL_TYPES" not in seen:
        raise ParticleFormatError(f"{path}: truncated: the file ends after CELLS, before CELL_TYPES")
    if seen and seen[-1] in ("POINT_DATA", "CELL_DATA"):
        raise ParticleFormatError(f"{path}: truncated: the file ends after {seen[-1]}, before its arrays")
    return positions, point_data


def write(path: Path, frame: ParticleFrame) -> None:
    """Binary legacy VTK unstructured grid of vertex cells, with ``velocity`` and ``radius`` point arrays."""
    n = len(frame.positions)
    out = [b"# vtk DataFile Version 3.0\ndeep-ssfr particles\nBINARY\nDATASET UNSTRUCTURED_GRID\n",
           f"POINTS {n} float\n".encode(), np.ascontiguousarray(frame.positions, ">f4").tobytes(), b"\n",
           f"CELLS {n} {2 * n}\n".encode()]
    cells = np.stack([np.ones(n, np.int64), np.arange(n)], axis=1).astype(">i4")
    out += [cells.tobytes(), b"\n", f"CELL_TYPES {n}\n".encode(), np.ones(n, ">i4").tobytes(), b"\n"]
    if frame.velocities is not None or frame.radii is not None:
        out.append(f"POINT_DATA {n}\n".encode())
    if frame.velocities is not None:
        out += [b"VECTORS velocity float\n", np.ascontiguousarray(frame.velocities, ">f4").tobytes(), b"\n"]
    if frame.radii is not None:
        out += [b"SCALARS radius float 1\nLOOKUP_TABLE default\n",
                np.ascontiguousarray(frame.radii, ">f4").tobytes(), b"\n"]
    Path(path).write_bytes(b"".join(out))
