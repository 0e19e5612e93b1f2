"""Warp kernels of Position Based Fluids (Macklin & Mueller, "Position Based Fluids", TOG 2013): the
physics, portable to the CPU and CUDA alike.

Density constraint C_i = rho_i / rho_0 - 1 (unilateral: only compression is corrected, which keeps
free surfaces from clumping) with poly6 density and spiky gradients, the artificial-pressure term
s_corr against tensile instability, vorticity confinement and XSPH viscosity. Masses enter through
the particle volume V = m / rho_0 so every constant keeps SI units.

Read top to bottom: boundaries and the grid, the prediction, the per-particle end of each solver
pass (``*_finish_at``), then the passes themselves over full neighbour lists (``*_gather``: what a
GPU runs), the reordering by particle id and a frame's health check. The CPU runs the same
per-particle functions from its fast path (``native.py``: half lists, C++ pair loops, one gang
launch a step). Every kernel takes ``offset`` first: the host launches chunks of the index range
from a thread pool (Warp releases the GIL and runs a CPU launch on one core). Kernels are kept
apart from the driver (``pbf.py``) so that editing the driver does not recompile them.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


# -- boundaries, the grid, the prediction ----------------------------------------------------------
@wp.func
def collide_once(
    p: wp.vec3,
    lo: wp.vec3,
    hi: wp.vec3,
    radius: float,
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """One round: push out of each obstacle, then clamp into the container."""
    for s in range(spheres.shape[0]):
        sp = spheres[s]
        c = wp.vec3(sp[0], sp[1], sp[2])
        rr = sp[3] + radius
        d = p - c
        dl = wp.length(d)
        if dl < rr:
            if dl > 1.0e-9:
                p = c + d * (rr / dl)
            else:
                p = c + wp.vec3(0.0, rr, 0.0)
    for b in range(box_lo.shape[0]):
        bl = box_lo[b] - wp.vec3(radius, radius, radius)
        bh = box_hi[b] + wp.vec3(radius, radius, radius)
        if p[0] > bl[0] and p[0] < bh[0] and p[1] > bl[1] and p[1] < bh[1] and p[2] > bl[2] and p[2] < bh[2]:
            # push out through the nearest face
            best = p[0] - bl[0]
            axis = int(0)
            target = bl[0]
            if bh[0] - p[0] < best:
                best = bh[0] - p[0]
                target = bh[0]
            for a in range(1, 3):
                if p[a] - bl[a] < best:
                    best = p[a] - bl[a]
                    axis = a
                    target = bl[a]
                if bh[a] - p[a] < best:
                    best = bh[a] - p[a]
                    axis = a
                    target = bh[a]
            p[axis] = target
    return wp.vec3(
        wp.clamp(p[0], lo[0] + radius, hi[0] - radius),
        wp.clamp(p[1], lo[1] + radius, hi[1] - radius),
        wp.clamp(p[2], lo[2] + radius, hi[2] - radius),
    )


@wp.func
def collide(
    p: wp.vec3,
    lo: wp.vec3,
    hi: wp.vec3,
    radius: float,
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
) -> wp.vec3:
    """Project a particle centre out of the obstacles and into the container.

    Two rounds, because where an obstacle meets a wall (a sphere resting on the floor) the wall
    clamp of the first round can push a particle back into the obstacle.
    """
    q = collide_once(p, lo, hi, radius, spheres, box_lo, box_hi)
    return collide_once(q, lo, hi, radius, spheres, box_lo, box_hi)


@wp.func
def wall_table(d: float, h: float, table: wp.array(dtype=wp.vec2)) -> wp.vec2:
    """(density per unit mass, its derivative in d) of the virtual fluid behind a wall at distance d."""
    if d >= h:
        return wp.vec2(0.0, 0.0)
    u = wp.max(d, 0.0) / h * float(table.shape[0] - 1)
    k = wp.min(int(u), table.shape[0] - 2)
    t = u - float(k)
    return table[k] * (1.0 - t) + table[k + 1] * t


@wp.func
def add_wall(acc: wp.vec4, d: float, n: wp.vec3, h: float, table: wp.array(dtype=wp.vec2)) -> wp.vec4:
    """Accumulate (gradient xyz, density) of one wall with inward normal n at distance d."""
    w = wall_table(d, h, table)
    g = n * w[1]
    return acc + wp.vec4(g[0], g[1], g[2], w[0])


@wp.func
def boundary_density(
    p: wp.vec3,
    lo: wp.vec3,
    hi: wp.vec3,
    h: float,
    table: wp.array(dtype=wp.vec2),
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
) -> wp.vec4:
    """Density per unit mass (w) and its gradient (xyz) contributed by container walls and obstacles.

    Without it a particle at a wall misses the neighbours the wall cuts away, the constraint
    drags it into the wall, and fluid piles up in corners and edges until it explodes.
    Each solid is treated locally as a plane backed by fluid at rest (a precomputed 1D table).
    """
    acc = wp.vec4(0.0, 0.0, 0.0, 0.0)
    for a in range(3):
        e = wp.vec3(0.0, 0.0, 0.0)
        e[a] = 1.0
        acc = add_wall(acc, p[a] - lo[a], e, h, table)
        acc = add_wall(acc, hi[a] - p[a], -e, h, table)
    for s in range(spheres.shape[0]):
        sp = spheres[s]
        r = p - wp.vec3(sp[0], sp[1], sp[2])
        rl = wp.length(r)
        if rl > 1.0e-9:
            acc = add_wall(acc, rl - sp[3], r / rl, h, table)
    for b in range(box_lo.shape[0]):
        q = wp.vec3(wp.clamp(p[0], box_lo[b][0], box_hi[b][0]), wp.clamp(p[1], box_lo[b][1], box_hi[b][1]),
                    wp.clamp(p[2], box_lo[b][2], box_hi[b][2]))
        r = p - q
        rl = wp.length(r)
        if rl > 1.0e-9:
            acc = add_wall(acc, rl, r / rl, h, table)
    return acc


@wp.func
def cell_coord(p: wp.vec3, lo: wp.vec3, inv_cell: float, dims: wp.vec3i) -> wp.vec3i:
    """Integer cell of a point in the dense grid over the container (clamped to the grid)."""
    q = (p - lo) * inv_cell
    return wp.vec3i(
        wp.clamp(int(wp.floor(q[0])), 0, dims[0] - 1),
        wp.clamp(int(wp.floor(q[1])), 0, dims[1] - 1),
        wp.clamp(int(wp.floor(q[2])), 0, dims[2] - 1),
    )


@wp.func
def cell_linear(c: wp.vec3i, dims: wp.vec3i) -> int:
    """Linear cell index, x fastest, so the three cells of a row are contiguous."""
    return (c[2] * dims[1] + c[1]) * dims[0] + c[0]


@wp.kernel
def predict_positions(
    offset: int,
    particle_x: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    gravity: wp.vec3,
    dt: float,
    lo: wp.vec3,
    hi: wp.vec3,
    radius: float,
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    inv_cell: float,
    dims: wp.vec3i,
    particle_id: wp.array(dtype=int),
    id_bits: int,
    v_out: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=int),
):
    """Explicit step under gravity (v* = v + dt g, x* = x + dt v*, projected out of solids), and
    the radix-sort key (cell << id_bits) | id of x* with the particle index as value.

    The id makes every key unique, so the order (and with it every floating-point sum over
    neighbours) depends only on positions and ids, not on the order particles sit in memory:
    a run resumed from a saved frame is bit-identical to an uninterrupted one.
    """
    i = wp.tid() + offset
    v = particle_v[i] + gravity * dt
    v_out[i] = v
    x = collide(particle_x[i] + v * dt, lo, hi, radius, spheres, box_lo, box_hi)
    x_pred[i] = x
    cell = cell_linear(cell_coord(x, lo, inv_cell, dims), dims)
    keys[i] = (wp.int64(cell) << wp.int64(id_bits)) | wp.int64(particle_id[i])
    values[i] = i


@wp.kernel
def find_cell_starts(offset: int, sorted_keys: wp.array(dtype=wp.int64), n: int, id_bits: int, num_cells: int,
                     cell_start: wp.array(dtype=int)):
    """cell_start[c] = first sorted index whose cell is >= c, over k in [0, n] (cell_start[cells] = n).

    Each sorted particle that opens a new cell fills the starts of the empty cells before it, so
    every entry is written exactly once: O(particles + cells) instead of a binary search per cell.
    """
    k = wp.tid() + offset
    cell = num_cells
    if k < n:
        cell = int(sorted_keys[k] >> wp.int64(id_bits))
    prev = int(-1)
    if k > 0:
        prev = int(sorted_keys[k - 1] >> wp.int64(id_bits))
    for c in range(prev + 1, cell + 1):
        cell_start[c] = k


@wp.kernel
def gather_state(
    offset: int,
    order: wp.array(dtype=int),
    particle_x: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    particle_id: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    x_pred_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    id_out: wp.array(dtype=int),
):
    """Reorder the particle state into sorted (cell) order, so neighbours are close in memory."""
    k = wp.tid() + offset
    src = order[k]
    x_out[k] = particle_x[src]
    x_pred_out[k] = x_pred[src]
    v_out[k] = particle_v[src]
    id_out[k] = particle_id[src]


# -- the end of each pass for one particle (shared by the gather passes and the CPU's) ---------------
@wp.func
def density_finish_at(
    i: int,
    x_pred: wp.array(dtype=wp.vec3),
    acc: wp.array(dtype=wp.vec4),
    acc_sq: wp.array(dtype=float),
    h: float,
    self_density: float,
    vol: float,
    rest_density: float,
    relaxation: float,
    lo: wp.vec3,
    hi: wp.vec3,
    wall: wp.array(dtype=wp.vec2),
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    particle_rho: wp.array(dtype=float),
    particle_lambda: wp.array(dtype=float),
    wall_grad: wp.array(dtype=wp.vec3),
):
    """Density rho_i (own, neighbours, walls) and multiplier lambda_i = -C_i / (sum |grad C|^2 + eps);
    clears the sums for the next pass."""
    a = acc[i]
    sq = acc_sq[i]
    acc[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
    acc_sq[i] = 0.0
    b = boundary_density(x_pred[i], lo, hi, h, wall, spheres, box_lo, box_hi)
    mass = vol * rest_density
    rho = self_density + a[3] + mass * b[3]
    gw = wp.vec3(b[0], b[1], b[2]) * vol
    wall_grad[i] = gw
    grad_i = wp.vec3(a[0], a[1], a[2]) + gw
    c = wp.max(rho / rest_density - 1.0, 0.0)
    particle_rho[i] = rho
    particle_lambda[i] = -c / (sq + wp.dot(grad_i, grad_i) + relaxation)


@wp.func
def correction_finish_at(
    i: int,
    x_pred: wp.array(dtype=wp.vec3),
    particle_lambda: wp.array(dtype=float),
    acc_dp: wp.array(dtype=wp.vec3),
    wall_grad: wp.array(dtype=wp.vec3),
    lo: wp.vec3,
    hi: wp.vec3,
    radius: float,
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    particle_x: wp.array(dtype=wp.vec3),
    inv_dt: float,
    last: int,
    v_out: wp.array(dtype=wp.vec3),
):
    """x_i + dp_i (pairs plus walls, at most r long), then collisions, in place; after the last
    iteration also the velocity v = (x* - x) / dt. Clears the sums for the next pass.

    In place is safe: a pass reads other particles' positions only in its pair loop, and every pair
    loop that reads particle i's position (i's own block and the one before) has run before i is
    finished."""
    dp = acc_dp[i] + wall_grad[i] * particle_lambda[i]
    acc_dp[i] = wp.vec3(0.0, 0.0, 0.0)
    # A correction longer than a particle radius only happens when particles are jammed against
    # walls; capping it keeps such corners from injecting energy (speeds of 50+ m/s otherwise).
    dl = wp.length(dp)
    if dl > radius:
        dp = dp * (radius / dl)
    x = collide(x_pred[i] + dp, lo, hi, radius, spheres, box_lo, box_hi)
    x_pred[i] = x
    if last != 0:
        v_out[i] = (x - particle_x[i]) * inv_dt


@wp.func
def vorticity_finish_at(i: int, omega: wp.array(dtype=wp.vec3), particle_rho: wp.array(dtype=float), mass: float,
                        omega_length: wp.array(dtype=float), particle_vol: wp.array(dtype=float)):
    """|omega_i| and the particle volume V_i = m / rho_i, both read per pair by the viscosity pass."""
    omega_length[i] = wp.length(omega[i])
    particle_vol[i] = mass / particle_rho[i]


@wp.func
def viscosity_finish_at(
    i: int,
    particle_v: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    acc_eta: wp.array(dtype=wp.vec3),
    acc_visc: wp.array(dtype=wp.vec3),
    vorticity_eps: float,
    xsph_c: float,
    dt: float,
    v_out: wp.array(dtype=wp.vec3),
):
    """XSPH v + c sum, then vorticity confinement f = eps (N x omega), N = eta / |eta|; clears the
    sums (omega among them) for the next step."""
    v = particle_v[i] + acc_visc[i] * xsph_c
    eta = acc_eta[i]
    omega = particle_omega[i]
    zero = wp.vec3(0.0, 0.0, 0.0)
    acc_visc[i] = zero
    acc_eta[i] = zero
    particle_omega[i] = zero
    el = wp.length(eta)
    if el > 1.0e-9 and vorticity_eps > 0.0:
        v += wp.cross(eta / el, omega) * (vorticity_eps * dt)
    v_out[i] = v


# -- the gather passes (full lists; CUDA's default) -------------------------------------------------
# Each particle walks its full neighbour list and sums its own pairs, then finishes itself in the
# same kernel: no atomics (the scatter passes' float atomics, 4-6 a pair end, bound a GPU step),
# half the launches, and sums in a fixed order, so GPU runs repeat bit for bit. A pair's term is
# the same IEEE operations on the same operands as the scatter's share for either end (the spiky
# gradient is odd, so g(x_j - x_i) = -g(x_i - x_j) exactly), so the two ways differ only in the
# order of their sums. A kernel reads only what no thread of it writes (positions in the density
# pass, multipliers in the correction pass, velocities in the two velocity passes), so finishing in
# place is race-free.


@wp.func
def pair_values(xi: wp.vec3, xj: wp.vec3, h: float, hh: float, poly6_coef: float, grad_coef: float) -> wp.vec4:
    """(g, W) of r = x_i - x_j as ``PAIR_GEOMETRY`` computes them: g = grad_coef (h - |r|)^2 r / |r|,
    W = poly6_coef (h^2 - |r|^2)^3, both 0 past h."""
    r = xi - xj
    r2 = wp.length_sq(r)
    d = wp.max(hh - r2, 0.0)
    rl = wp.max(wp.sqrt(r2), 1.0e-9)
    e = wp.max(h - rl, 0.0)
    f = grad_coef * e * e / rl
    return wp.vec4(r[0] * f, r[1] * f, r[2] * f, poly6_coef * d * d * d)


@wp.func
def artificial_pressure(w: float, corr_k: float, inv_corr_w_dq: float, corr_n: int) -> float:
    """s_corr = -k (W / W(dq))^n, as the density loop caches it (0 without the term)."""
    s = float(0.0)
    if corr_k > 0.0:
        ratio = w * inv_corr_w_dq
        if corr_n == 4:
            ratio2 = ratio * ratio
            s = -corr_k * ratio2 * ratio2
        else:
            corr = float(1.0)
            for _ in range(corr_n):
                corr = corr * ratio
            s = -corr_k * corr
    return s


@wp.kernel
def find_all_neighbours(
    offset: int,
    x_pred: wp.array(dtype=wp.vec3),
    cell_start: wp.array(dtype=int),
    lo: wp.vec3,
    inv_cell: float,
    dims: wp.vec3i,
    reach: int,
    h: float,
    max_neighbours: int,
    neighbour_count: wp.array(dtype=int),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
):
    """Full neighbour list: for each particle k every other particle within h, in ascending order
    (rows of cells are contiguous index ranges, visited z, y ascending), in k's own
    ``max_neighbours`` slots."""
    k = wp.tid() + offset
    xk = x_pred[k]
    c = cell_coord(xk, lo, inv_cell, dims)
    base = k * max_neighbours
    h2 = h * h
    x0 = wp.max(c[0] - reach, 0)
    x1 = wp.min(c[0] + reach, dims[0] - 1)
    count = int(0)
    for z in range(wp.max(c[2] - reach, 0), wp.min(c[2] + reach, dims[2] - 1) + 1):
        for y in range(wp.max(c[1] - reach, 0), wp.min(c[1] + reach, dims[1] - 1) + 1):
            row = (z * dims[1] + y) * dims[0]
            for j in range(cell_start[row + x0], cell_start[row + x1 + 1]):
                if j != k and wp.length_sq(x_pred[j] - xk) < h2 and count < max_neighbours:
                    neighbour_index[base + count] = j
                    count += 1
    neighbour_count[k] = count
    neighbour_start[k] = base
    neighbour_end[k] = base + count


@wp.kernel
def density_gather(
    offset: int,
    x_pred: wp.array(dtype=wp.vec3),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    h: float,
    poly6_coef: float,
    grad_coef: float,
    mass: float,
    corr_k: float,
    inv_corr_w_dq: float,
    corr_n: int,
    pair: wp.array(dtype=wp.vec4),
    acc: wp.array(dtype=wp.vec4),
    acc_sq: wp.array(dtype=float),
    self_density: float,
    vol: float,
    rest_density: float,
    relaxation: float,
    lo: wp.vec3,
    hi: wp.vec3,
    wall: wp.array(dtype=wp.vec2),
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    particle_rho: wp.array(dtype=float),
    particle_lambda: wp.array(dtype=float),
    wall_grad: wp.array(dtype=wp.vec3),
):
    """``density_pairs`` and ``density_finish`` of particle i over its full list: (sum g, sum m W),
    sum |g|^2 and each pair's (g, s_corr) cached for the correction pass; then rho_i and lambda_i."""
    i = wp.tid() + offset
    xi = x_pred[i]
    hh = h * h
    total = wp.vec4(0.0, 0.0, 0.0, 0.0)
    sq = float(0.0)
    for p in range(neighbour_start[i], neighbour_end[i]):
        g = pair_values(xi, x_pred[neighbour_index[p]], h, hh, poly6_coef, grad_coef)
        total += wp.vec4(g[0], g[1], g[2], mass * g[3])
        sq += g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
        pair[p] = wp.vec4(g[0], g[1], g[2], artificial_pressure(g[3], corr_k, inv_corr_w_dq, corr_n))
    acc[i] = total
    acc_sq[i] = sq
    density_finish_at(i, x_pred, acc, acc_sq, h, self_density, vol, rest_density, relaxation, lo, hi, wall, spheres,
                      box_lo, box_hi, particle_rho, particle_lambda, wall_grad)


