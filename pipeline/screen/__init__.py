"""Screen-space fluid inputs: sphere splatting, depth filters and normals (host side).

Each filter is a function ``(depth, ...) -> depth`` over NumPy H x W float32 maps in the
convention of ``pipeline.camera`` (positive view depth, 0 = empty). ``ScreenSpace.inputs`` chains
splat, filters and normals on the device without round trips through NumPy, in buffers that are
allocated once per image size and reused frame after frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from pipeline.camera import Camera
from pipeline.config import DatasetConfig
from pipeline.device import download, on_torch_stream, torch_waits_for_warp, wait_for_downloads, warp_waits_for_torch
from pipeline.ellipsoids import DENSITY_CHANNEL, Ellipsoids
from pipeline.parallel import Launcher
from pipeline.screen import filters as F
from pipeline.screen import kernels as K
from pipeline.screen import native as N
from pipeline.timing import Timings
from pipeline.vectors import host, is_tensor

_EMPTY = 1.0e30
FILTERS = ("gaussian", "bilateral", "nrf")

# Row bands of the splat per thread: threads take bands as they come free, so fluid crowded into a
# few rows still spreads over the cores; each band culls every particle, which costs ~0.1 ms.
SPLAT_BANDS_PER_THREAD = 4


@dataclass
class SplatResult:
    """Raw splat depth, mask and thickness of one view (and the ellipsoids' analytic normals)."""

    depth: np.ndarray
    mask: np.ndarray
    thickness: np.ndarray
    normals: np.ndarray | None = None


def row_bands(launch: Launcher, height: int) -> list[tuple[int, int]]:
    """Row bands for the per-particle splat kernels: one on CUDA or a single thread, else
    ``SPLAT_BANDS_PER_THREAD`` per thread, so bands own their rows and run without races."""
    parallel = launch.cpu and launch.threads > 1
    count = max(1, min(height, SPLAT_BANDS_PER_THREAD * launch.threads)) if parallel else 1
    bounds = [height * k // count for k in range(count + 1)]
    return [(bounds[k], bounds[k + 1]) for k in range(count) if bounds[k + 1] > bounds[k]]


def nearest_fluid_pixels(fluid):
    """Exact Euclidean feature transform of a boolean H x W torch tensor, where it lies: each
    pixel's distance to its nearest ``fluid`` pixel (float64; infinite without fluid) and that
    pixel's row and column (int32; -1 without fluid). The algorithm and tie rules of
    ``scipy.ndimage.distance_transform_edt(~fluid, return_indices=True)``, and its numbers bit for
    bit (tested), as two Warp passes on torch's stream: one thread per column, then per row."""
    import torch

    h, w = fluid.shape
    device = fluid.device
    rows = torch.empty((h, w), dtype=torch.int32, device=device)
    cols, envelope = torch.empty_like(rows), torch.empty_like(rows)
    distance = torch.empty((h, w), dtype=torch.float64, device=device)
    if h == 0 or w == 0:
        return distance, rows, cols
    site_row = torch.empty_like(rows)
    wp.init()
    on = wp.device_from_torch(device)
    with on_torch_stream(device):
        wp.launch(K.nearest_in_column, w, [wp.from_torch(fluid.to(torch.uint8).contiguous()), wp.from_torch(site_row)],
                  device=on)
        wp.launch(K.nearest_in_row, h, [wp.from_torch(site_row), wp.from_torch(envelope), wp.from_torch(rows),
                                       wp.from_torch(cols), wp.from_torch(distance)], device=on)
    return distance, rows, cols


class ScreenSpace:
    """Runs the screen-space kernels for one device (holds the thread pool and the frame buffers).

    Not thread-safe: give each thread its own instance (the buffers are reused between calls).
    """

    def __init__(self, device: str = "cpu", threads: int = 0):
        self.device = device
        self.launch = Launcher(device, threads, min_chunk=4096)
        self._buffers: dict[str, tuple[tuple, wp.array]] = {}

    # ---- device buffers -------------------------------------------------------------------------

    def _buffer(self, name: str, n: int, dtype=float) -> wp.array:
        """The device array ``name``, reused while its size and type stay (frames of one image
        size, views of one particle count) and replaced when they change, or once the host was
        handed it (``_hand_over``): one array a name, so an emitter's growing particle count or the
        dataset's random image sizes leave no array behind."""
        key = (n, dtype)
        kept = self._buffers.get(name)
        if kept is None or kept[0] != key:
            kept = self._buffers[name] = (key, wp.empty(n, dtype=dtype, device=self.device))
        return kept[1]

    def _upload(self, name: str, depth: np.ndarray) -> wp.array:
        buf = self._buffer(name, depth.size)
        buf.assign(np.ascontiguousarray(depth, np.float32).ravel())
        return buf

    def _download(self, a: wp.array, shape: tuple[int, ...], wait: bool = True) -> np.ndarray:
        """The buffer's pixels as a host array of their own: from a GPU one copy into page-locked
        memory (``pipeline.device.download``; without ``wait`` only queued: ``wait_for_downloads``
        before reading); on the CPU the buffer's memory itself, handed over (``_hand_over``)."""
        if a.device.is_cuda:
            return download(a, shape, wait)
        self._hand_over(a)
        return a.numpy().reshape(shape)

    def _hand_over(self, a: wp.array) -> None:
        """Forget the buffer ``a`` so that no later kernel writes it: its name gets a new one next
        time. Cheaper than copying it out (a copy of a 1080p map took 5-7 ms); the host array keeps
        the memory, which goes back to the heap with it."""
        for name, (_, kept) in list(self._buffers.items()):
            if kept is a:
                del self._buffers[name]

    def _take(self, a: wp.array, shape: tuple[int, ...], on_device: bool, wait: bool = True):
        """The buffer's pixels as a host array (``_download``; without ``wait`` only queued, and
        the caller waits once for all) or, ``on_device``, as a torch tensor on the device holding a
        copy made there (queued on Warp's stream; the caller hands the copies over to torch's once
        all are queued)."""
        return wp.to_torch(wp.clone(a)).reshape(shape) if on_device else self._download(a, shape, wait)

    # ---- kernels on device arrays ---------------------------------------------------------------

    def _splat_buffers(self, n: int) -> tuple[wp.array, wp.array, wp.array]:
        """Depth (cleared to empty), mask and thickness (cleared to 0) buffers for a splat."""
        depth, mask, thickness = (self._buffer(name, n) for name in ("depth", "mask", "thickness"))
        depth.fill_(_EMPTY)
        thickness.zero_()
        return depth, mask, thickness

    def _view_points(self, points_world: np.ndarray | wp.array, camera: Camera) -> wp.array:
        """World points in view space, float32 on the device: host points transformed on the host
        (``Camera.to_view``) and uploaded; points already on the device (a GPU's frame, uploaded
        once for all its views) transformed there in float64 (``view_centres``: within a float32
        ulp of the host's)."""
        if not isinstance(points_world, wp.array):
            return wp.array(camera.to_view(np.asarray(points_world, np.float64)).astype(np.float32), dtype=wp.vec3,
                            device=self.device)
        out = self._buffer("view_centres", len(points_world), wp.vec3)
        self.launch(K.view_centres, len(points_world), [
            points_world, wp.mat33d(*np.asarray(camera.view[:3, :3], np.float64).ravel()),
            wp.vec3d(*np.asarray(camera.view[:3, 3], np.float64)), out])
        return out

    def _splat(self, positions_world: np.ndarray | wp.array, radius: float, camera: Camera) -> tuple[wp.array, ...]:
        w, h = camera.width, camera.height
        depth, mask, thickness = self._splat_buffers(w * h)
        n = len(positions_world)
        if n:
            centers = self._view_points(positions_world, camera)
            bands = row_bands(self.launch, h)
            self.launch.tasks(K.splat_spheres, n, [[centers, radius, camera.focal_px, w, h, r0, r1, depth, thickness]
                                                   for r0, r1 in bands])
        self.launch(K.finish_splat, w * h, [depth, _EMPTY * 0.5, mask])
        return depth, mask, thickness

    def _splat_ellipsoids(self, ellipsoids: Ellipsoids, camera: Camera,
                          with_normals: bool = False) -> tuple[wp.array, ...]:
        """Depth, mask, thickness, normals (zero without ``with_normals``) and, where the ellipsoids
        carry their density, its largest value along each ray (0 where none; else None)."""
        w, h = camera.width, camera.height
        depth, mask, thickness = self._splat_buffers(w * h)
        normals = self._buffer("splat_normals", w * h, wp.vec3)
        normals.zero_()
        n = len(ellipsoids.centres)
        density = None
        if ellipsoids.density is not None:
            density = self._buffer("splat_density", w * h)
            density.zero_()
        if n:
            rot = wp.mat33d(*np.asarray(camera.view[:3, :3], np.float64).ravel())
            centres = self._view_points(ellipsoids.centres, camera)
            if isinstance(ellipsoids.centres, wp.array):  # on the device: read in place
                world_shapes, bounds = ellipsoids.shapes, ellipsoids.bounds
            else:
                world_shapes = wp.array(np.asarray(ellipsoids.shapes, np.float32), dtype=wp.mat33, device=self.device)
                bounds = wp.array(np.asarray(ellipsoids.bounds, np.float32), dtype=float, device=self.device)
            # the shapes turn into view space on the device (a host einsum took 15-20 ms for 49k)
            shapes = self._buffer("view_shapes", n, wp.mat33)
            self.launch(K.view_shapes, n, [world_shapes, rot, shapes])
            args = [centres, shapes, bounds, camera.focal_px, w, h]
            if density is None:
                drawn = [0, *[self._buffer("no_density", 1)] * 2]
            else:
                given = ellipsoids.density
                if not isinstance(given, wp.array):
                    given = wp.array(np.asarray(given, np.float32), dtype=float, device=self.device)
                drawn = [1, given, density]
            bands = row_bands(self.launch, h)
            if self.launch.cpu and not with_normals:  # each box row sixteen pixels a vector (screen.native)
                self.launch.tasks(N.splat_ellipsoid_rows, n, [[*args, r0, r1, depth, thickness, *drawn]
                                                              for r0, r1 in bands])
            else:
                for normals_pass in (0, 1) if with_normals else (0,):
                    self.launch.tasks(K.splat_ellipsoids, n, [[*args, r0, r1, normals_pass, depth, thickness, normals,
                                                               *drawn] for r0, r1 in bands])
        self.launch(K.finish_splat, w * h, [depth, _EMPTY * 0.5, mask])
        return depth, mask, thickness, normals, density

    def _gaussian(self, depth: wp.array, w: int, h: int, sigma_px: float) -> wp.array:
        a, b = self._buffer("pass", w * h), self._buffer("gaussian", w * h)
        args = [1.0, 0.0, 0.0, 0.0, max(w, h), sigma_px, 0]  # a fixed sigma, no range term, every pixel
        unused = self._buffer("no_sums", 1, wp.float64)
        self.launch(F.bilateral_pass, w * h, [depth, w, h, 0, *args, unused, a])
        self.launch(F.bilateral_pass, w * h, [a, w, h, 1, *args, unused, b])
        return b

    def _bilateral(self, depth: wp.array, camera: Camera, r: float, p: DatasetConfig) -> wp.array:
        w, h = camera.width, camera.height
        out = self._buffer("bilateral", w * h)
        args = [camera.focal_px, r, p.bilateral_sigma_px_scale, p.bilateral_range_radii * r, p.bilateral_max_radius_px]
        if p.filter_mode == "exact":
            self.launch(F.bilateral_filter, w * h, [depth, w, h, *args, out])
            return out
        a = self._buffer("pass", w * h)
        sums = self._buffer("line_sums", 3 * w * h, wp.float64)  # line_prefix's planes
        sizes = [camera.focal_px, r, p.bilateral_sigma_px_scale, p.bilateral_max_radius_px, p.bilateral_max_taps]
        for axis, src, dst in ((0, depth, a), (1, a, out)):
            if self.launch.cpu:  # sixteen pixels a vector (pipeline.screen.native)
                if p.bilateral_max_taps:
                    self.launch(N.line_prefix_blocks, N.lines(w, h, axis), [src, w, h, axis, *sizes, sums])
                self.launch(N.bilateral_pass_blocks, N.blocks(w, h), [src, w, h, axis, *args, p.bilateral_max_taps,
                                                                      sums, dst])
            else:
                if p.bilateral_max_taps:
                    self.launch(F.line_prefix, h if axis == 0 else w, [src, w, h, axis, *sizes, sums])
                self.launch(F.bilateral_pass, w * h, [src, w, h, axis, *args, 0.0, p.bilateral_max_taps, sums, dst])
        return out

    def _narrow_range(self, depth: wp.array, camera: Camera, r: float, p: DatasetConfig) -> wp.array:
        w, h = camera.width, camera.height
        delta, mu = p.nrf_delta_radii * r, p.nrf_mu_radii * r
        taps = p.nrf_max_taps if p.filter_mode == "fast" else 0
        # ping-pong between two buffers; the input stays untouched
        bufs = [self._buffer("pass", w * h), self._buffer("nrf", w * h)]
        passes = 2 * p.nrf_iterations + (p.nrf_cleanup_radius_px > 0)
        src, k = depth, passes % 2  # so that the last pass lands in the "nrf" buffer
        for _ in range(p.nrf_iterations):
            for axis in (0, 1):
                dst = bufs[k]
                self.launch(F.narrow_range_pass, w * h, [src, w, h, axis, camera.focal_px, r, p.nrf_radius_scale,
                                                         p.nrf_max_radius_px, delta, mu, taps, dst])
                src, k = dst, 1 - k
        if p.nrf_cleanup_radius_px > 0:
            dst = bufs[k]
            self.launch(F.narrow_range_cleanup, w * h, [src, w, h, p.nrf_cleanup_radius_px, delta, mu, dst])
            src = dst
        return src

    def _normals(self, depth: wp.array, camera: Camera) -> wp.array:
        w, h = camera.width, camera.height
        out = self._buffer("normals", w * h, wp.vec3)
        self.launch(K.normals_from_depth, w * h, [depth, w, h, camera.focal_px, out])
        return out

    def _filter(self, name: str, depth: wp.array, camera: Camera, r: float, p: DatasetConfig) -> wp.array:
        if name == "gaussian":
            return self._gaussian(depth, camera.width, camera.height, p.gaussian_sigma_px)
        if name == "bilateral":
            return self._bilateral(depth, camera, r, p)
        if name == "nrf":
            return self._narrow_range(depth, camera, r, p)
        raise ValueError(f"unknown filter {name!r} (one of {', '.join(FILTERS)})")

    # ---- NumPy API ------------------------------------------------------------------------------

    def inputs(self, positions_world: np.ndarray | wp.array, radius: float, camera: Camera, p: DatasetConfig,
               filters: tuple[str, ...] = FILTERS, timings: Timings | None = None,
               ellipsoids: Ellipsoids | None = None, on_device: bool = False,
               raw_normals: bool = True) -> dict[str, np.ndarray]:
        """Splat, filter and differentiate one view: ``Z``, ``A``, ``thickness`` and per filter
        ``<f>.Z`` and ``<f>.N`` (H x W x 3).

        With ``ellipsoids`` the particles are drawn as those instead of spheres and every name
        takes an ``aniso`` prefix: ``aniso.Z``, ``aniso.A``, ``aniso.thickness``, ``aniso.N`` (the
        normals of the unfiltered ellipsoid depth, left out without ``raw_normals``: only the
        ``aniso`` method shows them), ``aniso_<f>.Z`` and ``aniso_<f>.N``, and where the ellipsoids
        carry their density ``aniso.density``, its largest value along each pixel's ray.
        ``on_device``: torch tensors on the device instead of host arrays (nothing comes to the
        host; on a GPU, for the refiner and the shader there)."""
        t = timings or Timings()
        shape = (camera.height, camera.width)
        aniso = ellipsoids is not None
        raw = "aniso." if aniso else ""

        def take(a: wp.array, shape: tuple[int, ...], on_device: bool):  # queued: one wait at the end
            return self._take(a, shape, on_device, wait=False)

        with t("splat"):
            density = None
            if aniso:
                depth, mask, thickness, _, density = self._splat_ellipsoids(ellipsoids, camera)
            else:
                depth, mask, thickness = self._splat(positions_world, radius, camera)
            out = {f"{raw}Z": take(depth, shape, on_device), f"{raw}A": take(mask, shape, on_device),
                   f"{raw}thickness": take(thickness, shape, on_device)}
            if density is not None:
                out[DENSITY_CHANNEL] = take(density, shape, on_device)
        if aniso and raw_normals:
            with t("normals"):
                out["aniso.N"] = take(self._normals(depth, camera), (*shape, 3), on_device)
        for name in filters:
            with t(name):
                d = self._filter(name, depth, camera, radius, p)
            key = f"aniso_{name}" if aniso else name
            with t("normals"):
                out[f"{key}.Z"] = take(d, shape, on_device)
                out[f"{key}.N"] = take(self._normals(d, camera), (*shape, 3), on_device)
        if on_device:
            torch_waits_for_warp(self.device)
        else:  # the maps' copies have landed before the host reads them
            wait_for_downloads(self.device)
        return out

    def motion(self, positions_world: np.ndarray, particle_motion: np.ndarray, radius: float, camera: Camera,
               depth: np.ndarray | None = None, on_device: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel screen motion (H x W x 4) of the front-most particles, from each particle's
        ``particle_motion`` (N x 4, e.g. ``pipeline.screen.motion.particle_motion``), and the
        H x W mask of pixels it reached.

        Particles are spheres of ``radius``; those whose front surface lies within a radius of the
        nearest count as front-most. ``depth`` (H x W view depth of the surface the frame shows,
        0 or inf where none) replaces that nearest depth, and saves a splat: particles within two
        radii of it count, a margin for filtered depths. ``on_device``: both as torch tensors left
        on the device (``inputs``). The positions and their motion may be torch tensors on the
        device (``particle_motion`` of tensors): Warp reads them where they lie."""
        w, h = camera.width, camera.height
        if depth is None:
            reference, band = self._splat(host(positions_world), radius, camera)[0], radius
        else:
            reference, band = self._upload("motion_depth", np.where(np.isfinite(depth), depth, 0.0)), 2 * radius
        total, weight = self._buffer("motion_sum", w * h, wp.vec4), self._buffer("motion_weight", w * h)
        total.zero_()
        weight.zero_()
        n = len(positions_world)
        if n:
            if is_tensor(positions_world):  # made on the device by torch: Warp reads them there
                import torch

                centers = camera.to_view(positions_world.to(torch.float64)).to(torch.float32).contiguous()
                motion = particle_motion.to(torch.float32).contiguous()
                warp_waits_for_torch(self.device)  # torch_waits_for_warp below keeps their memory till read
                centers, motion = wp.from_torch(centers, dtype=wp.vec3), wp.from_torch(motion, dtype=wp.vec4)
            else:
                centers = wp.array(camera.to_view(np.asarray(positions_world, np.float64)).astype(np.float32),
                                   dtype=wp.vec3, device=self.device)
                motion = wp.array(np.ascontiguousarray(particle_motion, np.float32), dtype=wp.vec4,
                                  device=self.device)
            self.launch.tasks(K.splat_motion, n, [[centers, motion, radius, camera.focal_px, w, h, r0, r1, reference,
                                                   band, total, weight] for r0, r1 in row_bands(self.launch, h)])
        out = self._buffer("motion", w * h, wp.vec4)
        self.launch(K.finish_motion, w * h, [total, weight, out])
        motion, covered = self._take(out, (h, w, 4), on_device), self._take(weight, (h, w), on_device) > 0
        if on_device or is_tensor(positions_world):
            torch_waits_for_warp(self.device)
        return motion, covered

    def splat(self, positions_world: np.ndarray, radius: float, camera: Camera) -> SplatResult:
        """Nearest sphere-surface depth, fluid mask and summed chord thickness per pixel."""
        shape = (camera.height, camera.width)
        depth, mask, thickness = self._splat(positions_world, radius, camera)
        return SplatResult(*(self._download(a, shape) for a in (depth, mask, thickness)))

    def splat_ellipsoids(self, ellipsoids: Ellipsoids, camera: Camera, normals: bool = True) -> SplatResult:
        """Nearest ellipsoid-surface depth, mask, summed chord thickness and (with ``normals``, a
        second pass) the analytic view-space normal of the nearest ellipsoid per pixel."""
        shape = (camera.height, camera.width)
        depth, mask, thickness, n, _ = self._splat_ellipsoids(ellipsoids, camera, with_normals=normals)
        return SplatResult(*(self._download(a, shape) for a in (depth, mask, thickness)),
                           normals=self._download(n, (*shape, 3)) if normals else None)

    def gaussian(self, depth: np.ndarray, sigma_px: float) -> np.ndarray:
        """Naive separable Gaussian blur restricted to fluid pixels (fixed screen-space size)."""
        h, w = depth.shape
        return self._download(self._gaussian(self._upload("input", depth), w, h, sigma_px), depth.shape)

    def bilateral(self, depth: np.ndarray, camera: Camera, particle_radius: float, p: DatasetConfig) -> np.ndarray:
        """Bilateral Gaussian; spatial sigma from the projected particle radius at each pixel
        (two separable passes in 'fast' mode, a full 2D window in 'exact' mode)."""
        return self._download(self._bilateral(self._upload("input", depth), camera, particle_radius, p), depth.shape)

    def narrow_range(self, depth: np.ndarray, camera: Camera, particle_radius: float,
                     p: DatasetConfig) -> np.ndarray:
        """Narrow-Range Filter: alternating separable passes, then the 2D clean-up pass."""
        d = self._narrow_range(self._upload("input", depth), camera, particle_radius, p)
        return self._download(d, depth.shape)

    def normals(self, depth: np.ndarray, camera: Camera) -> np.ndarray:
        """View-space unit normals (H x W x 3) of a depth map; zero vectors where empty."""
        return self._download(self._normals(self._upload("input", depth), camera), (*depth.shape, 3))

    def close(self) -> None:
        """Stop the thread pool and free the buffers."""
        self.launch.close()
        self._buffers.clear()
