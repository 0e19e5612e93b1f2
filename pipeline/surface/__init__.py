"""Surface targets: anisotropic-kernel density (Yu & Turk 2013), marching cubes, ray-cast maps.

``reconstruct`` turns particle positions into a triangle mesh with smooth vertex normals;
``render_maps`` ray-casts it from a camera into view-space normal, depth and mask maps.
``raytrace_maps`` skips the mesh: it marches each pixel's ray through the density itself to the
iso-level (Biedert et al. 2018), so the target has no grid facets at any resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp
from skimage import measure

from pipeline.camera import Camera
from pipeline.config import DatasetConfig
from pipeline.ellipsoids import Ellipsoids
from pipeline.parallel import Launcher
from pipeline.sph import POLY6_NORM, anisotropy_support, lattice_offsets, particle_volume, spacing
from pipeline.surface import kernels as K
from pipeline.surface import native as N
from pipeline.timing import Timings
from pipeline.vectors import bounds, length

if TYPE_CHECKING:
    from pipeline.screen import ScreenSpace


@dataclass
class SurfaceMesh:
    """A reconstructed surface (world space)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    timings: Timings = field(default_factory=Timings)

    def to_trimesh(self):
        """The mesh as a trimesh object (not re-processed)."""
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, vertex_normals=self.normals, process=False)


def full_neighbourhood_variance(step: float, support: float) -> float:
    """Mean eigenvalue of the weighted covariance of an interior lattice neighbourhood.

    Dividing by it makes a full neighbourhood map to kernel scale 1, which is what Yu & Turk's
    k_s = 1400 achieves in their units; here it holds in any unit.
    """
    p = lattice_offsets(step, support)
    d = np.linalg.norm(p, axis=1)
    keep = d < support
    w = 1.0 - (d[keep] / support) ** 3
    cov = (p[keep].T * w) @ p[keep] / w.sum()
    return float(np.trace(cov) / 3.0)


# Hash-grid cells per covariance support radius: a query then scans 5^3 half-size cells, 0.58x the
# volume of 27 full-size ones; 2 is the fastest of 1, 2 and 3 for the anisotropy of 49k particles
ANISOTROPY_CELLS_PER_SUPPORT = 2


MAX_HASH_CELLS = 1 << 22
"""Cells of a hash grid's table at most (8 bytes each). Warp hashes a cell to (i mod dim_x, j mod dim_y,
k mod dim_z): a table smaller than the points' box makes far cells share a slot, whose points every
query there scans and rejects. A per-axis cap of 128 did that to the 1M-particle frame's 143 x 35 x 143
cells; the whole box (0.7M slots) makes its anisotropy 0.65 -> 0.55 s."""


def hash_table_dims(extent: np.ndarray, cell: float) -> tuple[int, int, int]:
    """A hash grid's table for a box of ``extent`` (m) in cells of ``cell``: the box's cells, every
    axis shrunk alike where that would pass ``MAX_HASH_CELLS``."""
    dims = np.maximum(1.0, np.ceil(np.asarray(extent, np.float64) / cell) + 1)
    shrink = max(1.0, float(np.prod(dims) / MAX_HASH_CELLS) ** (1.0 / 3.0))
    x, y, z = (max(1, int(d / shrink)) for d in dims)
    return x, y, z


def hash_grid(points: wp.array, host_points: np.ndarray, cell: float, device: str) -> wp.HashGrid:
    """A Warp hash grid over ``points`` with cells of ``cell`` (table: ``hash_table_dims``)."""
    lo, hi = bounds(host_points)
    grid = wp.HashGrid(*hash_table_dims(hi - lo, cell), device=device)
    grid.build(points, cell)
    return grid


WIDE_KERNEL_QUANTILE = 0.99
"""Kernels whose bounding radius exceeds this quantile of all of them go into ``KernelLookup``'s
wide grid (on the dam break the largest is 1.5x the 99th percentile, which the narrow grid's
query radius would otherwise have to reach)."""


class KernelLookup:
    """The anisotropic kernels in two hash grids, for sums at arbitrary points (mesh normals, ray
    marching): the narrow ones queried with their largest bounding radius, the few wide ones in a
    grid of their own with theirs. A single grid must be queried with the largest radius of all,
    which visits about 3x the candidates, nearly all of them too far to contribute.

    ``args()`` are the kernels' arguments narrow .. extents, in ``kernels.kernel_sum``'s order: the
    kernels reordered narrow first (each class in its original order, so sums are reproducible)."""

    def __init__(self, kernels: tuple[wp.array, wp.array, wp.array], device: str):
        centres, g, extents = kernels
        e = extents.numpy()
        cut = float(np.quantile(e, WIDE_KERNEL_QUANTILE))
        wide = e > cut
        order = np.concatenate([np.flatnonzero(~wide), np.flatnonzero(wide)])
        c = centres.numpy()[order]
        self.centres = wp.array(c, dtype=wp.vec3, device=device)
        self.g = wp.array(g.numpy()[order], dtype=wp.mat33, device=device)
        self.extents = wp.array(e[order], dtype=float, device=device)
        self.wide_start = int((~wide).sum())
        self.narrow_reach = float(e[~wide].max())
        self.narrow = hash_grid(self.centres[: self.wide_start], c[: self.wide_start], self.narrow_reach, device)
        if wide.any():
            self.wide_reach = float(e[wide].max())
            self.wide = hash_grid(self.centres[self.wide_start:], c[self.wide_start:], self.wide_reach, device)
        else:  # no wide kernels: kernel_sum skips the second grid
            self.wide_reach, self.wide = -1.0, self.narrow

    def args(self) -> list:
        """narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents."""
        return [self.narrow.id, self.narrow_reach, self.wide.id, self.wide_reach, self.wide_start, self.centres,
                self.g, self.extents]