@wp.kernel
def correction_gather(
    offset: int,
    particle_lambda: wp.array(dtype=float),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    pair: wp.array(dtype=wp.vec4),
    acc_dp: wp.array(dtype=wp.vec3),
    x_pred: wp.array(dtype=wp.vec3),
    wall_grad: wp.array(dtype=wp.vec3),
    lo: wp.vec3,
    hi: wp.vec3,
    radius: float,
    spheres: wp.array(dtype=wp.vec4),
    box_lo: wp.array(dtype=wp.vec3),
    box_hi: wp.array(dtype=wp.vec3),
    particle_x: wp.array(dtype=wp.vec3),
    inv_dt: float,
    last: int,
    v_out: wp.array(dtype=wp.vec3),
):
    """``correction_pairs`` and ``correction_finish`` of particle i over its full list:
    dp_i = sum_j (lambda_i + lambda_j + s_corr) g_ij, then the corrected position (in place)."""
    i = wp.tid() + offset
    li = particle_lambda[i]
    dp = wp.vec3(0.0, 0.0, 0.0)
    for p in range(neighbour_start[i], neighbour_end[i]):
        q = pair[p]
        dp += wp.vec3(q[0], q[1], q[2]) * (li + particle_lambda[neighbour_index[p]] + q[3])
    acc_dp[i] = dp
    correction_finish_at(i, x_pred, particle_lambda, acc_dp, wall_grad, lo, hi, radius, spheres, box_lo, box_hi,
                         particle_x, inv_dt, last, v_out)


