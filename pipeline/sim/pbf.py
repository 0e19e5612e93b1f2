"""Position Based Fluids solver (Macklin & Mueller 2013) driving the kernels in ``kernels.py`` (the physics)
and ``native.py`` (the CPU fast path).

Each step: predict under gravity, cell sort (particles are reordered into grid order so a
neighbour walk touches nearby memory), one half neighbour list (each pair once), ``iterations``
density-constraint solves with collision projection, then velocity from the position change,
vorticity confinement and XSPH viscosity. Pair passes scatter to both particles of a pair and a
per-particle pass finishes each quantity, the two fused block by block in two phases per pass (even
blocks, then odd ones; no zeroing passes). On the CPU all of a step's passes run as one gang launch
per thread (``N.step_passes``), the phases separated by native barriers; on CUDA, or with
``gang = False``, pass by pass through ``Launcher.scatter_passes``, with the same sums. Emitters add
layers of particles on a schedule fixed by the step index, so a run resumed from a saved frame
continues exactly as an uninterrupted one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from pipeline.config import SceneConfig, SimulateConfig
from pipeline.parallel import Launcher
from pipeline.sim import kernels as K
from pipeline.sim import native as N
from pipeline.sim.seeding import EmitterSchedule, lattice_rest_sum, seed_fluid, wall_density_table
from pipeline.sph import poly6_coefficient, spacing

# Cells per kernel radius of the neighbour grid: 2 tests ~40% fewer candidates than 1.
CELLS_PER_H = 2

# Blocks per thread and phase of the pair passes on the CPU; threads take them as they come free.
BLOCKS_PER_THREAD = 1


class SimulationError(RuntimeError):
    """The simulation blew up; the message names the frame and the symptom."""


@dataclass(frozen=True)
class FrameStats:
    """Diagnostics of one output frame."""

    particles: int
    max_density_ratio: float
    mean_neighbours: float


@dataclass(frozen=True)
class PendingFrame:
    """A frame whose state and diagnostics are on their way to the host (``PBFSolver.begin_frame``):
    ready once the device has passed ``event`` (None on the CPU, where they already are)."""

    frame: int
    particles: int
    x: wp.array
    v: wp.array
    diagnostics: wp.array
    event: wp.Event | None


class PBFSolver:
    """Holds the particle state of one scene on one device and advances it frame by frame."""

    def __init__(self, scene: SceneConfig, params: SimulateConfig, device: str, seed: int = 0, *,
                 gang: bool = True, vector_scan: bool = True):
        """``gang`` and ``vector_scan`` (CPU only) choose between equal ways of one step, for the
        tests and benchmarks that compare them: all pair passes of a step as one gang launch (False:
        a launch per phase, the same sums), and the AVX-512 row scan of the neighbour search where
        the CPU has one (False: the scalar scan, the same lists)."""
        self.scene, self.params, self.device = scene, params, device
        r = params.particle_radius
        self.radius = r
        self.h = params.kernel_radius_factor * r
        self.dt = 1.0 / (params.fps * params.substeps)
        self.poly6_coef = poly6_coefficient(self.h)
        self.spiky_coef = -45.0 / (math.pi * self.h**6)
        # Mass such that an interior particle of the initial lattice (spacing 2r) is at rest density.
        self.mass = params.rest_density / lattice_rest_sum(spacing(r), self.h)
        dq = params.artificial_pressure_dq * self.h
        self.corr_w_dq = self.poly6_coef * (self.h**2 - dq**2) ** 3
        self.self_density = self.mass * self.poly6_coef * self.h**6
        self.lo = wp.vec3(*scene.domain_lo)
        self.hi = wp.vec3(*scene.domain_hi)

        rng = np.random.default_rng(seed)
        x0, v0 = seed_fluid(scene, r, rng)
        self.schedule = EmitterSchedule(scene.emitters, r, self.dt)
        self.capacity = len(x0) + self.schedule.total_particles(params.frames * params.substeps)
        if self.capacity == 0:
            raise SimulationError(f"scene {scene.name!r} has no particles")
        self.n = 0
        self.step_index = 0
        self.launch = Launcher(device, params.threads, reuse=True)
        # the pair passes: gather over full lists (CUDA's default) or scatter over half lists
        self.gather = params.pair_passes == "gather" or (params.pair_passes == "auto" and not self.launch.cpu)
        # a particle's list slots: its half list, or (gather) its whole neighbourhood
        self.list_capacity = params.max_neighbours * (2 if self.gather else 1)
        self.vector_scan, self.gang = vector_scan, gang
        self._allocate()
        self._upload_obstacles()
        self._append(x0, v0)

    # -- memory -----------------------------------------------------------------------------
    def _allocate(self) -> None:
        cap, dev, nb = self.capacity, self.device, self.list_capacity

        def vec() -> wp.array:
            return wp.zeros(cap, dtype=wp.vec3, device=dev)

        self.particle_x, self.x_sorted = vec(), vec()
        self.x_pred, self.x_pred_other = vec(), vec()
        self.particle_v, self.v_tmp = vec(), vec()
        self.particle_omega = vec()
        self.particle_id = wp.zeros(cap, dtype=int, device=dev)
        self.id_sorted = wp.zeros(cap, dtype=int, device=dev)
        self.particle_rho = wp.zeros(cap, dtype=float, device=dev)
        self.particle_lambda = wp.zeros(cap, dtype=float, device=dev)
        # radix sort needs room for 2 x count
        self.cell_keys = wp.zeros(2 * cap, dtype=wp.int64, device=dev)
        self.order = wp.zeros(2 * cap, dtype=int, device=dev)
        self.neighbour_count = wp.zeros(cap, dtype=int, device=dev)
        self.neighbour_span = wp.zeros(cap, dtype=int, device=dev)
        self.neighbour_start = wp.zeros(cap, dtype=int, device=dev)
        self.neighbour_end = wp.zeros(cap, dtype=int, device=dev)
        self.neighbour_cursor = wp.zeros(cap, dtype=int, device=dev)
        # 8 slots of padding: the pair loops compute whole vectors of 8 pairs, reading up to 7 past a list
        self.neighbour_index = wp.zeros(cap * nb + 8, dtype=int, device=dev)
        self.pair = wp.zeros(cap * nb, dtype=wp.vec4, device=dev)
        self.wall_grad = vec()
        # pair-sum accumulators of the scatter passes
        self.acc4 = wp.zeros(cap, dtype=wp.vec4, device=dev)
        self.acc1 = wp.zeros(cap, dtype=float, device=dev)
        self.acc3a, self.acc3b = vec(), vec()
        self.omega_length = wp.zeros(cap, dtype=float, device=dev)
        self.particle_vol = wp.zeros(cap, dtype=float, device=dev)
        # a frame's output: the state in id order on the device, and two host copies (pinned on CUDA,
        # so the copies run while the host goes on) that alternate from frame to frame
        self.out_x, self.out_v = vec(), vec()
        self.diagnostics = wp.zeros(K.DIAG_SIZE, dtype=float, device=dev)
        pinned = wp.get_device(dev).is_cuda
        self._host = [(wp.empty(cap, dtype=wp.vec3, device="cpu", pinned=pinned),
                       wp.empty(cap, dtype=wp.vec3, device="cpu", pinned=pinned),
                       wp.empty(K.DIAG_SIZE, dtype=float, device="cpu", pinned=pinned)) for _ in range(2)]
        self.wall_table = wp.array(wall_density_table(2.0 * self.radius, self.h), dtype=wp.vec2, device=dev)
        # (start, end) of the pair-pass blocks (``Launcher.scatter_blocks``: at most 2 x BLOCKS_PER_THREAD a thread)
        self.block_bounds = wp.zeros(2 * BLOCKS_PER_THREAD * self.launch.threads, dtype=wp.vec2i, device=dev)
        self.pass_constants = self._pass_constants()
        self._arrangements: dict[tuple[int, ...], N.PassArrays] = {}
        # Dense grid of cells of width h over the container.
        extent = np.asarray(self.scene.domain_hi) - np.asarray(self.scene.domain_lo)
        self.cell_width = self.h / CELLS_PER_H
        dims = [max(1, math.ceil(e / self.cell_width)) for e in extent]
        self.grid_dims = wp.vec3i(*dims)
        self.num_cells = int(np.prod(dims))
        self.cell_start = wp.zeros(self.num_cells + 1, dtype=int, device=dev)
        # sort keys (cell << id_bits) | id: the order of cell * capacity + id, but a shift, not a
        # 64-bit division, recovers the cell (the cell starts took 1.0 ms per step with the division)
        self.id_bits = max(1, int(math.ceil(math.log2(cap))))
        self.key_bits = self.id_bits + max(1, int(math.ceil(math.log2(self.num_cells + 1))))

    def _upload_obstacles(self) -> None:
        spheres = [(*o.center, o.radius) for o in self.scene.obstacles if o.shape == "sphere"]
        boxes = [o for o in self.scene.obstacles if o.shape == "box"]
        dev = self.device
        self.spheres = wp.array(np.array(spheres, np.float32).reshape(-1, 4), dtype=wp.vec4, device=dev)
        self.box_lo = wp.array(np.array([b.lo for b in boxes], np.float32).reshape(-1, 3), dtype=wp.vec3,
                               device=dev)
        self.box_hi = wp.array(np.array([b.hi for b in boxes], np.float32).reshape(-1, 3), dtype=wp.vec3,
                               device=dev)

    def _append(self, x: np.ndarray, v: np.ndarray) -> None:
        """Add particles at the end of the active range, with the next ids."""
        k = len(x)
        if k == 0:
            return
        if self.n + k > self.capacity:
            raise SimulationError("emitter produced more particles than the precomputed capacity")
        dev = self.device
        wp.copy(self.particle_x, wp.array(x.astype(np.float32), dtype=wp.vec3, device=dev), self.n, 0, k)
        wp.copy(self.particle_v, wp.array(v.astype(np.float32), dtype=wp.vec3, device=dev), self.n, 0, k)
        ids = np.arange(self.n, self.n + k, dtype=np.int32)
        wp.copy(self.particle_id, wp.array(ids, dtype=int, device=dev), self.n, 0, k)
        self.n += k

    # -- state ------------------------------------------------------------------------------
    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities (float32, N x 3) in stable particle-id order."""
        n = self.n
        out_x = wp.zeros(n, dtype=wp.vec3, device=self.device)
        out_v = wp.zeros(n, dtype=wp.vec3, device=self.device)
        self.launch(K.scatter_by_id, n, [self.particle_id, self.particle_x, out_x])
        self.launch(K.scatter_by_id, n, [self.particle_id, self.particle_v, out_v])
        return out_x.numpy(), out_v.numpy()

    def set_state(self, x: np.ndarray, v: np.ndarray, step_index: int) -> None:
        """Restore a saved frame (positions and velocities in id order) at a given step count."""
        self.n = 0
        self._append(x, v)
        self.step_index = step_index

    # -- stepping ---------------------------------------------------------------------------
    def predict_and_search(self) -> list[tuple[int, int]]:
        """The start of a step: predict positions under gravity, sort into cell order and build the
        half neighbour lists on the predicted positions (``x_pred``); returns the blocks of the
        pair passes."""
        p, n, launch = self.params, self.n, self.launch
        obstacles = [self.spheres, self.box_lo, self.box_hi]
        bounds = [self.lo, self.hi, self.radius]
        g = wp.vec3(*p.gravity)
        # Predict, then sort into cell order (radix sort of (cell << id_bits) | id).
        grid = [self.lo, 1.0 / self.cell_width, self.grid_dims]
        launch(K.predict_positions, n, [self.particle_x, self.particle_v, g, self.dt, *bounds, *obstacles,
                                        *grid[1:], self.particle_id, self.id_bits,
                                        self.v_tmp, self.x_pred, self.cell_keys, self.order])
        wp.utils.radix_sort_pairs(self.cell_keys, self.order, n, end_bit=self.key_bits)
        launch(K.find_cell_starts, n + 1, [self.cell_keys, n, self.id_bits, self.num_cells, self.cell_start])
        launch(K.gather_state, n, [self.order, self.particle_x, self.x_pred, self.v_tmp, self.particle_id,
                                   self.x_sorted, self.x_pred_other, self.particle_v, self.id_sorted])
        self.particle_x, self.x_sorted = self.x_sorted, self.particle_x
        self.particle_id, self.id_sorted = self.id_sorted, self.particle_id
        self.x_pred, self.x_pred_other = self.x_pred_other, self.x_pred
        if self.gather:
            launch(K.find_all_neighbours, n, [self.x_pred, self.cell_start, *grid, CELLS_PER_H, self.h,
                                              self.list_capacity, self.neighbour_count, self.neighbour_start,
                                              self.neighbour_end, self.neighbour_index])
            return [(0, n)]
        self.neighbour_cursor.zero_()
        launch(N.find_neighbours, n, [self.x_pred, self.cell_start, *grid, CELLS_PER_H, self.h, p.max_neighbours,
                                      int(self.vector_scan), int(launch.cpu), self.neighbour_cursor,
                                      self.neighbour_count, self.neighbour_span, self.neighbour_start,
                                      self.neighbour_end, self.neighbour_index])
        # Blocks for the pair passes: how far past itself a particle's pairs reach bounds their
        # size, the pair counts balance them (CPU only; on CUDA atomics make one launch safe).
        blocks = [(0, n)]
        if launch.cpu:
            counts = self.neighbour_count.numpy()[:n]
            blocks = launch.scatter_blocks(n, int(self.neighbour_span.numpy()[:n].max()),
                                           np.concatenate([[0], np.cumsum(counts)]), BLOCKS_PER_THREAD)
        return blocks

    def step(self) -> None:
        """One solver step of length dt."""
        n, launch = self.n, self.launch
        x_new, v_new = self.schedule.emit(self.step_index)
        if len(x_new):
            self._append(x_new, v_new)
            n = self.n
        if n == 0:  # an emitter that has not started yet
            self.step_index += 1
            return
        blocks = self.predict_and_search()
        if self.gather:
            self._gather_passes()
        elif launch.cpu and self.gang:
            self._gang_passes(blocks)
        else:
            launch.scatter_passes(blocks, self._passes())
        self.particle_x, self.x_pred = self.x_pred, self.particle_x
        self.step_index += 1

    def _pass_constants(self) -> N.PassConstants:
        """The scalars of the pair passes, as the gang kernel takes them."""
        p = self.params
        c = N.PassConstants()
        c.iterations = p.iterations
        c.h, c.poly6_coef, c.spiky_coef = self.h, self.poly6_coef, self.spiky_coef
        c.mass, c.vol = self.mass, self.mass / p.rest_density
        c.corr_k, c.inv_corr_w_dq, c.corr_n = p.artificial_pressure_k, 1.0 / self.corr_w_dq, p.artificial_pressure_n
        c.self_density, c.rest_density, c.relaxation = self.self_density, p.rest_density, p.relaxation
        c.lo, c.hi, c.radius = self.lo, self.hi, self.radius
        c.inv_dt, c.vorticity_eps, c.xsph_c, c.dt = 1.0 / self.dt, p.vorticity_epsilon, p.xsph_viscosity, self.dt
        return c

    def _gang_passes(self, blocks: list[tuple[int, int]]) -> None:
        """Every pair pass of the step as one gang launch (the CPU): ``N.step_passes``."""
        bounds = self.block_bounds.numpy()  # a view of the CPU array
        bounds[: len(blocks)] = [(start, start + count) for start, count in blocks]
        passes = 2 * self.params.iterations + 2
        self.launch.gang(N.step_passes, 2 * passes + 1, [self.block_bounds, len(blocks), self.pass_constants,
                                                         self._pass_arrays()])

    def _pass_arrays(self) -> N.PassArrays:
        """The pair passes' arrays as they stand this step (the buffers trade places from step to step;
        each arrangement gets one struct, so a recorded launch replays with the right arrays)."""
        arrays = {"x_pred": self.x_pred, "particle_x": self.particle_x, "v_tmp": self.v_tmp,
                  "particle_v": self.particle_v, "neighbour_start": self.neighbour_start,
                  "neighbour_end": self.neighbour_end, "neighbour_index": self.neighbour_index, "pair": self.pair,
                  "acc4": self.acc4, "acc1": self.acc1, "acc3a": self.acc3a, "acc3b": self.acc3b,
                  "particle_rho": self.particle_rho, "particle_lambda": self.particle_lambda,
                  "wall_grad": self.wall_grad, "particle_omega": self.particle_omega,
                  "omega_length": self.omega_length, "particle_vol": self.particle_vol, "wall": self.wall_table,
                  "spheres": self.spheres, "box_lo": self.box_lo, "box_hi": self.box_hi}
        key = tuple(id(a) for a in arrays.values())
        struct = self._arrangements.get(key)
        if struct is None:
            struct = self._arrangements[key] = N.PassArrays()
            for name, array in arrays.items():
                setattr(struct, name, array)
        return struct

    def _gather_passes(self) -> None:
        """The step's passes over full lists, each particle summing its own pairs and finishing
        itself (``K.*_gather``): two launches an iteration, two for the velocities."""
        p, n, launch = self.params, self.n, self.launch
        obstacles = [self.spheres, self.box_lo, self.box_hi]
        nb = [self.neighbour_start, self.neighbour_end, self.neighbour_index]
        vol = self.mass / p.rest_density
        for it in range(p.iterations):
            launch(K.density_gather, n, [
                self.x_pred, *nb, self.h, self.poly6_coef, self.spiky_coef * vol, self.mass, p.artificial_pressure_k,
                1.0 / self.corr_w_dq, p.artificial_pressure_n, self.pair, self.acc4, self.acc1, self.self_density,
                vol, p.rest_density, p.relaxation, self.lo, self.hi, self.wall_table, *obstacles, self.particle_rho,
                self.particle_lambda, self.wall_grad])
            launch(K.correction_gather, n, [
                self.particle_lambda, *nb, self.pair, self.acc3a, self.x_pred, self.wall_grad, self.lo, self.hi,
                self.radius, *obstacles, self.particle_x, 1.0 / self.dt, int(it == p.iterations - 1), self.v_tmp])
        launch(K.vorticity_gather, n, [self.x_pred, self.v_tmp, *nb, self.h, self.poly6_coef, self.spiky_coef, vol,
                                       self.pair, self.particle_omega, self.particle_rho, self.mass,
                                       self.omega_length, self.particle_vol])
        launch(K.viscosity_gather, n, [self.v_tmp, self.omega_length, self.particle_vol, *nb, self.pair, self.acc3a,
                                       self.acc3b, self.particle_omega, p.vorticity_epsilon, p.xsph_viscosity, self.dt,
                                       self.particle_v])

    def _passes(self) -> list[tuple]:
        """The step's pair passes for ``Launcher.scatter_passes`` (CUDA: one block, atomics)."""
        p = self.params
        obstacles = [self.spheres, self.box_lo, self.box_hi]
        bounds = [self.lo, self.hi, self.radius]
        nb = [self.neighbour_start, self.neighbour_end, self.neighbour_index]
        vol = self.mass / p.rest_density
        passes = []
        for it in range(p.iterations):
            passes.append((
                N.density_pairs, [self.x_pred, *nb, self.h, self.poly6_coef, self.spiky_coef, self.mass, vol,
                                  p.artificial_pressure_k, 1.0 / self.corr_w_dq, p.artificial_pressure_n, self.pair,
                                  self.acc4, self.acc1],
                N.density_finish, [self.x_pred, self.acc4, self.acc1, self.h, self.self_density, vol, p.rest_density,
                                   p.relaxation, self.lo, self.hi, self.wall_table, *obstacles,
                                   self.particle_rho, self.particle_lambda, self.wall_grad]))
            passes.append((
                N.correction_pairs, [self.particle_lambda, *nb, self.pair, self.acc3a],
                N.correction_finish, [self.x_pred, self.particle_lambda, self.acc3a, self.wall_grad, *bounds,
                                      *obstacles, self.particle_x, 1.0 / self.dt, int(it == p.iterations - 1),
                                      self.v_tmp]))
        passes.append((
            N.vorticity_pairs, [self.x_pred, self.v_tmp, *nb, self.h, self.poly6_coef, self.spiky_coef, vol, self.pair,
                                self.particle_omega],
            N.vorticity_finish, [self.particle_omega, self.particle_rho, self.mass, self.omega_length,
                                 self.particle_vol]))
        passes.append((
            N.viscosity_pairs, [self.v_tmp, self.omega_length, self.particle_vol, *nb, self.pair, self.acc3a,
                                self.acc3b],
            N.viscosity_finish, [self.v_tmp, self.particle_omega, self.acc3a, self.acc3b, p.vorticity_epsilon,
                                 p.xsph_viscosity, self.dt, self.particle_v]))
        return passes

    def advance_frame(self, frame: int) -> FrameStats:
        """Run one frame's substeps and check for a blow-up (NaN, escape, runaway density)."""
        stats, _, _ = self.finish_frame(self.begin_frame(frame))
        return stats

    def begin_frame(self, frame: int) -> PendingFrame:
        """Queue one frame's substeps, then its state in id order and its diagnostics on their way to
        the host, and return without waiting for the device. Finish a frame (``finish_frame``) before
        beginning the one after next: two frames' host copies alternate."""
        for _ in range(self.params.substeps):
            self.step()
        n, dev = self.n, self.device
        host_x, host_v, host_diag = self._host[frame % 2]
        self.diagnostics.zero_()
        if n:
            self.launch(K.scatter_by_id, n, [self.particle_id, self.particle_x, self.out_x])
            self.launch(K.scatter_by_id, n, [self.particle_id, self.particle_v, self.out_v])
            margin = wp.vec3(1e-3, 1e-3, 1e-3)
            wp.launch(K.frame_diagnostics, n, [self.particle_x, self.particle_v, self.particle_rho,
                                               self.neighbour_count, self.lo - margin, self.hi + margin,
                                               self.diagnostics], device=dev)
            wp.copy(host_x, self.out_x, count=n)
            wp.copy(host_v, self.out_v, count=n)
        wp.copy(host_diag, self.diagnostics)
        device = wp.get_device(dev)
        event = device.stream.record_event() if device.is_cuda else None
        return PendingFrame(frame, n, host_x, host_v, host_diag, event)

    def finish_frame(self, pending: PendingFrame) -> tuple[FrameStats, np.ndarray, np.ndarray]:
        """Wait for a begun frame, check it for a blow-up (non-finite values, a runaway speed, an escape
        from the container, a runaway density) and return its stats, positions and velocities (id
        order, copies the caller may keep)."""
        if pending.event is not None:
            wp.synchronize_event(pending.event)
        n, frame = pending.particles, pending.frame
        d = pending.diagnostics.numpy()
        if d[K.DIAG_NONFINITE] > 0:
            raise SimulationError(f"blow-up at frame {frame}: non-finite positions, velocities or densities")
        speed = math.sqrt(float(d[K.DIAG_MAX_SPEED2]))
        if speed > self.params.max_speed:
            raise SimulationError(f"blow-up at frame {frame}: a particle moves at {speed:.0f} m/s")
        if d[K.DIAG_OUTSIDE] > 0:
            raise SimulationError(f"blow-up at frame {frame}: particles left the container")
        ratio = float(d[K.DIAG_MAX_DENSITY]) / self.params.rest_density if n else 0.0
        if ratio > 3.0:
            raise SimulationError(f"blow-up at frame {frame}: density {ratio:.1f}x rest")
        # a half list stores each pair once: a particle has twice as many neighbours on average
        mean_nb = (1.0 if self.gather else 2.0) * float(d[K.DIAG_NEIGHBOURS]) / n if n else 0.0
        x, v = pending.x.numpy()[:n].copy(), pending.v.numpy()[:n].copy()
        return FrameStats(n, ratio, mean_nb), x, v

    def close(self) -> None:
        """Release the thread pool."""
        self.launch.close()