DENSITY_REACH = 1.25
"""``KernelMaker.densities`` sums the kernels of the particles within this many kernel radii h (an
interior kernel's extent) of a particle: all that reach an interior or surface particle's centre
(tested), some of a spray cloud's stretched ones (both the dataset and the render sum the same)."""
DENSITY_CAP = 3.0
"""``KernelMaker.densities`` stops at this many iso-levels (the feature's tanh(1.5) = 0.91): a dense
particle's sum ends early, which halves its cost."""


def _empty() -> SurfaceMesh:
    return SurfaceMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))


class KernelMaker:
    """The anisotropy of one frame's particles on one hash grid: of every particle at once
    (``all``), or of some at a time into kernels that start as the interior one (``some``)."""

    def __init__(self, positions: np.ndarray, radius: float, p: DatasetConfig, launch: Launcher, device: str,
                 x: wp.array | None = None):
        """``x``: the positions already on ``device`` (float32), if they are."""
        self.n, self.launch, self.device = len(positions), launch, device
        self.h = p.aniso_kernel_radius * radius
        support = anisotropy_support(radius, p.aniso_kernel_radius)
        positions = np.ascontiguousarray(positions, np.float32)
        self.x = wp.array(positions, dtype=wp.vec3, device=device) if x is None else x
        self.grid = hash_grid(self.x, positions, support / ANISOTROPY_CELLS_PER_SUPPORT, device)
        a = K.Anisotropy()
        a.support, a.kernel_radius, a.smoothing, a.kr = support, self.h, p.aniso_smoothing, p.aniso_kr
        a.ks_scale = (p.aniso_ks / 1400.0) / full_neighbourhood_variance(spacing(radius), support)
        a.kn, a.n_eps = p.aniso_kn, p.aniso_neps
        self.anisotropy = a
        self.cell = support / ANISOTROPY_CELLS_PER_SUPPORT
        self.amplitude = particle_volume(radius) * POLY6_NORM / p.iso_level
        self.rest = 1.0 / p.iso_level
        self._grid_ids: wp.array | None = None
        self._order: np.ndarray | None = None
        self._table: N.CellTable | None = None

    def all(self) -> tuple[wp.array, wp.array, wp.array]:
        """Every particle's smoothed centre, kernel matrix and ellipsoid extent."""
        n, device = self.n, self.device
        centres = wp.zeros(n, dtype=wp.vec3, device=device)
        g = wp.zeros(n, dtype=wp.mat33, device=device)
        extents = wp.zeros(n, dtype=float, device=device)
        return self._anisotropy(self._grid_order(), (centres, g, extents))

    def interior(self) -> tuple[wp.array, wp.array, wp.array]:
        """Every particle with the kernel of a full interior neighbourhood: its own place, a sphere."""
        n, device = self.n, self.device
        kernels = (wp.empty(n, dtype=wp.vec3, device=device), wp.empty(n, dtype=wp.mat33, device=device),
                   wp.empty(n, dtype=float, device=device))
        self.launch(K.interior_kernels, n, [self.x, float(self.h), *kernels])
        return kernels

    def _grid_order(self) -> wp.array:
        """Every particle's index in the grid's cell order."""
        if self._grid_ids is None:
            self._grid_ids = wp.empty(self.n, dtype=int, device=self.device)
            self.launch(K.grid_order, self.n, [self.grid.id, self._grid_ids])
        return self._grid_ids

    def _in_grid_order(self, picked: np.ndarray) -> wp.array:
        """The indices of the ``picked`` particles in the grid's cell order, as the full launch runs
        them: each thread's neighbours stay in cache."""
        if self._order is None:
            self._order = self._grid_order().numpy()
        return wp.array(self._order[picked[self._order]], dtype=int, device=self.device)

    def table(self) -> N.CellTable:
        """The particles sorted by the grid's cells (``native.CellTable``), made once."""
        if self._table is None:
            t = N.CellTable()
            t.ids = self._grid_order()
            t.x = wp.empty(self.n, dtype=wp.vec3, device=self.device)
            t.dim_x, t.dim_y, t.dim_z = self.grid._dim_x, self.grid._dim_y, self.grid._dim_z
            t.cell = float(self.cell)
            t.inv = float(np.float32(1.0) / np.float32(self.cell))  # the grid's own float32 inverse
            t.first = wp.empty(t.dim_x * t.dim_y * t.dim_z + 1, dtype=int, device=self.device)
            slots = wp.empty(self.n, dtype=int, device=self.device)
            self.launch(N.table_entries, self.n, [t, self.x, slots])
            self.launch(N.table_first, self.n + 1, [self.n, slots, t.first])
            self._table = t
        return self._table

    def some(self, kernels: tuple[wp.array, wp.array, wp.array], picked: np.ndarray) -> tuple[wp.array, ...]:
        """The anisotropy of the ``picked`` particles (a bool a particle) into ``kernels``, in place."""
        if picked.any():
            self._anisotropy(self._in_grid_order(picked), kernels)
        return kernels

    def _anisotropy(self, which: wp.array, kernels: tuple[wp.array, wp.array, wp.array]) -> tuple[wp.array, ...]:
        """The anisotropy of the particles listed in ``which`` (in the grid's cell order) into
        ``kernels``: on the CPU the vectorised loop over the cell table, on CUDA the hash grid's."""
        if self.launch.cpu:
            self.launch(N.anisotropy_of_table, len(which), [which, self.table(), self.x, self.anisotropy, *kernels])
        else:
            self.launch(K.compute_anisotropy_of, len(which), [which, self.grid.id, self.x, self.anisotropy, *kernels])
        return kernels

    def densities(self, kernels: tuple[wp.array, wp.array, wp.array], picked: np.ndarray | None = None) -> np.ndarray:
        """The mesh's density at each ``picked`` particle's kernel centre (every particle's by
        default), in iso-levels: below 1 the particle's centre lies outside the mesh, as a spray
        particle or one of a sheet the mesh opens does (``kernel_densities``). The others, deep
        inside the fluid, get the rest density (1 over the iso-level). On the CPU the sums run over
        the cell table, 16 candidates a vector (``native.density_of_table``)."""
        picked = np.ones(self.n, bool) if picked is None else picked
        out = wp.full(self.n, float(self.rest), dtype=float, device=self.device)
        if picked.any():
            which = self._in_grid_order(picked)
            sums = [float(DENSITY_REACH * self.h), float(self.amplitude), float(DENSITY_CAP)]
            if self.launch.cpu:  # 16 candidates a vector over the cell table (surface.native)
                t = self.table()
                planes = wp.empty(N.KERNEL_PLANES * self.n, dtype=float, device=self.device)
                self.launch(N.table_kernels, self.n, [t, *kernels, planes])
                self.launch(N.density_of_table, len(which), [which, t, self.x, kernels[0], planes, *sums, out])
            else:
                self.launch(K.centre_density, len(which), [which, self.grid.id, self.x, sums[0], *kernels, *sums[1:],
                                                           out])
        return out.numpy()