@wp.kernel
def vorticity_gather(
    offset: int,
    x_pred: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    h: float,
    poly6_coef: float,
    grad_coef: float,
    vol: float,
    pair: wp.array(dtype=wp.vec4),
    omega: wp.array(dtype=wp.vec3),
    particle_rho: wp.array(dtype=float),
    mass: float,
    omega_length: wp.array(dtype=float),
    particle_vol: wp.array(dtype=float),
):
    """``vorticity_pairs`` and ``vorticity_finish`` of particle i over its full list: omega_i and
    each pair's (grad W, W) cached for the viscosity pass; then |omega_i| and V_i."""
    i = wp.tid() + offset
    xi = x_pred[i]
    vi = particle_v[i]
    hh = h * h
    total = wp.vec3(0.0, 0.0, 0.0)
    for p in range(neighbour_start[i], neighbour_end[i]):
        j = neighbour_index[p]
        g = pair_values(xi, x_pred[j], h, hh, poly6_coef, grad_coef)
        d = particle_v[j] - vi
        total += wp.vec3((d[1] * -g[2] - d[2] * -g[1]) * vol, (d[2] * -g[0] - d[0] * -g[2]) * vol,
                         (d[0] * -g[1] - d[1] * -g[0]) * vol)
        pair[p] = g
    omega[i] = total
    vorticity_finish_at(i, omega, particle_rho, mass, omega_length, particle_vol)


