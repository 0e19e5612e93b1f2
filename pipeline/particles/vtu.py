"""VTK XML unstructured grids (``.vtu``: ASCII, base64 or raw appended data, optionally compressed),
read with meshio. Velocities and radii are picked by name from the point data.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pipeline.particles.frame import ParticleFormatError, ParticleFrame, frame_from_point_data


def read(path: Path) -> ParticleFrame:
    """Read points and point data."""
    import meshio

    raw = Path(path).read_bytes()
    if not raw.rstrip().endswith(b"</VTKFile>"):  # meshio reports a cut file as an empty ReadError
        raise ParticleFormatError(f"{path}: truncated or not a VTU file: it does not end with </VTKFile>")
    if set(re.findall(rb'NumberOfPoints="(\d+)"', raw)) == {b"0"}:  # meshio fails on these
        return ParticleFrame(np.zeros((0, 3), np.float32))
    try:
        mesh = meshio.vtu.read(str(path))
    except meshio.ReadError as exc:
        raise ParticleFormatError(f"{path}: not a readable VTU file (meshio: {exc or 'ReadError'})") from exc
    return frame_from_point_data(mesh.points, mesh.point_data)
