"""Position Based Fluids (Macklin & Mueller, TOG 2013) in Taichi: the project's solver as a peer.

The same algorithm and constants as ``pipeline/sim`` (``pbf.py``, ``kernels.py``, ``seeding.py``),
so that a speed ratio compares implementations, not physics:

- predict v* = v + dt g, x* = x + dt v*, clamped into the container (centres at least r from a wall);
- neighbours within h of x*, found once per step and kept through the iterations;
- per iteration (Jacobi): rho_i = m W(0) + sum_j m W_ij + m rho_wall(d) with poly6 W and a
  precomputed wall table (fluid at rest mirrored behind each wall); g_ij = V spiky grad W_ij with
  V = m / rho_0; a unilateral constraint C_i = max(rho_i / rho_0 - 1, 0);
  lambda_i = -C_i / (sum_j |g_ij|^2 + |sum_j g_ij + V grad rho_wall|^2 + eps);
  dp_i = sum_j (lambda_i + lambda_j + s_corr) g_ij + lambda_i V grad rho_wall, with the artificial
  pressure s_corr = -k (W_ij / W(dq))^n, the correction capped at r, then the wall clamp;
- v = (x* - x) / dt; vorticity omega_i = sum_j V (v_j - v_i) x grad_j W_ij; XSPH
  v += c sum_j (m / rho_j) (v_j - v_i) W_ij and confinement v += dt eps (N x omega),
  N = eta / |eta|, eta_i = sum_j (m / rho_j) grad W_ij (|omega_j| - |omega_i|);
- the same mass (the initial lattice at rest density), the same initial particles and jitter.

The data layout is Taichi's own, written for speed on its CPU backend: particles are counting-
sorted into cells of h/2 every step (rows of cells are contiguous, as in the project), a full
neighbour list per particle (all neighbours within h) and gathered sums, so every loop is a plain
parallel loop without atomics. Walls are the container only (the benchmark has no obstacles).

    .venv/bin/python benchmarks/peers/taichi_pbf.py --particles 50000 --steps 40 --threads 2
"""

import argparse
import dataclasses
import math
import os
import sys

import numpy as np
import taichi as ti

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import dam_break  # noqa: E402

from pipeline.sim.seeding import lattice_rest_sum, seed_fluid, wall_density_table  # noqa: E402
from pipeline.sph import poly6_coefficient, spacing  # noqa: E402

# The same neighbour grid as the project's solver: cells of h / 2, scanned two cells each way.
CELLS_PER_H = 2