@wp.kernel
def viscosity_gather(
    offset: int,
    particle_v: wp.array(dtype=wp.vec3),
    omega_length: wp.array(dtype=float),
    particle_vol: wp.array(dtype=float),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    pair: wp.array(dtype=wp.vec4),
    acc_eta: wp.array(dtype=wp.vec3),
    acc_visc: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    vorticity_eps: float,
    xsph_c: float,
    dt: float,
    v_out: wp.array(dtype=wp.vec3),
):
    """``viscosity_pairs`` and ``viscosity_finish`` of particle i over its full list: eta_i and the
    XSPH sum, then the new velocity."""
    i = wp.tid() + offset
    vi = particle_v[i]
    wi = omega_length[i]
    eta = wp.vec3(0.0, 0.0, 0.0)
    visc = wp.vec3(0.0, 0.0, 0.0)
    for p in range(neighbour_start[i], neighbour_end[i]):
        j = neighbour_index[p]
        q = pair[p]
        volj = particle_vol[j]
        eta += wp.vec3(q[0], q[1], q[2]) * ((omega_length[j] - wi) * volj)
        visc += (particle_v[j] - vi) * (q[3] * volj)
    acc_eta[i] = eta
    acc_visc[i] = visc
    viscosity_finish_at(i, particle_v, particle_omega, acc_eta, acc_visc, vorticity_eps, xsph_c, dt, v_out)