def anisotropic_kernels(positions: np.ndarray, radius: float, p: DatasetConfig, launch: Launcher,
                        device: str, only: np.ndarray | None = None) -> tuple[wp.array, wp.array, wp.array]:
    """Smoothed centres, kernel matrices and ellipsoid extents (Warp arrays).

    With ``only`` (particle indices) just those particles get their anisotropy; every other one gets
    the kernel of a full interior neighbourhood (its own position, a sphere: scale 1), which costs
    nothing (``seen_kernels`` picks the particles a camera can see)."""
    if len(positions) == 0:
        return (wp.zeros(0, dtype=wp.vec3, device=device), wp.zeros(0, dtype=wp.mat33, device=device),
                wp.zeros(0, dtype=float, device=device))
    maker = KernelMaker(positions, radius, p, launch, device)
    if only is None:
        return maker.all()
    picked = np.zeros(len(positions), bool)
    picked[only] = True
    return maker.some(maker.interior(), picked)


def kernel_densities(positions: np.ndarray, radius: float, p: DatasetConfig, launch: Launcher, device: str,
                     kernels: tuple[wp.array, wp.array, wp.array]) -> np.ndarray:
    """Every particle's density at its own kernel centre in iso-levels (``KernelMaker.densities``)
    for ``anisotropic_kernels``' output."""
    if len(positions) == 0:
        return np.zeros(0, np.float32)
    return KernelMaker(np.asarray(positions, np.float32), radius, p, launch, device).densities(kernels)


REVEAL_PASSES = 2
"""Most passes of ``seen_kernels`` that look behind the seen particles' own ellipsoids (the 1M
frame of bench_scale: 118k particles in the first pass, 16k and 167 in the two reveal passes)."""

SEEN_DEPTH_RADII = 5.0
"""``seen_kernels``' first pass: the particles within this many radii under the spheres' surface.
On the validation scene, with the reveal passes, depths of 3 to 11 radii all give the refined
normals of every particle's anisotropy to 0.015 degree (``benchmarks/bench_seen.py``); the
anisotropy of bench_scale's 1M frame takes 614 ms at 5 radii, 862 at 11."""

