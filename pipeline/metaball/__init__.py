"""The metaball system of Horvath 2019 ("Image-Space Metaballs Using Deep Learning", master's thesis,
TU Wien): ray-marched target G-buffers of a metaball field, the cheap circle image the network
sees, and the paper's encodings of both (host side; the kernels are in ``kernels``, the pix2pix
networks and losses in ``networks``).

Arrays follow ``pipeline.camera``: view depth is positive along -Z (0 = empty), normals are unit
view-space vectors (n_z > 0 facing the camera), pixel (col i, row j) has its centre at
(i + 0.5, j + 0.5) with row 0 at the top. Lengths (positions, radii, depths, the march step) are in
scene units, the thesis' units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from pipeline.camera import Camera
from pipeline.metaball import kernels as K
from pipeline.parallel import Launcher
from pipeline.screen import row_bands
from pipeline.surface import WIDE_KERNEL_QUANTILE, hash_grid
from pipeline.vectors import box_mean, length

_EMPTY = 1.0e30
_NO_OWNER = 2**31 - 1

PAPER_FOV_Y_DEG = 60.0
"""Vertical field of view of the thesis' targets. Its shader's 'FOV 30' is used as tan(30 deg) at the
image edge (``(uv - 0.5) * 2 * tan(fov)``), so the full angle is 60 degrees."""

TARGET_CHANNELS = ("R", "G", "B", "Z", "N.X", "N.Y", "N.Z")
"""The 7 channels of ``encode_targets`` and of the generator's output, in order."""

INPUT_CHANNELS = ("R", "G", "B", "Z")
"""The 4 channels of ``circle_input`` (the thesis' generator input), in order."""

SPHERE_CHANNELS = ("A", "N.X", "N.Y", "N.Z", "relief", "behind", "thickness")
"""The 7 channels of ``sphere_input`` (the default generator input), in order."""

RELIEF_WINDOW_RADII = 6.0
"""Half width (projected ball radii) of the window the relief compares the front depth with."""
RELIEF_SCALE_RADII = 4.0
"""Relief of this many ball radii maps to tanh(1)."""
LAYER_SPAN_RADII = 8.0
"""Gaps and thicknesses are coded over this many ball radii (twice the field's cut-off): beyond it
a ball behind cannot shape the front surface."""


@dataclass(frozen=True)
class MetaballParams:
    """Field, march and input-drawing parameters of the metaball system (defaults: the thesis' values
    where it has one; the cut-off, the bisections and the narrowest outline are ours)."""

    iso_level: float = 1.0
    """Iso-level c of the surface f(X) = c (dimensionless); an isolated ball's surface has radius r / sqrt(c)."""
    kernel_radius_radii: float = 4.0
    """Where each ball's term r^2 / d^2 reaches zero, in that ball's radii; it is tapered smoothly from half of
    that. 0: the thesis' infinite support (every ball at every sample, cost grows with the ball count)."""
    depth_near: float = 7.0
    """Nearest view depth marched and the depth that encodes as 0 (scene units)."""
    depth_far: float = 25.0
    """Farthest view depth marched and the depth that encodes as 1 (scene units)."""
    step: float = 0.01
    """Ray-march step in view depth (scene units): the thesis' fixed step, and the smallest one with
    ``adaptive_step``."""
    adaptive_step: bool = True
    """Skip empty space: step by the distance within which the field provably stays below the
    iso-level when that is longer than ``step`` (the same surfaces, far fewer samples)."""
    bisections: int = 8
    """Halvings of the step that holds the first crossing: depth error at most step / 2^(bisections + 1)."""
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Colour (linear RGB in [0, 1]) of every ball when no per-ball colours are given."""
    outline_width: float = 0.05
    """Width of a ball's outline in the circle input, a share of its quad's side (twice the circle radius)."""
    outline_min_px: float = 1.0
    """Narrowest outline (pixels), so that circles under ten pixels in radius still show; 0 for the thesis'."""

    def __post_init__(self):
        checks = {"iso_level": self.iso_level > 0, "kernel_radius_radii": self.kernel_radius_radii >= 0,
                  "depth_near": 0 < self.depth_near < self.depth_far, "step": self.step > 0,
                  "bisections": self.bisections >= 0, "outline_width": 0 < self.outline_width <= 0.5,
                  "outline_min_px": self.outline_min_px >= 0}
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"metaball parameters out of range: {', '.join(f'{b}={getattr(self, b)!r}' for b in bad)}")
        if self.kernel_radius_radii and self.kernel_radius_radii <= 2.0 / math.sqrt(self.iso_level):
            raise ValueError(f"kernel_radius_radii={self.kernel_radius_radii} tapers inside an isolated ball's surface "
                             f"(radius 1/sqrt(iso_level) radii): use more than {2.0 / math.sqrt(self.iso_level):.3g}")