@wp.kernel
def scatter_by_id(
    offset: int,
    particle_id: wp.array(dtype=int),
    src: wp.array(dtype=wp.vec3),
    dst: wp.array(dtype=wp.vec3),
):
    """dst[id[k]] = src[k]: return to stable particle order for output."""
    k = wp.tid() + offset
    dst[particle_id[k]] = src[k]


# -- a frame's health ------------------------------------------------------------------------------
# Slots of ``frame_diagnostics``' output: the frame checks read these five numbers from the device
# instead of copying every particle's state to the host before the next frame may start.
DIAG_MAX_DENSITY = wp.constant(0)
DIAG_MAX_SPEED2 = wp.constant(1)
DIAG_NONFINITE = wp.constant(2)
DIAG_OUTSIDE = wp.constant(3)
DIAG_NEIGHBOURS = wp.constant(4)
DIAG_SIZE = 5


@wp.kernel
def frame_diagnostics(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    rho: wp.array(dtype=float),
    neighbour_count: wp.array(dtype=int),
    lo: wp.vec3,
    hi: wp.vec3,
    out: wp.array(dtype=float),
):
    """Reduce a frame into ``out`` (zeroed first; one launch, not chunked: atomics are plain adds on the
    CPU): the largest density and squared speed of the finite particles, how many particles are not
    finite, how many are outside [lo, hi], and the half neighbour lists' total length. Maxima and
    integer-valued sums (exact in float32 below 2^24) come out the same in any order."""
    i = wp.tid()
    xi = x[i]
    vi = v[i]
    r = rho[i]
    if wp.isfinite(xi) and wp.isfinite(vi) and wp.isfinite(r):
        wp.atomic_max(out, DIAG_MAX_DENSITY, r)
        wp.atomic_max(out, DIAG_MAX_SPEED2, wp.dot(vi, vi))
        if xi[0] < lo[0] or xi[1] < lo[1] or xi[2] < lo[2] or xi[0] > hi[0] or xi[1] > hi[1] or xi[2] > hi[2]:
            wp.atomic_add(out, DIAG_OUTSIDE, 1.0)
    else:
        wp.atomic_add(out, DIAG_NONFINITE, 1.0)
    wp.atomic_add(out, DIAG_NEIGHBOURS, float(neighbour_count[i]))