MOTION_BAND_RADII = 5.0
"""``seen_kernels`` also returns the particles within this many radii under the ellipsoids' surface,
for the motion splat (``ScreenSpace.motion`` reads those only, and counts every particle within two
radii of the filtered depth, which lies deeper): its pass is then every particle's (tested)."""


def seen_kernels(positions: np.ndarray, radius: float, p: DatasetConfig, camera: Camera, launch: Launcher,
                 device: str, depth_margin: float | None = None, densities: bool = False
                 ) -> tuple[tuple[wp.array, wp.array, wp.array], np.ndarray, np.ndarray | None]:
    """``anisotropic_kernels`` for what ``camera`` sees, the interior kernel (its own place, a
    sphere of radius r) for every other particle: the ellipsoid splat of every particle's anisotropy
    but for a few pixels (tested), at a fraction of its cost for a million particles.

    First the particles within ``depth_margin`` (m; default ``SEEN_DEPTH_RADII`` radii) under the
    surface of the particles as spheres, or near the silhouette, get their anisotropy
    (``near_front``). Their ellipsoids lie elsewhere than their spheres: a surface recedes (the
    centres are smoothed inwards), spray shrinks to half a radius, a thin sheet flattens, and what
    the spheres hid shows. The particles left as spheres within a radius of the nearest ellipsoid
    surface get their anisotropy too, until a pass finds none (``REVEAL_PASSES`` at most). The
    spheres' surface alone (one support and a radius deep, as before) left the refined normals of
    the validation scene 0.12 degree worse than every particle's anisotropy; with these passes they
    are the same (``benchmarks/bench_seen.py``). Returns the kernels, the indices of the
    particles the camera may see (those that got their anisotropy and those within
    ``MOTION_BAND_RADII`` under the ellipsoids' surface) and, with ``densities``, each particle's
    density at its kernel centre (``KernelMaker.densities``; the rest density for those left as
    spheres, which lie inside), else None."""
    support = anisotropy_support(radius, p.aniso_kernel_radius)
    # a surface particle moves inwards by at most the smoothing times its one-sided neighbourhood's
    # mean offset (3/8 of the support for a half ball): a hidden one left a sphere in its place
    # would stand out that far, plus its radius, past the silhouette
    edge_reach = p.aniso_smoothing * 0.375 * support + radius
    margin = SEEN_DEPTH_RADII * radius if depth_margin is None else depth_margin
    tiles = FrontTiles.of(positions, radius, camera, launch, device, edge_reach)
    if tiles is None:
        seen = np.zeros(0, np.int64)
        return (anisotropic_kernels(positions, radius, p, launch, device, only=seen), seen,
                np.full(len(positions), 1.0 / p.iso_level, np.float32) if densities else None)
    # which particles have their anisotropy, a bool each (sets of a million indices took 50 ms a frame)
    seen = tiles.behind(tiles.sphere_front(launch), launch) <= margin
    maker = KernelMaker(positions, radius, p, launch, device, tiles.x)
    kernels = maker.some(maker.interior(), seen)

    def under_ellipsoids() -> np.ndarray:
        """How far each particle lies under the surface of the kernels' own ellipsoids."""
        return tiles.behind(tiles.kernel_front(kernels, seen, p.aniso_kernel_radius, launch), launch)

    behind = None
    for _ in range(REVEAL_PASSES):
        # the particles left as spheres that the kernels' own ellipsoids show
        behind = under_ellipsoids()
        new = (behind <= radius) & ~seen
        if not new.any():
            break
        maker.some(kernels, new)
        seen |= new
    if behind is None:
        behind = under_ellipsoids()
    # the last pass's surface (a few hundred particles' kernels newer at most): the motion's band
    visible = np.flatnonzero(seen | (behind <= MOTION_BAND_RADII * radius))
    return kernels, visible, maker.densities(kernels, seen) if densities else None


NEAR_FRONT_TILE_RADII = 1.0
"""Screen tiles of ``near_front``'s depth buffer in projected particle radii (at the particles'
median depth, at least a pixel): each sphere covers about three tile centres."""


