"""Particle files: one module per format, dispatched by extension.

Readers return ``ParticleFrame`` (positions float32 N x 3, velocities float32 N x 3 or None, radii
float32 N or None); a corrupt, truncated or empty file raises ``ParticleFormatError`` naming the file
and what is wrong. Formats: legacy VTK (own reader, versions 3.0 to 5.1, ASCII or binary), VTU (meshio),
PLY (own reader, LF or CRLF), BGEO v5 (own reader, plain or gzip, also ``.bgeo.gz``), XYZ (raw float32).

Point attributes are picked by name, case-insensitively: velocities from ``velocity``, ``v``, ``vel``
or ``velocities`` (3 components), radii from ``pscale`` (Houdini), ``radius`` or ``radii`` (1 component).

The pipeline is Y-up. ``read_particles(path, up="z")`` converts Z-up data by a right-handed rotation
of -90 degrees about x: (x, y, z) -> (x, z, -y), applied to positions and velocities (radii are
unchanged), so +z becomes +y and handedness is kept.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.particles.frame import ParticleFormatError, ParticleFrame

READ_FORMATS = (".vtk", ".vtu", ".bgeo", ".ply", ".xyz")
"""Extensions ``read_particles`` reads (keys of ``particle_format``)."""
UP_AXES = ("y", "z")


def particle_format(path: str | Path) -> str:
    """The format key of a particle file: its lower-case extension, ``.bgeo`` also for ``.bgeo.gz``."""
    name = Path(path).name.lower()
    return ".bgeo" if name.endswith(".bgeo.gz") else Path(name).suffix


Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""(x, y, z) -> (x, z, -y): the right-handed -90 degree rotation about x taking +z to +y, from Z-up
worlds (Blender, Houdini's Z-up scenes) to the pipeline's Y-up one; cameras use it too."""


def _z_up_to_y_up(vectors: np.ndarray) -> np.ndarray:
    """Rows of ``vectors`` rotated by ``Z_UP_TO_Y_UP`` (float32 kept)."""
    return (vectors @ Z_UP_TO_Y_UP.T).astype(vectors.dtype)


def _check(path: Path, frame: ParticleFrame) -> None:
    """Raise ``ParticleFormatError`` unless the frame holds finite, consistently shaped arrays."""
    x = frame.positions
    if x.ndim != 2 or x.shape[1] != 3:
        raise ParticleFormatError(f"{path}: positions have shape {x.shape}, expected N x 3")
    if len(x) == 0:
        raise ParticleFormatError(f"{path}: the file holds no particles")
    if not np.isfinite(x).all():
        raise ParticleFormatError(f"{path}: positions contain NaN or infinity")
    if frame.velocities is not None:
        if frame.velocities.shape != x.shape:
            raise ParticleFormatError(f"{path}: velocities have shape {frame.velocities.shape}, "
                                      f"expected {len(x)} x 3 like the positions")
        if not np.isfinite(frame.velocities).all():
            raise ParticleFormatError(f"{path}: velocities contain NaN or infinity")
    if frame.radii is not None:
        if frame.radii.shape != (len(x),):
            raise ParticleFormatError(f"{path}: radii have shape {frame.radii.shape}, expected ({len(x)},)")
        if not (np.isfinite(frame.radii).all() and (frame.radii >= 0).all()):
            raise ParticleFormatError(f"{path}: radii contain negative values, NaN or infinity")


def read_particles(path: str | Path, up: str = "y") -> ParticleFrame:
    """Read a frame from legacy VTK, VTU, BGEO, PLY or XYZ; ``up="z"`` converts Z-up data to Y-up."""
    from pipeline.particles import bgeo, ply, vtk, vtu, xyz

    if up not in UP_AXES:
        raise ValueError(f"up must be one of {', '.join(UP_AXES)}, got {up!r}")
    path = Path(path)
    readers = dict(zip(READ_FORMATS, (vtk.read, vtu.read, bgeo.read, ply.read, xyz.read), strict=True))
    reader = readers.get(particle_format(path))
    if reader is None:
        raise ParticleFormatError(f"{path}: unsupported particle format {path.suffix!r} "
                                  f"(supported: {', '.join(readers)}, .bgeo.gz)")
    if not path.is_file():
        raise ParticleFormatError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise ParticleFormatError(f"{path}: the file holds no particles (it is empty, 0 bytes)")
    try:
        frame = reader(path)
    except ParticleFormatError:
        raise
    except Exception as exc:  # any parse failure becomes a located, readable error
        raise ParticleFormatError(f"{path}: cannot read ({type(exc).__name__}: {exc})") from exc
    _check(path, frame)
    if up == "z":
        frame.positions = _z_up_to_y_up(frame.positions)
        if frame.velocities is not None:
            frame.velocities = _z_up_to_y_up(frame.velocities)
    return frame


def write_particles(path: str | Path, frame: ParticleFrame, fmt: str = "") -> None:
    """Write a frame as PLY, legacy VTK (binary) or XYZ, by ``fmt`` or else the extension."""
    from pipeline.particles import ply, vtk, xyz

    path = Path(path)
    writers = {"vtk": vtk.write, "ply": ply.write, "xyz": xyz.write}
    fmt = fmt or path.suffix.lower().lstrip(".")
    writer = writers.get(fmt)
    if writer is None:
        raise ValueError(f"{path}: cannot write {fmt!r} (supported: {', '.join(writers)})")
    writer(path, frame)