def paper_camera(width: int = 512, height: int = 512) -> Camera:
    """The thesis' camera: at the origin looking down -Z (its +Z, mirrored into our convention) with a
    60 degree vertical field of view; balls go in front of it at view depths 7 to 25."""
    return Camera(np.eye(4), PAPER_FOV_Y_DEG, width, height)


def minimal_radius(radii: np.ndarray, iso_level: float) -> np.ndarray:
    """Radius r / sqrt(iso) of each ball's surface in isolation: the smallest it can be, since other
    balls only add to the field."""
    return np.asarray(radii, np.float64) / math.sqrt(iso_level)


def _balls(positions: np.ndarray, radii, colours: np.ndarray | None,
           p: MetaballParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked float64 positions (N x 3), radii (N) and float32 colours (N x 3)."""
    pos = np.asarray(positions, np.float64).reshape(-1, 3) if np.size(positions) else np.zeros((0, 3))
    n = len(pos)
    rad = np.broadcast_to(np.asarray(radii, np.float64), (n,)).copy()
    if n and not (np.isfinite(pos).all() and np.isfinite(rad).all() and (rad > 0).all()):
        raise ValueError("metaballs need finite positions and positive finite radii")
    if colours is None:
        col = np.broadcast_to(np.asarray(p.colour, np.float32), (n, 3))
    else:
        col = np.asarray(colours, np.float32)
        if col.shape != (n, 3):
            raise ValueError(f"colours must be N x 3 for {n} balls, got shape {col.shape}")
    return pos, rad, np.ascontiguousarray(col, np.float32)


def ellipsoid_maps(shapes: np.ndarray | None, radii: np.ndarray, keep: np.ndarray | None = None,
                   rotation: np.ndarray | None = None,
                   bounds: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray]:
    """Checked ellipsoid maps (N x 3 x 3, float64; ``keep``'s rows, turned into a frame whose
    coordinates are ``rotation`` times the world's) and the radius that bounds each ball: its
    largest semi-axis 1 / sigma_min(A) (``bounds`` when the caller knows them: a turn leaves them
    be), or its radius without shapes."""
    if shapes is None:
        return None, radii
    a = np.asarray(shapes, np.float64).reshape(-1, 3, 3)
    if keep is not None:
        a = a[keep]
        bounds = bounds[keep] if bounds is not None else None
    if len(a) != len(radii) or not np.isfinite(a).all():
        raise ValueError(f"shapes must be finite N x 3 x 3 maps for {len(radii)} balls, got {np.shape(shapes)}")
    if rotation is not None:
        a = a @ np.asarray(rotation, np.float64).T
    if bounds is not None:
        return a, np.asarray(bounds, np.float64)
    smallest = np.linalg.eigvalsh(np.swapaxes(a, 1, 2) @ a)[:, 0] if len(a) else np.ones(0)
    if (smallest <= 0).any():
        raise ValueError("ellipsoid shapes must be invertible")
    return a, 1.0 / np.sqrt(smallest)


def _shape_array(shapes: np.ndarray | None, device: str) -> wp.array:
    """The kernels' ``shapes`` argument: the maps as mat33, or an empty array for spheres."""
    if shapes is None:
        return wp.zeros(0, dtype=wp.mat33, device=device)
    return wp.array(np.ascontiguousarray(shapes, np.float32), dtype=wp.mat33, device=device)


def _support_span(centres_view: np.ndarray, supports: np.ndarray, camera: Camera, p: MetaballParams,
                  launch: Launcher) -> tuple[wp.array, wp.array]:
    """Per pixel the view depths where its ray enters its first and leaves its last ball support
    (1e30 and 0 where it meets none). Without a cut-off, or where a support holds the camera (no
    splat can bound it), every ray spans the depth range."""
    w, h = camera.width, camera.height
    device = launch.device
    if len(supports) == 0 or np.any(-centres_view[:, 2] <= supports):
        return (wp.full(w * h, p.depth_near, dtype=float, device=device),
                wp.full(w * h, p.depth_far, dtype=float, device=device))
    t_in = wp.full(w * h, _EMPTY, dtype=float, device=device)
    t_out = wp.zeros(w * h, dtype=float, device=device)
    args = [wp.array(centres_view.astype(np.float32), dtype=wp.vec3, device=device),
            wp.array(supports.astype(np.float32), dtype=float, device=device), camera.focal_px, w, h]
    launch.tasks(K.splat_supports, len(centres_view),
                 [[*args, r0, r1, t_in, t_out] for r0, r1 in row_bands(launch, h)])
    return t_in, t_out


def metaball_targets(positions: np.ndarray, radii, camera: Camera, params: MetaballParams, launch: Launcher,
                     colours: np.ndarray | None = None, shapes: np.ndarray | None = None,
                     bounds: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Ray-march the metaball surface f = iso of balls at world ``positions`` (N x 3) with ``radii``
    (N, or one for all) and ``colours`` (N x 3, default ``params.colour``) for one view. With
    ``shapes`` (N x 3 x 3 world maps A_i) the balls are ellipsoids, terms 1 / |A_i (X - P_i)|^2, of
    largest semi-axes ``bounds`` (computed from the maps when not given).

    Returns ``depth`` (H x W view depth, 0 where empty), ``normals`` (H x W x 3 view-space unit
    normals, -grad f, 0 where empty), ``colour`` (H x W x 3, the field-weighted blend of the ball
    colours, 0 where empty) and ``mask`` (H x W, 1 on the surface). Only surfaces between
    ``depth_near`` and ``depth_far`` are seen."""
    p = params
    device = launch.device
    w, h = camera.width, camera.height
    pos, rad, col = _balls(positions, radii, colours, p)
    out = {"depth": np.zeros((h, w), np.float32), "normals": np.zeros((h, w, 3), np.float32),
           "colour": np.zeros((h, w, 3), np.float32), "mask": np.zeros((h, w), np.float32)}
    if len(pos) == 0:
        return out
    shapes, rad = ellipsoid_maps(shapes, rad, bounds=bounds)
    k = p.kernel_radius_radii
    supports = k * rad if k > 0 else np.zeros(0)  # none: every ray is marched over the depth range
    reach = float(supports.max()) if k > 0 else 0.0
    t_entry, t_exit = _support_span(camera.to_view(pos), supports, camera, p, launch)
    centres = wp.array(pos.astype(np.float32), dtype=wp.vec3, device=device)
    grid = hash_grid(centres, pos, reach, device) if k > 0 else None
    arrays = {name: wp.zeros(w * h, dtype=dtype, device=device)
              for name, dtype in (("depth", float), ("normals", wp.vec3), ("colour", wp.vec3), ("mask", float))}
    rot = camera.cam_to_world[:3, :3].astype(np.float32)
    balls = [grid.id if grid is not None else wp.uint64(0), centres,
             wp.array(rad.astype(np.float32), dtype=float, device=device), _shape_array(shapes, device),
             wp.array(col, dtype=wp.vec3, device=device)]
    view = [wp.vec3(*camera.eye.astype(np.float32)), wp.mat33(*rot.ravel()), w, h, camera.focal_px]
    launch(K.march_metaballs, w * h, [*balls, float(k), reach, p.iso_level, *view, t_entry, t_exit, p.depth_near,
                                      p.depth_far, p.step, int(p.adaptive_step), p.bisections,
                                      *arrays.values()])
    for name, a in arrays.items():
        out[name] = a.numpy().reshape(out[name].shape)
    return out


def circle_input(positions: np.ndarray, radii, camera: Camera, params: MetaballParams, launch: Launcher,
                 colours: np.ndarray | None = None) -> np.ndarray:
    """The thesis' network input for one view (4 x H x W float32: R, G, B and the depth code).

    Each ball in front of the camera is a circle outline centred on its projection, of radius
    focal x minimal radius / centre depth (its camera-facing quad's half side) and width
    ``outline_width`` of the quad's side (at least ``outline_min_px``), drawn in its colour with
    its centre's depth code (d - near) / (far - near), clamped to [0, 1]. Where outlines overlap
    the ball with the nearest centre wins (the lower index on a tie); the background is 0."""
    p = params
    device = launch.device
    w, h = camera.width, camera.height
    pos, rad, col = _balls(positions, radii, colours, p)
    n = len(pos)
    if n == 0:
        return np.zeros((4, h, w), np.float32)
    view = camera.to_view(pos)
    depth = -view[:, 2]
    front = depth > 0
    safe = np.where(front, depth, 1.0)
    f = camera.focal_px
    cx, cy = w / 2.0 + f * view[:, 0] / safe, h / 2.0 - f * view[:, 1] / safe
    outer = np.where(front, f * minimal_radius(rad, p.iso_level) / safe, 0.0)
    ring = np.maximum(2.0 * p.outline_width * outer, p.outline_min_px)
    inner = np.maximum(outer - ring, 0.0)
    circles = np.stack([cx, cy, outer, inner], axis=1)
    code = np.clip((depth - p.depth_near) / (p.depth_far - p.depth_near), 0.0, 1.0)
    depth_buf = wp.full(w * h, _EMPTY, dtype=float, device=device)
    owner = wp.full(w * h, _NO_OWNER, dtype=int, device=device)
    args = [wp.array(circles.astype(np.float32), dtype=wp.vec4, device=device),
            wp.array(depth.astype(np.float32), dtype=float, device=device), w]
    bands = row_bands(launch, h)
    for owner_pass in (0, 1):
        launch.tasks(K.draw_outlines, n, [[*args, r0, r1, owner_pass, depth_buf, owner] for r0, r1 in bands])
    image = wp.zeros(4 * w * h, dtype=float, device=device)
    launch(K.finish_outlines, w * h, [owner, wp.array(col, dtype=wp.vec3, device=device),
                                      wp.array(code.astype(np.float32), dtype=float, device=device), n, w * h, image])
    return image.numpy().reshape(4, h, w)


def sphere_layers(positions: np.ndarray, radii, camera: Camera, params: MetaballParams, launch: Launcher,
                  splat_radius: float = 1.0, field_steps: int | None = None, shapes: np.ndarray | None = None,
                  bounds: np.ndarray | None = None) -> dict[str, np.ndarray | float]:
    """The balls as spheres of ``splat_radius`` times their minimal radius, splatted exactly (ray-sphere,
    two passes), for one view: per pixel the view depth where the ray enters its first sphere
    (``front``, 0 where none), the unit normal there (``normals``, H x W x 3: the sphere's own, or
    with ``field_steps`` the metaball field's after that many Newton steps towards its iso-surface,
    ``kernels.field_normals``), where the ray leaves its last sphere (``back``) and where it enters
    the nearest sphere more than a radius behind ``front`` (``behind``, 0 where none); ``r`` is the
    median sphere radius and ``r_px`` its median projection (pixels). ``shapes`` (world maps, as in
    ``metaball_targets``, with their ``bounds``) make the field's balls ellipsoids; the splat keeps
    spheres of ``radii``."""
    p = params
    device = launch.device
    w, h = camera.width, camera.height
    pos, rad, _ = _balls(positions, radii, None, p)
    view = camera.to_view(pos)
    r_min = splat_radius * minimal_radius(rad, p.iso_level)
    keep = -view[:, 2] > r_min  # spheres wholly in front of the camera
    view, r_min, rad = view[keep], r_min[keep], rad[keep]
    if field_steps is not None:
        shapes, bounds = ellipsoid_maps(shapes, rad, keep, camera.view[:3, :3], bounds)
    empty = {"front": np.zeros((h, w), np.float32), "back": np.zeros((h, w), np.float32),
             "behind": np.zeros((h, w), np.float32), "normals": np.zeros((h, w, 3), np.float32),
             "r": 1.0, "r_px": 1.0}
    if len(view) == 0:
        return empty
    r = float(np.median(r_min))
    t_in, t_out = _support_span(view, r_min, camera, p, launch)
    t_behind = wp.full(w * h, _EMPTY, dtype=float, device=device)
    normals = wp.zeros(w * h, dtype=wp.vec3, device=device)
    args = [wp.array(view.astype(np.float32), dtype=wp.vec3, device=device),
            wp.array(r_min.astype(np.float32), dtype=float, device=device), camera.focal_px, w, h]
    bands = row_bands(launch, h)
    launch.tasks(K.splat_behind_and_normals, len(view),
                 [[*args, r0, r1, r, t_in, t_behind, normals] for r0, r1 in bands])
    if field_steps is not None:
        field_normals(view, rad, camera, p, launch, t_in, field_steps, normals, shapes, bounds)
    front, back, behind = (a.numpy().reshape(h, w) for a in (t_in, t_out, t_behind))
    covered = front < 0.5 * _EMPTY
    return {"front": np.where(covered, front, 0.0).astype(np.float32),
            "back": np.where(covered, back, 0.0).astype(np.float32),
            "behind": np.where(behind < 0.5 * _EMPTY, behind, 0.0).astype(np.float32),
            "normals": normals.numpy().reshape(h, w, 3), "r": r,
            "r_px": float(np.median(camera.focal_px * r_min / -view[:, 2]))}


def field_normals(view: np.ndarray, radii: np.ndarray, camera: Camera, params: MetaballParams,
                  launch: Launcher, t_front: wp.array, steps: int, normals: wp.array,
                  shapes: np.ndarray | None = None, bounds: np.ndarray | None = None) -> None:
    """Overwrite ``normals`` (H x W, view space) with the metaball field's where the rays enter their
    front sphere at ``t_front`` (``kernels.field_normals``, Newton steps of at most a ball radius) for
    balls at view-space centres ``view`` with ``radii`` (and view-space ellipsoid ``shapes`` of
    largest semi-axes ``bounds``, as ``ellipsoid_maps`` returns them; without bounds they are
    computed). Needs the field's cut-off (hash grids)."""
    k = params.kernel_radius_radii
    if k <= 0:
        raise ValueError("field normals need a kernel radius (metaball.kernel_radius_radii > 0)")
    device = launch.device
    if bounds is None:
        shapes, bounds = ellipsoid_maps(shapes, radii)
    # The few widest balls get a grid of their own: one grid must be queried with the largest reach
    # of all, which on a splash frame is 1.5x the 99th percentile's and visits 3x the candidates.
    wide = bounds > np.quantile(bounds, WIDE_KERNEL_QUANTILE)
    order = np.concatenate([np.flatnonzero(~wide), np.flatnonzero(wide)])
    start = int((~wide).sum())
    pos = np.ascontiguousarray(view[order], np.float32)
    centres = wp.array(pos, dtype=wp.vec3, device=device)
    narrow_reach = float(k * bounds[~wide].max())
    narrow = hash_grid(centres[:start], pos[:start], narrow_reach, device)
    wide_reach, wide_grid = -1.0, narrow
    if wide.any():
        wide_reach = float(k * bounds[wide].max())
        wide_grid = hash_grid(centres[start:], pos[start:], wide_reach, device)
    launch(K.field_normals, camera.width * camera.height,
           [narrow.id, narrow_reach, wide_grid.id, wide_reach, start, centres,
            wp.array(bounds[order].astype(np.float32), dtype=float, device=device),
            _shape_array(None if shapes is None else shapes[order], device), float(k), params.iso_level,
            camera.width, camera.height, camera.focal_px, t_front, int(steps), float(np.median(radii)), normals])


def sphere_input(layers: dict) -> np.ndarray:
    """The default network input (7 x H x W float32 in [0, 1], ``SPHERE_CHANNELS``) of a view's
    ``sphere_layers``:

    0. ``A``: 1 where a sphere covers the pixel;
    1-3. ``N``: the front sphere's normal as (n + 1) / 2: the surface's orientation, which the blend
       smooths (the refiner's input, here exact);
    4. ``relief``: tanh of the front depth minus its mean over a window of +-6 projected radii, in
       units of 4 ball radii (mapped to [0, 1]): which parts stand in front of their neighbourhood,
       scale-free (absolute depth never enters);
    5. ``behind``: 1 - gap / 8 radii, the gap from the front entry to the nearest sphere entered more
       than one radius behind it (0 where none is within 8 radii): a second layer that still shapes
       the surface, and where it stops doing so (the thesis' named failure: balls at different
       depths blended);
    6. ``thickness``: how far the ray runs from the first entry to the last exit, over 8 radii.
    All 0 outside the spheres."""
    d, r = layers["front"], float(layers["r"])
    covered = d > 0
    m = covered.astype(np.float32)
    size = 2 * max(1, round(RELIEF_WINDOW_RADII * float(layers["r_px"]))) + 1
    local = box_mean(d, size) / np.maximum(box_mean(m, size), 1e-6)
    span = LAYER_SPAN_RADII * r
    behind = layers["behind"]
    channels = [m[None], 0.5 * (np.moveaxis(layers["normals"], -1, 0) + 1.0),
                (0.5 * (np.tanh((d - local) / (RELIEF_SCALE_RADII * r)) + 1.0))[None],
                np.where(behind > 0, np.clip(1.0 - (behind - d) / span, 0.0, 1.0), 0.0)[None],
                np.clip((layers["back"] - d) / span, 0.0, 1.0)[None]]
    return np.where(covered, np.concatenate(channels), 0.0).astype(np.float32)


def encode_targets(targets: dict[str, np.ndarray], params: MetaballParams) -> np.ndarray:
    """The thesis' 7 x H x W target buffers in [0, 1] (``TARGET_CHANNELS``): colour, the depth code
    (d - near) / (far - near) (1 where empty, as its shader's miss depth clamps to white) and the
    normal as (n + 1) / 2 (0 where empty). The network sees 2 x - 1 of these."""
    p = params
    mask = targets["mask"] > 0
    code = np.clip((targets["depth"] - p.depth_near) / (p.depth_far - p.depth_near), 0.0, 1.0)
    code = np.where(mask, code, 1.0)
    normal = np.where(mask[..., None], 0.5 * (targets["normals"] + 1.0), 0.0)
    colour = np.where(mask[..., None], targets["colour"], 0.0)
    return np.concatenate([colour.transpose(2, 0, 1), code[None], normal.transpose(2, 0, 1)]).astype(np.float32)


def decode_gbuffers(encoded: np.ndarray, params: MetaballParams, min_encoded_normal: float = 0.25) -> dict:
    """``encode_targets``' inverse for 7 x H x W buffers in [0, 1] (a generator's tanh output y maps
    to (y + 1) / 2 first): ``colour``, ``depth``, ``normals`` (renormalised) and ``mask``.

    A pixel is surface where its encoded normal is longer than ``min_encoded_normal``: empty pixels
    encode as 0, and a unit normal facing the camera (n_z >= 0) encodes longer than 0.54."""
    p = params
    e = np.asarray(encoded, np.float32)
    enc_n = e[4:7].transpose(1, 2, 0)
    mask = length(enc_n) > min_encoded_normal
    n = 2.0 * enc_n - 1.0
    n /= np.maximum(length(n), 1e-12)[..., None]
    depth = p.depth_near + e[3] * (p.depth_far - p.depth_near)
    return {"colour": np.where(mask[..., None], e[0:3].transpose(1, 2, 0), 0.0).astype(np.float32),
            "depth": np.where(mask, depth, 0.0).astype(np.float32),
            "normals": np.where(mask[..., None], n, 0.0).astype(np.float32), "mask": mask.astype(np.float32)}


def input_names(kind: str) -> list[str]:
    """EXR channel names of a network input kind ('circles' or 'spheres')."""
    return [f"{kind}.{c}" for c in (INPUT_CHANNELS if kind == "circles" else SPHERE_CHANNELS)]


def view_channels(targets: dict[str, np.ndarray], inputs: np.ndarray, kind: str = "circles") -> dict[str, np.ndarray]:
    """EXR channels of one view (for ``pipeline.exr.write_exr``): the input as ``input_names(kind)``
    (``circles.R``, ``.G``, ``.B``, ``.Z``, or ``spheres.A``, ``.relief``, ``.behind``, ``.thickness``)
    and the targets as ``metaball.R``, ``.G``, ``.B``, ``metaball.Z`` (view depth), ``metaball.N.X``,
    ``.Y``, ``.Z`` and ``metaball.A`` (mask)."""
    out = dict(zip(input_names(kind), inputs, strict=True))
    out.update({f"metaball.{c}": targets["colour"][..., k] for k, c in enumerate("RGB")})
    out["metaball.Z"] = targets["depth"]
    out.update({f"metaball.N.{c}": targets["normals"][..., k] for k, c in enumerate("XYZ")})
    out["metaball.A"] = targets["mask"]
    return out