@dataclass
class FrontTiles:
    """The coarse screen tiles of ``near_front``: a camera over tiles of about a projected particle
    radius, with a border as wide as the nearest particles' reach past the image."""

    view: K.TileView
    x: wp.array
    band: int
    """Tiles around the silhouette (empty tiles) whose particles are all kept."""
    shape: tuple[int, int]

    @staticmethod
    def of(positions: np.ndarray, radius: float, camera: Camera, launch: Launcher, device: str,
           edge_reach: float = 0.0) -> FrontTiles | None:
        """The tiles of a camera for these particles; None when none lies in front of it."""
        n = len(positions)
        if n == 0:
            return None
        rotation = camera.view[:3, :3].astype(np.float32)
        translation = camera.view[:3, 3].astype(np.float32)
        sample = np.asarray(positions[:: max(1, n // 4096)], np.float32)
        depths = -(sample @ rotation[2] + translation[2])
        depths = depths[depths > radius]
        if not len(depths):
            return None
        tile = max(1.0, NEAR_FRONT_TILE_RADII * camera.focal_px * radius / float(np.median(depths)))
        # the nearest particles' projected radius in tiles (a particle at the lens is not one to size by)
        near_radius = camera.focal_px * radius / float(np.percentile(depths, 1)) / tile
        image_tiles = int(math.ceil(max(camera.width, camera.height) / tile))
        border = min(int(math.ceil(4.0 * near_radius)) + 1, image_tiles)
        tiles_x = int(math.ceil(camera.width / tile)) + 2 * border
        tiles_y = int(math.ceil(camera.height / tile)) + 2 * border
        view = K.TileView()
        view.rotation, view.translation = wp.mat33(*rotation.ravel()), wp.vec3(*translation)
        view.focal, view.width, view.height, view.radius = camera.focal_px, camera.width, camera.height, float(radius)
        view.tile_px, view.border, view.tiles_x, view.tiles_y = float(tile), border, tiles_x, tiles_y
        x = wp.array(np.ascontiguousarray(positions, np.float32), dtype=wp.vec3, device=device)
        band = min(int(math.ceil(near_radius * edge_reach / radius)), image_tiles)
        return FrontTiles(view, x, band, (tiles_y, tiles_x))

    def _front(self, kernel: Any, inputs: list, launch: Launcher) -> np.ndarray:
        """A tile buffer of ``kernel``'s nearest surfaces (``EMPTY_FRONT`` where none)."""
        size, device = self.shape[0] * self.shape[1], self.x.device
        if not launch.cpu:
            front = wp.full(size, K.EMPTY_FRONT, dtype=float, device=device)
            launch(kernel, len(self.x), [*inputs, self.view, front])
            return front.numpy().reshape(self.shape)
        # chunks on the CPU would race on one buffer (atomics are atomic only within a launch): each
        # fills its own and the nearest of them is kept, the same numbers in any order
        fronts: list[wp.array] = []

        def chunk_inputs(_: int) -> list:
            fronts.append(wp.full(size, K.EMPTY_FRONT, dtype=float, device=device))
            return [*inputs, self.view, fronts[-1]]

        launch.map(kernel, len(self.x), chunk_inputs)
        return np.minimum.reduce([f.numpy() for f in fronts]).reshape(self.shape)

    def sphere_front(self, launch: Launcher) -> np.ndarray:
        """The nearest sphere surface through each tile's centre (``nearest_front``)."""
        return self._front(K.nearest_front, [self.x], launch)

    def kernel_front(self, kernels: tuple[wp.array, wp.array, wp.array], own: np.ndarray, scale: float,
                     launch: Launcher) -> np.ndarray:
        """The nearest surface of the kernels' ellipsoids (``kernel_ellipsoids``' ``scale``) through
        each tile's centre (``nearest_kernel_front``); the particles not ``own`` (a bool each) have the
        interior kernel, a sphere of radius r at their own place."""
        flags = wp.array(own.view(np.uint8), dtype=wp.uint8, device=self.x.device)
        return self._front(K.nearest_kernel_front, [self.x, flags, *kernels, float(scale)], launch)

    def behind(self, front: np.ndarray, launch: Launcher) -> np.ndarray:
        """How far each particle lies under ``front`` (m, ``depth_behind_front``): -1 within the
        silhouette's band of tiles, ``EMPTY_FRONT`` where it is not seen at all; a particle within a
        depth margin m of the front has ``behind <= m``."""
        if self.band > 0:  # the silhouette's band counts as empty: every particle there is kept
            from scipy.ndimage import binary_dilation

            front = front.copy()
            front[binary_dilation(front >= K.EMPTY_FRONT, iterations=self.band)] = K.EMPTY_FRONT
        buffer = wp.array(np.ascontiguousarray(front, np.float32).ravel(), dtype=float, device=self.x.device)
        behind = wp.empty(len(self.x), dtype=float, device=self.x.device)
        launch(K.depth_behind_front, len(self.x), [self.x, self.view, buffer, behind])
        return behind.numpy()


def near_front(positions: np.ndarray, radius: float, camera: Camera, depth_margin: float, launch: Launcher,
               device: str, edge_reach: float = 0.0) -> np.ndarray:
    """Indices of the particles a camera may see: in front of it, projected into the image (or
    within a few particle radii of it), and no more than ``depth_margin`` (m) behind the nearest
    sphere surface seen through their screen tile. The rest are hidden inside the fluid
    (or outside the view) whatever shape their kernels take, so they need no anisotropy.

    The nearest fronts are a coarse depth buffer of the particles as spheres (``nearest_front``),
    so a particle is judged by the surface actually seen at its tile, steep or not. Every particle
    projected within ``edge_reach`` (m, at the depth of the nearest particles) of the fluid's
    silhouette is kept too: there the surfaces facing away, whatever their depth, border the image."""
    tiles = FrontTiles.of(positions, radius, camera, launch, device, edge_reach)
    if tiles is None:
        return np.zeros(0, np.int64)
    return np.flatnonzero(tiles.behind(tiles.sphere_front(launch), launch) <= depth_margin)


def particle_ellipsoids(positions: np.ndarray, radius: float, p: DatasetConfig, launch: Launcher,
                        device: str | None = None, kernels: tuple[wp.array, wp.array, wp.array] | None = None,
                        on_device: bool | None = None, density: np.ndarray | bool | None = None) -> Ellipsoids:
    """Each particle's ellipsoid from the same anisotropy as the mesh target (Yu & Turk): the
    smoothed centre, and semi-axes of r times the kernel's principal scales (a full neighbourhood
    gives scale 1, so an interior particle stays a sphere of radius r, a surface one flattens).

    ``kernels`` are ``anisotropic_kernels``' outputs when they were already computed. ``on_device``
    keeps the ellipsoids on the Warp device as arrays (default: on a GPU, where bringing 52 bytes a
    particle to the host and back to splat each view cost a round trip and a wait). ``density``: each
    particle's density at its kernel centre (``kernel_densities``; True: computed here), which the
    splat then draws too (a refiner with ``density_feature`` needs it)."""
    device = device or launch.device
    positions = np.asarray(positions, np.float32)
    if len(positions) == 0:
        return Ellipsoids(np.zeros((0, 3), np.float32), np.zeros((0, 3, 3), np.float32), np.zeros(0, np.float32))
    on_device = str(device).startswith("cuda") if on_device is None else on_device
    kernels = kernels or anisotropic_kernels(positions, radius, p, launch, device)
    if density is True:
        density = kernel_densities(positions, radius, p, launch, device, kernels)
    return kernel_ellipsoids(kernels, p, launch if on_device else None, None if density is False else density)


def kernel_ellipsoids(kernels: tuple[wp.array, wp.array, wp.array], p: DatasetConfig,
                      launch: Launcher | None = None, density: np.ndarray | None = None) -> Ellipsoids:
    """The particle ellipsoids of ``anisotropic_kernels``' output: G = Q diag(1 / s) Q^T / h and
    extent = h max(s), so with h = scale r the ellipsoid of semi-axes r s is |(scale G)(x - c)| = 1.
    With a ``launch`` they are made where the kernels lie (the same float32 numbers, tested) and
    stay there; without, on the host."""
    centres, g, extents = kernels
    scale = p.aniso_kernel_radius
    if launch is not None:
        n = len(centres)
        shapes = wp.empty(n, dtype=wp.mat33, device=centres.device)
        bounds = wp.empty(n, dtype=float, device=centres.device)
        launch(K.scale_ellipsoids, n, [g, extents, float(scale), shapes, bounds])
        if density is not None:
            density = wp.array(np.asarray(density, np.float32), dtype=float, device=centres.device)
        return Ellipsoids(centres, shapes, bounds, density)
    return Ellipsoids(centres.numpy(), (g.numpy() * scale).astype(np.float32),
                      (extents.numpy() / scale).astype(np.float32), density)


def marching_cubes(grid: np.ndarray | wp.array, level: float, cell: float, origin: np.ndarray, device: str,
                   backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Vertices (world, float32) and triangles of the ``level`` set of a density grid (a 3D numpy
    array, or ``density_grid``'s Warp array); none where the grid stays below ``level``.

    ``backend``: 'skimage' (``measure.marching_cubes``, the reference targets were built with it),
    'warp' (``warp.geometry.IsoSurfaceMarchingCubes``: kernels on the grid's device, no copy to
    the host on a GPU) or 'auto' (warp on CUDA, skimage on the CPU)."""
    use_warp = backend == "warp" or (backend == "auto" and str(device).startswith("cuda"))
    if use_warp and isinstance(grid, wp.array) and grid.device == wp.get_device(device):
        field = grid  # read where it lies
    else:
        values = np.ascontiguousarray(grid.numpy() if isinstance(grid, wp.array) else grid, np.float32)
        if not use_warp:
            if values.max() <= level:  # scikit-image refuses a level outside the grid's range
                return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32)
            verts, faces, _, _ = measure.marching_cubes(values, level=level, spacing=(cell, cell, cell),
                                                        allow_degenerate=False)
            return (verts + origin).astype(np.float32), faces.astype(np.int32)
        field = wp.array(values, dtype=float, device=device)
    from warp.geometry import IsoSurfaceMarchingCubes

    upper = origin + cell * (np.asarray(field.shape) - 1)
    verts, tris = IsoSurfaceMarchingCubes.extract(field, level, lower=wp.vec3(*origin), upper=wp.vec3(*upper))
    return verts.numpy().astype(np.float32), tris.numpy().reshape(-1, 3).astype(np.int32)


def _grid_normals(grid: wp.array, index: np.ndarray, launch: Launcher) -> np.ndarray:
    """Outward (descending) unit gradient of the grid at the nearest nodes of fractional indices:
    ``np.gradient``'s differences, taken at those nodes only (``kernels.grid_gradient``)."""
    nodes = np.clip(np.rint(index).astype(np.int32), 0, np.asarray(grid.shape) - 1)
    out = wp.zeros(len(nodes), dtype=wp.vec3, device=grid.device)
    launch(K.grid_gradient, len(nodes), [grid, wp.array(nodes, dtype=wp.vec3i, device=grid.device), out])
    n = -out.numpy()
    return (n / np.maximum(length(n), 1e-12)[..., None]).astype(np.float32)


def density_grid(centres: wp.array, kernel_g: wp.array, extents: wp.array, volume: float, cell: float,
                 launch: Launcher, device: str) -> tuple[wp.array, np.ndarray]:
    """The anisotropic density on a grid covering every ellipsoid; returns (grid, origin), the grid a
    3D Warp array on ``device`` (on a GPU it never visits the host)."""
    c = centres.numpy()
    e = float(extents.numpy().max())
    lo, hi = bounds(c)
    lo, hi = lo - e - 2 * cell, hi + e + 2 * cell
    dims = np.maximum(np.ceil((hi - lo) / cell).astype(int) + 1, 2)
    size = int(np.prod(dims))
    buffers: list[wp.array] = []

    def inputs(chunk: int):
        while len(buffers) <= chunk:
            buffers.append(wp.zeros(size, dtype=float, device=device))
        return [centres, kernel_g, extents, volume, wp.vec3(*lo), cell, *map(int, dims), buffers[chunk]]

    launch.map(K.splat_density, len(c), inputs)
    if len(buffers) > 1:  # the CPU's private chunk grids, summed into the first in chunk order
        total = buffers[0].numpy()
        for b in buffers[1:]:
            total += b.numpy()
    return buffers[0].reshape(tuple(map(int, dims))), lo.astype(np.float64)


def density_normals(centres: wp.array, kernel_g: wp.array, extents: wp.array, vertices: np.ndarray,
                    launch: Launcher, device: str) -> np.ndarray:
    """Outward unit normals of the anisotropic density at the given points (analytic gradient)."""
    lookup = KernelLookup((centres, kernel_g, extents), device)
    out = wp.zeros(len(vertices), dtype=wp.vec3, device=device)
    launch(K.density_gradient_normals, len(vertices),
           [*lookup.args(), wp.array(vertices, dtype=wp.vec3, device=device), out])
    return out.numpy()


def reconstruct(positions: np.ndarray, radius: float, p: DatasetConfig, launch: Launcher,
                device: str | None = None, kernels: tuple[wp.array, wp.array, wp.array] | None = None) -> SurfaceMesh:
    """Anisotropic kernels -> density grid -> marching cubes -> mesh with gradient normals.

    ``kernels`` are ``anisotropic_kernels``' outputs when they were already computed."""
    device = device or launch.device
    timings = Timings()
    positions = np.asarray(positions, np.float32)
    if len(positions) == 0:
        return _empty()
    with timings("anisotropy"):
        centres, g, extents = kernels or anisotropic_kernels(positions, radius, p, launch, device)
    cell = radius / p.grid_cells_per_radius
    c = centres.numpy()
    lo, hi = bounds(c)
    span = float((hi - lo).max() + 2 * extents.numpy().max())
    cell = max(cell, span / (p.max_grid_cells - 5))
    with timings("density"):
        grid, origin = density_grid(centres, g, extents, particle_volume(radius), cell, launch, device)
    with timings("marching_cubes"):
        verts, faces = marching_cubes(grid, p.iso_level, cell, origin, device, p.marching_cubes)
    if len(faces) == 0:
        return _empty()
    with timings("normals"):
        normals = density_normals(centres, g, extents, verts, launch, device)
        # a few vertices a frame (0-14 of 40k in the dam break) lie where a kernel thinner than a
        # cell already ends: the density there is 0 and so is its gradient; they take the grid's
        bad = length(normals) < 0.5
        if bad.any():
            normals[bad] = _grid_normals(grid, (verts[bad] - origin) / cell, launch)
    mesh = SurfaceMesh(verts, faces, normals.astype(np.float32), timings)
    return mesh


RASTER_NEAR = 1.0e-4
"""View depth (m) of the near plane ``render_maps`` clips triangles' screen boxes to."""


def render_maps(mesh: SurfaceMesh, camera: Camera, launch: Launcher,
                device: str | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast a mesh: view-space normals (H x W x 3), view depth and mask (H x W).

    Each triangle casts the rays of the pixels in its screen box (``kernels.raster_mesh``) rather
    than each pixel searching a BVH: on the CPU the BVH's build alone took as long as the cast.
    A pixel keeps its nearest hit, ties going to the lowest-numbered triangle, so the maps do not
    depend on how the triangles are split over threads (each CPU chunk writes a private buffer and
    the buffers are merged by minimum)."""
    device = device or launch.device
    w, h = camera.width, camera.height
    if len(mesh.faces) == 0:
        return np.zeros((h, w, 3), np.float32), np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    rot = camera.cam_to_world[:3, :3].astype(np.float64)
    view = lambda v: np.ascontiguousarray((np.asarray(v, np.float64) @ rot).astype(np.float32))  # noqa: E731
    vertices = wp.array(view(mesh.vertices - camera.eye), dtype=wp.vec3, device=device)
    normals = wp.array(view(mesh.normals), dtype=wp.vec3, device=device)
    faces = wp.array(mesh.faces.ravel(), dtype=int, device=device)
    none_f, none_i = wp.zeros(0, dtype=float, device=device), wp.zeros(0, dtype=int, device=device)
    depths: list[wp.array] = []
    triangles: list[wp.array] = []

    def depth_pass(chunk: int) -> list:
        depths.append(wp.full(w * h, 1.0e30, dtype=float, device=device))
        return [vertices, faces, w, h, camera.focal_px, RASTER_NEAR, none_f, depths[chunk], none_i]

    def merged(buffers: list[wp.array], dtype) -> wp.array:
        """The chunks' private buffers merged by minimum (one chunk on CUDA: its buffer)."""
        if len(buffers) == 1:
            return buffers[0]
        return wp.array(np.minimum.reduce([b.numpy() for b in buffers]), dtype=dtype, device=device)

    launch.map(K.raster_mesh, len(mesh.faces), depth_pass)
    nearest = merged(depths, float)

    def triangle_pass(chunk: int) -> list:
        triangles.append(wp.full(w * h, int(K.NO_TRIANGLE), dtype=int, device=device))
        return [vertices, faces, w, h, camera.focal_px, RASTER_NEAR, nearest, none_f, triangles[chunk]]

    launch.map(K.raster_mesh, len(mesh.faces), triangle_pass)
    winner = merged(triangles, int)
    out_n = wp.zeros(w * h, dtype=wp.vec3, device=device)
    out_d = wp.zeros(w * h, dtype=float, device=device)
    launch(K.raster_mesh_resolve, w * h, [vertices, normals, faces, winner, w, h, camera.focal_px, out_n, out_d])
    depth = out_d.numpy().reshape(h, w)
    return out_n.numpy().reshape(h, w, 3), depth, (depth > 0).astype(np.float32)


def raytrace_maps(kernels: tuple[wp.array, wp.array, wp.array], radius: float, p: DatasetConfig, camera: Camera,
                  ss: ScreenSpace, launch: Launcher, device: str | None = None,
                  with_thickness: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ray-march the anisotropic density of ``anisotropic_kernels``' output: view-space normals
    (H x W x 3, the analytic -grad phi), view depth, mask and (with ``with_thickness``) the length
    of each ray inside the surface.

    Each ray starts where it enters the first kernel support (a splat of the support spheres), steps
    ``raytrace_step_radii`` particle radii, and refines the first iso crossing by bisection. Only
    the kernels near each sample are summed (``KernelLookup``)."""
    device = device or launch.device
    w, h = camera.width, camera.height
    centres, g, extents = kernels
    c, e = centres.numpy(), extents.numpy()
    empty = np.zeros((h, w), np.float32)
    if len(c) == 0:
        return np.zeros((h, w, 3), np.float32), empty, empty, empty
    supports = Ellipsoids(c, (np.eye(3, dtype=np.float32)[None] / e[:, None, None]).astype(np.float32), e)
    t_start = ss.splat_ellipsoids(supports, camera, normals=False).depth
    reach = float(e.max())
    lo, hi = bounds(c)
    lookup = KernelLookup(kernels, device)
    amplitude = particle_volume(radius) * POLY6_NORM
    out_n = wp.zeros(w * h, dtype=wp.vec3, device=device)
    out_d = wp.zeros(w * h, dtype=float, device=device)
    out_t = wp.zeros(w * h, dtype=float, device=device)
    rot = camera.cam_to_world[:3, :3].astype(np.float32)
    launch(K.raymarch_density, w * h, [
        *lookup.args(), amplitude, p.iso_level, wp.vec3(*camera.eye.astype(np.float32)),
        wp.mat33(*rot.ravel()), w, h, camera.focal_px, wp.array(t_start.ravel(), dtype=float, device=device),
        wp.vec3(*(lo - reach)), wp.vec3(*(hi + reach)), p.raytrace_step_radii * radius,
        p.raytrace_bisections, int(with_thickness), out_n, out_d, out_t])
    depth = out_d.numpy().reshape(h, w)
    return (out_n.numpy().reshape(h, w, 3), depth, (depth > 0).astype(np.float32),
            out_t.numpy().reshape(h, w))