@ti.data_oriented
class TaichiPBF:
    """A PBF over particles ``x0``, ``v0`` (N x 3) with parameters ``p`` (a SimulateConfig) in the box [lo, hi]."""

    def __init__(self, x0: np.ndarray, v0: np.ndarray, p, domain_lo, domain_hi):
        # constants, read by the kernels at compile time
        self.gravity = tuple(float(c) for c in p.gravity)
        self.rest_density, self.relaxation, self.iterations = p.rest_density, p.relaxation, p.iterations
        self.corr_k, self.corr_n = p.artificial_pressure_k, p.artificial_pressure_n
        self.xsph_c, self.vorticity_eps = p.xsph_viscosity, p.vorticity_epsilon
        n = len(x0)
        r = p.particle_radius
        h = p.kernel_radius_factor * r
        self.n, self.radius, self.h = n, r, h
        self.dt = 1.0 / (p.fps * p.substeps)
        self.poly6 = poly6_coefficient(h)
        self.spiky = -45.0 / (math.pi * h**6)
        self.mass = p.rest_density / lattice_rest_sum(spacing(r), h)
        self.vol = self.mass / p.rest_density
        dq = p.artificial_pressure_dq * h
        self.inv_corr_w_dq = 1.0 / (self.poly6 * (h**2 - dq**2) ** 3)
        self.self_density = self.mass * self.poly6 * h**6
        self.max_neighbours = 2 * p.max_neighbours  # the project's cap is on a half list
        self.lo = tuple(float(c) for c in domain_lo)
        self.hi = tuple(float(c) for c in domain_hi)
        self.cell_width = h / CELLS_PER_H
        self.dims = [max(1, math.ceil((b - a) / self.cell_width)) for a, b in zip(self.lo, self.hi, strict=True)]
        self.num_cells = int(np.prod(self.dims))
        table = wall_density_table(spacing(r), h)
        self.table_size = len(table)
        f32, i32 = ti.f32, ti.i32
        # two copies of the sortable state: a step gathers one into the other in cell order
        self.particle_x = [ti.Vector.field(3, f32, n) for _ in range(2)]
        self.particle_v = [ti.Vector.field(3, f32, n) for _ in range(2)]
        self.particle_id = [ti.field(i32, n) for _ in range(2)]
        self.x_pred = [ti.Vector.field(3, f32, n) for _ in range(2)]
        self.v_pred = ti.Vector.field(3, f32, n)
        self.particle_rho = ti.field(f32, n)
        self.particle_lambda = ti.field(f32, n)
        self.wall_grad = ti.Vector.field(3, f32, n)
        self.particle_omega = ti.Vector.field(3, f32, n)
        self.omega_length = ti.field(f32, n)
        self.particle_cell = ti.field(i32, n)
        self.order = ti.field(i32, n)
        self.cell_start = ti.field(i32, self.num_cells + 1)
        self.cell_cursor = ti.field(i32, self.num_cells + 1)
        self.neighbour_count = ti.field(i32, n)
        self.neighbour_index = ti.field(i32, (n, self.max_neighbours))
        self.wall_table = ti.Vector.field(2, f32, self.table_size)
        self.current = 0
        self.wall_table.from_numpy(table)
        self.particle_x[0].from_numpy(x0.astype(np.float32))
        self.particle_v[0].from_numpy(v0.astype(np.float32))
        self.particle_id[0].from_numpy(np.arange(n, dtype=np.int32))

    def field_bytes(self) -> int:
        """Bytes of every field the solver allocated."""
        n, nb = self.n, self.max_neighbours
        per_particle = 4 * (2 * 3 + 2 * 3 + 2 + 2 * 3 + 3 + 1 + 1 + 3 + 3 + 1 + 1 + 1 + 1 + nb)
        return n * per_particle + 8 * (self.num_cells + 1) + 8 * self.table_size

    # -- helpers (inlined into the kernels) ------------------------------------------------
    @ti.func
    def cell_coord(self, x):
        q = (x - ti.Vector(self.lo, ti.f32)) * (1.0 / self.cell_width)
        return ti.Vector([ti.math.clamp(int(ti.floor(q[a])), 0, self.dims[a] - 1) for a in ti.static(range(3))])

    @ti.func
    def cell_linear(self, c):
        return (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]

    @ti.func
    def clamp_to_box(self, x):
        r = self.radius
        return ti.Vector([ti.math.clamp(x[a], self.lo[a] + r, self.hi[a] - r) for a in ti.static(range(3))])

    @ti.func
    def pair_weights(self, r, grad_coef):
        """(spiky gradient times grad_coef, poly6 W) of one pair, with the project's clamps."""
        h = self.h
        r2 = r.dot(r)
        d = ti.max(h * h - r2, 0.0)
        rl = ti.max(ti.sqrt(r2), 1.0e-9)
        e = ti.max(h - rl, 0.0)
        return r * (grad_coef * e * e / rl), self.poly6 * d * d * d

    @ti.func
    def wall_lookup(self, d):
        """(density per unit mass, derivative) of the virtual fluid behind a wall at distance d."""
        out = ti.Vector([0.0, 0.0], ti.f32)
        if d < self.h:
            u = ti.max(d, 0.0) / self.h * float(self.table_size - 1)
            k = ti.min(int(u), self.table_size - 2)
            t = u - float(k)
            out = self.wall_table[k] * (1.0 - t) + self.wall_table[k + 1] * t
        return out

    @ti.func
    def boundary_density(self, x):
        """(gradient xyz, density per unit mass) of the six container walls."""
        grad = ti.Vector([0.0, 0.0, 0.0], ti.f32)
        rho = 0.0
        for a in ti.static(range(3)):
            # one name per value: reassigning a ti.func's vector result here kept the first value
            lower = self.wall_lookup(x[a] - self.lo[a])
            upper = self.wall_lookup(self.hi[a] - x[a])
            grad[a] += lower[1] - upper[1]
            rho += lower[0] + upper[0]
        return grad, rho

    # -- kernels ---------------------------------------------------------------------------
    @ti.kernel
    def predict(self, x: ti.template(), v: ti.template(), x_pred: ti.template()):
        g = ti.Vector(self.gravity, ti.f32)
        for i in range(self.n):
            vi = v[i] + g * self.dt
            v[i] = vi
            xp = self.clamp_to_box(x[i] + vi * self.dt)
            x_pred[i] = xp
            self.particle_cell[i] = self.cell_linear(self.cell_coord(xp))

    @ti.kernel
    def count_sort(self):
        """Stable counting sort by cell: order[k] is the particle at sorted place k."""
        for c in self.cell_start:
            self.cell_start[c] = 0
        for i in range(self.n):
            ti.atomic_add(self.cell_start[self.particle_cell[i] + 1], 1)
        ti.loop_config(serialize=True)
        for c in range(self.num_cells):
            self.cell_start[c + 1] += self.cell_start[c]
        for c in self.cell_start:
            self.cell_cursor[c] = self.cell_start[c]
        ti.loop_config(serialize=True)
        for i in range(self.n):
            c = self.particle_cell[i]
            self.order[self.cell_cursor[c]] = i
            self.cell_cursor[c] += 1

    @ti.kernel
    def gather(self, x: ti.template(), v: ti.template(), ids: ti.template(), x_pred: ti.template(),
               x_out: ti.template(), v_out: ti.template(), ids_out: ti.template(), x_pred_out: ti.template()):
        for k in range(self.n):
            src = self.order[k]
            x_out[k] = x[src]
            v_out[k] = v[src]
            ids_out[k] = ids[src]
            x_pred_out[k] = x_pred[src]

    @ti.kernel
    def find_neighbours(self, x_pred: ti.template()):
        h2 = self.h * self.h
        reach = ti.static(CELLS_PER_H)
        for i in range(self.n):
            xi = x_pred[i]
            c = self.cell_coord(xi)
            x0 = ti.max(c[0] - reach, 0)
            x1 = ti.min(c[0] + reach, self.dims[0] - 1)
            count = 0
            for dz in range(-reach, reach + 1):
                z = c[2] + dz
                if 0 <= z < self.dims[2]:
                    for dy in range(-reach, reach + 1):
                        y = c[1] + dy
                        if 0 <= y < self.dims[1]:
                            row = (z * self.dims[1] + y) * self.dims[0]
                            for j in range(self.cell_start[row + x0], self.cell_start[row + x1 + 1]):
                                if j != i and (x_pred[j] - xi).norm_sqr() < h2 and count < self.max_neighbours:
                                    self.neighbour_index[i, count] = j
                                    count += 1
            self.neighbour_count[i] = count

    @ti.kernel
    def solve_density(self, x_pred: ti.template()):
        """rho_i and lambda_i."""
        grad_coef = self.spiky * self.vol
        for i in range(self.n):
            xi = x_pred[i]
            grad = ti.Vector([0.0, 0.0, 0.0], ti.f32)
            rho = 0.0
            sq = 0.0
            for k in range(self.neighbour_count[i]):
                g, w = self.pair_weights(xi - x_pred[self.neighbour_index[i, k]], grad_coef)
                grad += g
                rho += self.mass * w
                sq += g.dot(g)
            wg, wrho = self.boundary_density(xi)
            rho = self.self_density + rho + self.mass * wrho
            gw = wg * self.vol
            self.wall_grad[i] = gw
            grad += gw
            c = ti.max(rho / self.rest_density - 1.0, 0.0)
            self.particle_rho[i] = rho
            self.particle_lambda[i] = -c / (sq + grad.dot(grad) + self.relaxation)

    @ti.kernel
    def solve_correction(self, x_pred: ti.template(), x: ti.template(), x_out: ti.template(), last: ti.i32):
        """x_i + dp_i, capped at r, clamped into the box; after the last iteration v = (x* - x) / dt."""
        grad_coef = self.spiky * self.vol
        for i in range(self.n):
            xi = x_pred[i]
            li = self.particle_lambda[i]
            dp = ti.Vector([0.0, 0.0, 0.0], ti.f32)
            for k in range(self.neighbour_count[i]):
                j = self.neighbour_index[i, k]
                g, w = self.pair_weights(xi - x_pred[j], grad_coef)
                scorr = 0.0
                if ti.static(self.corr_k > 0.0):
                    ratio = w * self.inv_corr_w_dq
                    power = 1.0
                    for _ in ti.static(range(self.corr_n)):
                        power *= ratio
                    scorr = -self.corr_k * power
                dp += g * (li + self.particle_lambda[j] + scorr)
            dp += self.wall_grad[i] * li
            dl = dp.norm()
            if dl > self.radius:
                dp *= self.radius / dl
            xn = self.clamp_to_box(xi + dp)
            x_out[i] = xn
            if last != 0:
                self.v_pred[i] = (xn - x[i]) * (1.0 / self.dt)

    @ti.kernel
    def vorticity(self, x_pred: ti.template()):
        for i in range(self.n):
            xi = x_pred[i]
            vi = self.v_pred[i]
            omega = ti.Vector([0.0, 0.0, 0.0], ti.f32)
            for k in range(self.neighbour_count[i]):
                j = self.neighbour_index[i, k]
                g, _ = self.pair_weights(xi - x_pred[j], self.spiky)
                omega += (self.v_pred[j] - vi).cross(-g) * self.vol
            self.particle_omega[i] = omega
            self.omega_length[i] = omega.norm()

    @ti.kernel
    def viscosity(self, x_pred: ti.template(), x: ti.template(), v: ti.template()):
        """XSPH and vorticity confinement into v; x = x*."""
        for i in range(self.n):
            xi = x_pred[i]
            vi = self.v_pred[i]
            wi = self.omega_length[i]
            eta = ti.Vector([0.0, 0.0, 0.0], ti.f32)
            visc = ti.Vector([0.0, 0.0, 0.0], ti.f32)
            for k in range(self.neighbour_count[i]):
                j = self.neighbour_index[i, k]
                g, w = self.pair_weights(xi - x_pred[j], self.spiky)
                volj = self.mass / self.particle_rho[j]
                eta += g * ((self.omega_length[j] - wi) * volj)
                visc += (self.v_pred[j] - vi) * (w * volj)
            vn = vi + visc * self.xsph_c
            if ti.static(self.vorticity_eps > 0.0):
                el = eta.norm()
                if el > 1.0e-9:
                    vn += (eta / el).cross(self.particle_omega[i]) * (self.vorticity_eps * self.dt)
            v[i] = vn
            x[i] = xi

    # -- host ------------------------------------------------------------------------------
    def step(self):
        a, b = self.current, 1 - self.current
        x, v, ids = self.particle_x, self.particle_v, self.particle_id
        self.predict(x[a], v[a], self.x_pred[a])
        self.count_sort()
        self.gather(x[a], v[a], ids[a], self.x_pred[a], x[b], self.v_pred, ids[b], self.x_pred[b])
        self.find_neighbours(self.x_pred[b])
        pred = b
        for it in range(self.iterations):
            self.solve_density(self.x_pred[pred])
            self.solve_correction(self.x_pred[pred], x[b], self.x_pred[1 - pred], int(it == self.iterations - 1))
            pred = 1 - pred
        self.vorticity(self.x_pred[pred])
        self.viscosity(self.x_pred[pred], x[b], v[b])
        self.current = b

    def state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and densities (float32) in particle-id order."""
        c = self.current
        order = np.argsort(self.particle_id[c].to_numpy())
        return (self.particle_x[c].to_numpy()[order], self.particle_v[c].to_numpy()[order],
                self.particle_rho.to_numpy()[order])



def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=50_000)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--warmup", type=int, default=dam_break.WARMUP_STEPS, help="untimed steps first")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads (0: one per core)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arch", choices=("cpu", "cuda"), default="cpu", help="Taichi's backend")
    parser.add_argument("--state", help="write positions, velocities and densities after the run (.npz)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="change a solver parameter (SimulateConfig field), e.g. iterations=2")
    args = parser.parse_args()
    threads = args.threads or os.cpu_count() or 1
    import taichi as ti

    if args.arch == "cuda":
        ti.init(arch=ti.cuda, default_fp=ti.f32, log_level=ti.WARN)
    else:
        ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f32, log_level=ti.WARN)
    scene, p = dam_break.scene(), dam_break.params(args.particles, threads)
    for item in args.set:
        key, _, value = item.partition("=")
        p = dataclasses.replace(p, **{key: type(getattr(p, key))(value)})
    x0, v0 = seed_fluid(scene, p.particle_radius, np.random.default_rng(args.seed))
    before = dam_break.resident_bytes()
    solver = TaichiPBF(x0, v0, p, scene.domain_lo, scene.domain_hi)
    for _ in range(args.warmup):
        solver.step()
    ti.sync()
    seconds, rates = dam_break.time_steps(solver.step, ti.sync, args.steps)
    memory = dam_break.resident_bytes() - before
    if args.state:
        x, v, rho = solver.state()
        np.savez(args.state, x=x, v=v, rho=rho, steps=args.warmup + args.steps)
    print(dam_break.Measurement("Taichi PBF", solver.n, args.steps, seconds, rates, memory, threads,
                                {"taichi": ti.__version__, "field_bytes": solver.field_bytes(),
                                 "arch": args.arch}).to_json())


if __name__ == "__main__":
    main()
