"""The CPU fast path of the PBF step (``kernels.py`` holds the physics): half neighbour lists, each
pair once at its lower index, found with a vectorised row scan; the pair loops in C++
(``wp.func_native``) that add each pair's share to both of its particles; and every pair pass of a
step as one gang launch (``pipeline.gang``), one launch per thread with barriers in native code.

The ``*_pairs`` kernels are race-free (and order-fixed) under the two-phase block launch of
``Launcher.scatter_passes``; the ``*_finish`` kernels turn a block's sums into per-particle results
(``kernels.*_finish_at``). Results equal the gather passes' up to the order of their sums.
"""

import warp as wp

from pipeline import gang
from pipeline.sim.kernels import (
    cell_coord,
    correction_finish_at,
    density_finish_at,
    viscosity_finish_at,
    vorticity_finish_at,
)

wp.set_module_options({"enable_backward": False})


# -- the pair loops (native) ------------------------------------------------------------------------
# The loops over a particle's half list, written in C++ (``wp.func_native``). They index arrays through
# their data pointers: Warp's a[i] wraps negative indices (a shift, an and and an add per access), and
# the plain access measured 16% faster, bit for bit the same. ``wp::atomic_add`` is a
# plain add on the CPU and an atomic on CUDA. A pair's values, for r = x_i - x_j: the spiky gradient
# g = grad_coef (h - |r|)^2 r / |r| (grad_coef = -45 / (pi h^6), times a volume where wanted) and the
# poly6 value poly6_coef (h^2 - |r|^2)^3. Pairs come from the neighbour list, so they are almost
# always inside h; the clamps keep a pair that left h during the solver iterations at zero, and
# coincident particles give a zero gradient. The density and vorticity loops take a particle's pairs in
# groups of ``GROUP``: a first loop computes everything a pair contributes (its gradient, value and
# scattered terms, and its pair-cache entry) into small local arrays, which the CPU compiler
# vectorises (eight square roots and divisions at once) over whole vectors of 8, so no pair falls to
# a scalar tail; a second loop then only adds the terms up and scatters them in list order. Every
# value is the same IEEE operation on the same operands in either form, so the results are bit for
# bit those of one scalar loop, which runs 15-30% slower per pair; the squares, products and cache
# entries go in the vector loop too (about 5% of a step).
GROUP = 16

# The start of the vector loop over a group: a0..a2 = g and w for pair p0 + q (j3 indexes the flat
# floats ``xf`` of x_pred, and ``vf`` of the velocities where a loop has them). Lanes past the group's
# m pairs read the slots after the list (the index array's padding, or another list's entries: valid
# indices either way), and their values are never used.
PAIR_GEOMETRY = f"""
    const int m = wp::min(last - p0, {GROUP});
    const int mv = (m + 7) & ~7;
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width(8) interleave(disable)
#endif
    for (int q = 0; q < mv; ++q) {{
        const int j = idx[p0 + q];
        const int j3 = 3 * j;  // a 32-bit float offset: dword-indexed gathers (qword ones ran 4% slower)
        const float r0 = xi.c[0] - xf[j3];
        const float r1 = xi.c[1] - xf[j3 + 1];
        const float r2_ = xi.c[2] - xf[j3 + 2];
        const float r2 = wp::length_sq(wp::vec3(r0, r1, r2_));
        const float d = wp::max(hh - r2, 0.0f);
        const float rl = wp::max(wp::sqrt(r2), 1.0e-9f);
        const float e = wp::max(h - rl, 0.0f);
        const float f = grad_coef * e * e / rl;
        const float a0 = r0 * f;
        const float a1 = r1 * f;
        const float a2 = r2_ * f;
        const float w = poly6_coef * d * d * d;"""


@wp.func_native(f"""
const wp::vec3* x = x_pred.data;
const float* xf = reinterpret_cast<const float*>(x);
const int* idx = neighbour_index.data;
const wp::vec3 xi = x[i];
const float hh = h * h;
wp::vec4 scatter[{GROUP}], cached[{GROUP}];
float squares[{GROUP}], values[{GROUP}];
wp::vec4 own_neg(0.0f);
float own_sq = 0.0f;
// s_corr = -k (W / W(dq))^n: in the vector loop for the default n = 4, else after it
const bool quartic = corr_k > 0.0f && corr_n == 4;
const int last = neighbour_end.data[i];
for (int p0 = neighbour_start.data[i]; p0 < last; p0 += {GROUP}) {{
{PAIR_GEOMETRY}
        const float ratio = w * inv_corr_w_dq;
        const float ratio2 = ratio * ratio;
        const float quartic_corr = -corr_k * ratio2 * ratio2;
        values[q] = w;
        squares[q] = a0 * a0 + a1 * a1 + a2 * a2;  // wp::dot(g, g)
        scatter[q] = wp::vec4(-a0, -a1, -a2, mass * w);
        cached[q] = wp::vec4(a0, a1, a2, quartic ? quartic_corr : 0.0f);
    }}
    if (corr_k > 0.0f && corr_n != 4) {{
        for (int q = 0; q < m; ++q) {{
            const float ratio = values[q] * inv_corr_w_dq;
            float corr = 1.0f;
            for (int k = 0; k < corr_n; ++k) corr = corr * ratio;
            cached[q][3] = -corr_k * corr;
        }}
    }}
    for (int q = 0; q < m; ++q) {{
        const int j = idx[p0 + q];
        own_neg += scatter[q];
        own_sq += squares[q];
        wp::atomic_add(acc.data + j, scatter[q]);
        wp::atomic_add(acc_sq.data + j, squares[q]);
        pair.data[p0 + q] = cached[q];
    }}
}}
// i gains (g, mW) per pair: the sum of the negated gradients, negated, is exactly their sum
wp::atomic_add(acc.data + i, wp::vec4(-own_neg[0], -own_neg[1], -own_neg[2], own_neg[3]));
wp::atomic_add(acc_sq.data + i, own_sq);
""")
def density_pair_loop(i: int, x_pred: wp.array(dtype=wp.vec3), neighbour_start: wp.array(dtype=int),
                      neighbour_end: wp.array(dtype=int), neighbour_index: wp.array(dtype=int), h: float,
                      poly6_coef: float, grad_coef: float, mass: float, corr_k: float, inv_corr_w_dq: float,
                      corr_n: int, pair: wp.array(dtype=wp.vec4), acc: wp.array(dtype=wp.vec4),
                      acc_sq: wp.array(dtype=float)):
    """``density_pairs``' loop over particle i's half list."""
    ...


@wp.func_native("""
const int* idx = neighbour_index.data;
const float* lam = particle_lambda.data;
const float li = lam[i];
wp::vec3 own(0.0f);
for (int p = neighbour_start.data[i], last = neighbour_end.data[i]; p < last; ++p) {
    const wp::vec4 q = pair.data[p];
    const int j = idx[p];
    const wp::vec3 t = wp::vec3(q[0], q[1], q[2]) * (li + lam[j] + q[3]);
    own += t;
    wp::atomic_add(acc_dp.data + j, -t);
}
wp::atomic_add(acc_dp.data + i, own);
""")
def correction_pair_loop(i: int, particle_lambda: wp.array(dtype=float), neighbour_start: wp.array(dtype=int),
                         neighbour_end: wp.array(dtype=int), neighbour_index: wp.array(dtype=int),
                         pair: wp.array(dtype=wp.vec4), acc_dp: wp.array(dtype=wp.vec3)):
    """``correction_pairs``' loop over particle i's half list."""
    ...


@wp.func_native(f"""
const wp::vec3* x = x_pred.data;
const float* xf = reinterpret_cast<const float*>(x);
const wp::vec3* v = particle_v.data;
const float* vf = reinterpret_cast<const float*>(v);
const int* idx = neighbour_index.data;
const wp::vec3 xi = x[i];
const wp::vec3 vi = v[i];
const float hh = h * h;
float t0[{GROUP}], t1[{GROUP}], t2[{GROUP}];
wp::vec4 cached[{GROUP}];
wp::vec3 own(0.0f);
const int last = neighbour_end.data[i];
for (int p0 = neighbour_start.data[i]; p0 < last; p0 += {GROUP}) {{
{PAIR_GEOMETRY}
        // cross(v_j - v_i, -g) * vol, as wp::cross and the vec3 product compute it
        const float d0 = vf[j3] - vi.c[0];
        const float d1 = vf[j3 + 1] - vi.c[1];
        const float d2 = vf[j3 + 2] - vi.c[2];
        t0[q] = (d1 * -a2 - d2 * -a1) * vol;
        t1[q] = (d2 * -a0 - d0 * -a2) * vol;
        t2[q] = (d0 * -a1 - d1 * -a0) * vol;
        cached[q] = wp::vec4(a0, a1, a2, w);
    }}
    for (int q = 0; q < m; ++q) {{
        const wp::vec3 term(t0[q], t1[q], t2[q]);
        own += term;
        wp::atomic_add(acc_omega.data + idx[p0 + q], term);
        pair.data[p0 + q] = cached[q];
    }}
}}
wp::atomic_add(acc_omega.data + i, own);
""")
def vorticity_pair_loop(i: int, x_pred: wp.array(dtype=wp.vec3), particle_v: wp.array(dtype=wp.vec3),
                        neighbour_start: wp.array(dtype=int), neighbour_end: wp.array(dtype=int),
                        neighbour_index: wp.array(dtype=int), h: float, poly6_coef: float, grad_coef: float,
                        vol: float, pair: wp.array(dtype=wp.vec4), acc_omega: wp.array(dtype=wp.vec3)):
    """``vorticity_pairs``' loop over particle i's half list."""
    ...


@wp.func_native("""
const wp::vec3* v = particle_v.data;
const float* wl = omega_length.data;
const float* vol = particle_vol.data;
const int* idx = neighbour_index.data;
const wp::vec3 vi = v[i];
const float wi = wl[i];
const float voli = vol[i];
wp::vec3 own_eta(0.0f);
wp::vec3 own_visc(0.0f);
for (int p = neighbour_start.data[i], last = neighbour_end.data[i]; p < last; ++p) {
    const int j = idx[p];
    const wp::vec4 q = pair.data[p];
    const wp::vec3 g = wp::vec3(q[0], q[1], q[2]);
    const float volj = vol[j];
    const float dw = wl[j] - wi;
    const wp::vec3 dv = v[j] - vi;
    own_eta += g * (dw * volj);
    own_visc += dv * (q[3] * volj);
    wp::atomic_add(acc_eta.data + j, g * (dw * voli));
    wp::atomic_add(acc_visc.data + j, dv * (-q[3] * voli));
}
wp::atomic_add(acc_eta.data + i, own_eta);
wp::atomic_add(acc_visc.data + i, own_visc);
""")
def viscosity_pair_loop(i: int, particle_v: wp.array(dtype=wp.vec3), omega_length: wp.array(dtype=float),
                        particle_vol: wp.array(dtype=float), neighbour_start: wp.array(dtype=int),
                        neighbour_end: wp.array(dtype=int), neighbour_index: wp.array(dtype=int),
                        pair: wp.array(dtype=wp.vec4), acc_eta: wp.array(dtype=wp.vec3),
                        acc_visc: wp.array(dtype=wp.vec3)):
    """``viscosity_pairs``' loop over particle i's half list."""
    ...


# The row scan of the neighbour search, 16 candidates at a time with AVX-512 (F and DQ; the CPU
# compiler targets the host): load the candidates' coordinates under a mask, de-interleave them,
# test all 16 distances at once and compress the hits' indices into the list. The scalar loop
# branches on every candidate, about one in four a hit, and its mispredictions cost more than the
# tests: the vector scan measured 2.2x faster (8.7 -> 3.9 ms per step of the benchmark), the same
# lists. Defines ``SCAN_ROW(first, end)`` for the search below; without AVX-512 (or on CUDA) it is
# the scalar loop, which ``vector_scan = 0`` also selects at run time.
ROW_SCAN = """
#if defined(__AVX512F__) && defined(__AVX512DQ__) && !defined(__CUDA_ARCH__)
typedef float v16f __attribute__((ext_vector_type(16)));
typedef int v16i __attribute__((ext_vector_type(16)));
const v16f zero_f = 0.0f;
const v16i zero_i = 0;
const v16i lanes = (v16i){0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};
auto lane_mask = [](int n) -> unsigned short {
    return n <= 0 ? 0 : n >= 16 ? 0xFFFF : static_cast<unsigned short>((1u << n) - 1u);
};
auto scan_vector = [&](int first, int end) {
    for (int j0 = first; j0 < end; j0 += 16) {
        const int m = wp::min(end - j0, 16);
        const float* p = reinterpret_cast<const float*>(x + j0);
        const v16f a = __builtin_ia32_loadups512_mask(p, zero_f, lane_mask(3 * m));
        const v16f b = __builtin_ia32_loadups512_mask(p + 16, zero_f, lane_mask(3 * m - 16));
        const v16f e = __builtin_ia32_loadups512_mask(p + 32, zero_f, lane_mask(3 * m - 32));
        const v16f px = __builtin_shufflevector(__builtin_shufflevector(a, b, 0, 3, 6, 9, 12, 15, 18, 21, 24,
            27, 30, -1, -1, -1, -1, -1), e, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 17, 20, 23, 26, 29);
        const v16f py = __builtin_shufflevector(__builtin_shufflevector(a, b, 1, 4, 7, 10, 13, 16, 19, 22, 25,
            28, 31, -1, -1, -1, -1, -1), e, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 18, 21, 24, 27, 30);
        const v16f pz = __builtin_shufflevector(__builtin_shufflevector(a, b, 2, 5, 8, 11, 14, 17, 20, 23, 26,
            29, -1, -1, -1, -1, -1, -1), e, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 19, 22, 25, 28, 31);
        // x[j] - x_k and its squared length: the scalar loop's operations, lane by lane
        const v16f d0 = px - xk.c[0];
        const v16f d1 = py - xk.c[1];
        const v16f d2 = pz - xk.c[2];
        const v16i hit = (d0 * d0 + d1 * d1 + d2 * d2 < h2) & (lanes < m);
        const unsigned short found = __builtin_ia32_cvtd2mask512(hit);
        if (count + 16 <= max_neighbours) {
            // compress in a register and store all 16 lanes: the lanes past the hits fall inside
            // this particle's max_neighbours slots and are overwritten or ignored (a compressing
            // store to memory is microcoded and measured 1.6x slower than the scalar loop)
            const v16i hits = __builtin_ia32_compresssi512_mask(lanes + j0, zero_i, found);
            __builtin_memcpy(out + count, &hits, sizeof(hits));
            count += __builtin_popcount(found);
        } else {
            for (int q = 0; q < m && count < max_neighbours; ++q)
                if ((found >> q) & 1) out[count++] = j0 + q;
        }
    }
};
#define SCAN_ROW(first, end) if (vector_scan) scan_vector(first, end); else SCAN_SCALAR(first, end)
#else
#define SCAN_ROW(first, end) SCAN_SCALAR(first, end)
#endif
"""


@wp.func_native("""
const wp::vec3* x = x_pred.data;
const int* cs = cell_start.data;
int* out = neighbour_index.data + base;
const wp::vec3 xk = x[k];
const float h2 = h * h;
const int x0 = wp::max(c.c[0] - reach, 0);
const int x1 = wp::min(c.c[0] + reach, dims.c[0] - 1);
int count = 0;
#define SCAN_SCALAR(first, end) \\
    for (int j = first; j < end; ++j) \\
        if (wp::length_sq(x[j] - xk) < h2 && count < max_neighbours) out[count++] = j;
""" + ROW_SCAN + """
for (int dz = 0; dz <= reach; ++dz) {
    const int z = c.c[2] + dz;
    if (z >= dims.c[2]) break;
    const int y_first = wp::max(dz == 0 ? c.c[1] : c.c[1] - reach, 0);
    const int y_last = wp::min(c.c[1] + reach, dims.c[1] - 1);
    for (int y = y_first; y <= y_last; ++y) {
        const int row = (z * dims.c[1] + y) * dims.c[0];
        const int first = (dz == 0 && y == c.c[1]) ? k + 1 : cs[row + x0];
        const int end = cs[row + x1 + 1];
        SCAN_ROW(first, end);
    }
}
#undef SCAN_ROW
#undef SCAN_SCALAR
return wp::vec2i(count, count > 0 ? out[count - 1] : k);
""")
def upper_neighbours(k: int, x_pred: wp.array(dtype=wp.vec3), cell_start: wp.array(dtype=int), c: wp.vec3i,
                     dims: wp.vec3i, reach: int, h: float, max_neighbours: int, vector_scan: int,
                     neighbour_index: wp.array(dtype=int), base: int) -> wp.vec2i:
    """``find_neighbours``' scan: the particles j > k within h, written to neighbour_index[base...] in
    ascending order; returns (count, last j). ``vector_scan`` picks the AVX-512 row scan where the
    CPU has it (``ROW_SCAN``). The scalar loop is native: 10% faster than the same loops in Warp.
    Trimming each row to the sphere (the row's nearest point bounds the x range) tests a fifth fewer
    candidates but measured 10% slower, in Warp and natively: the rows are short."""
    ...


@wp.kernel
def find_neighbours(
    offset: int,
    x_pred: wp.array(dtype=wp.vec3),
    cell_start: wp.array(dtype=int),
    lo: wp.vec3,
    inv_cell: float,
    dims: wp.vec3i,
    reach: int,
    h: float,
    max_neighbours: int,
    vector_scan: int,
    packed: int,
    cursor: wp.array(dtype=int),
    neighbour_count: wp.array(dtype=int),
    neighbour_span: wp.array(dtype=int),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
):
    """Half neighbour list: for each particle k, the neighbours j > k (sorted order) within h.

    Every pair is stored once, at its lower index, and the solver passes scatter each pair's
    contribution to both ends: half the distance tests and half the pair arithmetic of a full
    list. Particles are sorted by cell (x fastest), so the neighbours after k lie in the rows
    dz > 0, or dz = 0 and dy > 0, plus the rest of k's own row; each row of cells is one
    contiguous index range. neighbour_span[k] is the largest j - k (indices come out ascending),
    which bounds how far a pass that writes to j reaches past k.

    ``packed`` (the CPU, where a chunk runs its indices in order): each chunk writes its lists one
    after another into its own region (chunk offset x max_neighbours), so a pair pass streams
    through memory (35% faster per pass than fixed slots); otherwise (CUDA) each particle has
    max_neighbours slots of its own. ``vector_scan`` = 0 forces the scalar row scan (the same lists).
    """
    k = wp.tid() + offset
    c = cell_coord(x_pred[k], lo, inv_cell, dims)
    base = k * max_neighbours
    if packed != 0:
        base = offset * max_neighbours + cursor[offset]
    found = upper_neighbours(k, x_pred, cell_start, c, dims, reach, h, max_neighbours, vector_scan,
                             neighbour_index, base)
    count = found[0]
    last = found[1]
    if packed != 0:
        cursor[offset] = cursor[offset] + count
    neighbour_count[k] = count
    neighbour_span[k] = last - k
    neighbour_start[k] = base
    neighbour_end[k] = base + count


# -- the scatter passes over half lists ------------------------------------------------------------
@wp.kernel
def density_pairs(
    offset: int,
    x_pred: wp.array(dtype=wp.vec3),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    h: float,
    poly6_coef: float,
    spiky_coef: float,
    mass: float,
    vol: float,
    corr_k: float,
    inv_corr_w_dq: float,
    corr_n: int,
    pair: wp.array(dtype=wp.vec4),
    acc: wp.array(dtype=wp.vec4),
    acc_sq: wp.array(dtype=float),
):
    """Pair sums of the density constraint: (sum V grad W, sum m W) into acc and sum |V grad W|^2.

    With r = x_i - x_j and g = V grad W(r), particle i gains (g, mW) and j gains (-g, mW); both
    gain |g|^2. Each pair's g and artificial pressure s_corr = -k (W / W(dq))^n are cached in one
    vec4 for the correction pass, which then needs no square root. The scatter to j is a plain
    add on the CPU, made race-free by the two-phase block launch (``Launcher.scatter``).
    """
    density_pair_loop(wp.tid() + offset, x_pred, neighbour_start, neighbour_end, neighbour_index, h, poly6_coef,
                      spiky_coef * vol, mass, corr_k, inv_corr_w_dq, corr_n, pair, acc, acc_sq)


@wp.kernel
def density_finish(
    offset: int,
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
    """``density_finish_at`` for every particle of the launch."""
    density_finish_at(wp.tid() + offset, x_pred, acc, acc_sq, h, self_density, vol, rest_density, relaxation, lo,
                      hi, wall, spheres, box_lo, box_hi, particle_rho, particle_lambda, wall_grad)


@wp.kernel
def correction_pairs(
    offset: int,
    particle_lambda: wp.array(dtype=float),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    pair: wp.array(dtype=wp.vec4),
    acc_dp: wp.array(dtype=wp.vec3),
):
    """Position corrections: t = (lambda_i + lambda_j + s_corr) V grad W_ij, +t to i and -t to j."""
    correction_pair_loop(wp.tid() + offset, particle_lambda, neighbour_start, neighbour_end, neighbour_index, pair,
                         acc_dp)


@wp.kernel
def correction_finish(
    offset: int,
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
    """``correction_finish_at`` for every particle of the launch."""
    correction_finish_at(wp.tid() + offset, x_pred, particle_lambda, acc_dp, wall_grad, lo, hi, radius, spheres,
                         box_lo, box_hi, particle_x, inv_dt, last, v_out)


@wp.kernel
def vorticity_pairs(
    offset: int,
    x_pred: wp.array(dtype=wp.vec3),
    particle_v: wp.array(dtype=wp.vec3),
    neighbour_start: wp.array(dtype=int),
    neighbour_end: wp.array(dtype=int),
    neighbour_index: wp.array(dtype=int),
    h: float,
    poly6_coef: float,
    spiky_coef: float,
    vol: float,
    pair: wp.array(dtype=wp.vec4),
    acc_omega: wp.array(dtype=wp.vec3),
):
    """Vorticity omega_i = sum_j V (v_j - v_i) x grad_j W_ij (1/s).

    The term is the same for both ends of a pair (swapping i and j flips both factors), so it is
    added to i and j. Each pair's grad W and W are cached for the viscosity pass.
    """
    vorticity_pair_loop(wp.tid() + offset, x_pred, particle_v, neighbour_start, neighbour_end, neighbour_index, h,
                        poly6_coef, spiky_coef, vol, pair, acc_omega)


@wp.kernel
def vorticity_finish(offset: int, omega: wp.array(dtype=wp.vec3), particle_rho: wp.array(dtype=float), mass: float,
                     omega_length: wp.array(dtype=float), particle_vol: wp.array(dtype=float)):
    """``vorticity_finish_at`` for every particle of the launch."""
    vorticity_finish_at(wp.tid() + offset, omega, particle_rho, mass, omega_length, particle_vol)


@wp.kernel
def viscosity_pairs(
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
):
    """eta_i = sum_j V_j grad W_ij (|omega_j| - |omega_i|) and XSPH sum_j V_j (v_j - v_i) W_ij, both ends."""
    viscosity_pair_loop(wp.tid() + offset, particle_v, omega_length, particle_vol, neighbour_start, neighbour_end,
                        neighbour_index, pair, acc_eta, acc_visc)


@wp.kernel
def viscosity_finish(
    offset: int,
    particle_v: wp.array(dtype=wp.vec3),
    particle_omega: wp.array(dtype=wp.vec3),
    acc_eta: wp.array(dtype=wp.vec3),
    acc_visc: wp.array(dtype=wp.vec3),
    vorticity_eps: float,
    xsph_c: float,
    dt: float,
    v_out: wp.array(dtype=wp.vec3),
):
    """``viscosity_finish_at`` for every particle of the launch."""
    viscosity_finish_at(wp.tid() + offset, particle_v, particle_omega, acc_eta, acc_visc, vorticity_eps, xsph_c, dt,
                        v_out)


# -- the finish passes over a block, natively (CPU, walls only) ------------------------------------
# ``density_finish_at`` and ``correction_finish_at`` for a whole block in loops the compiler
# vectorises across particles (the scalar Warp functions took about 20 ns a particle, a fifth of a
# step on one thread). They do the same IEEE operations in the same order: a wall out of reach,
# whose table value is zero, is skipped instead of added (adding a zero leaves a sum that starts at
# +0 unchanged), and so is the zero a wall's normal gives the other two axes. Obstacles need the
# general functions, so a scene with any takes those.
WALL_TERM = """
#define WALL_TERM(distance, axis_sum, sign) {                                        \\
    const float dd = (distance);                                                     \\
    if (dd < h) {                                                                    \\
        const float u = wp::max(dd, 0.0f) / h * scale;                               \\
        const int k = wp::min(static_cast<wp::int32>(u), last_entry - 1);            \\
        const float t = u - static_cast<float>(k);                                   \\
        const float w0 = tab[k].c[0] * (1.0f - t) + tab[k + 1].c[0] * t;             \\
        const float w1 = tab[k].c[1] * (1.0f - t) + tab[k + 1].c[1] * t;             \\
        axis_sum = axis_sum + (sign) * w1;                                           \\
        wall_sum = wall_sum + w0;                                                    \\
    }                                                                                \\
}
"""


@wp.func_native("""
const wp::vec3* x = x_pred.data;
wp::vec4* a4 = acc.data;
float* a1 = acc_sq.data;
const wp::vec2* tab = wall.data;
const int last_entry = wall.shape[0] - 1;
const float scale = static_cast<float>(last_entry);
const float mass = vol * rest_density;
""" + WALL_TERM + """
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety)
#endif
for (int i = start; i < end; ++i) {
    const wp::vec4 a = a4[i];
    const float sq = a1[i];
    a4[i] = wp::vec4(0.0f, 0.0f, 0.0f, 0.0f);
    a1[i] = 0.0f;
    const wp::vec3 p = x[i];
    float b0 = 0.0f, b1 = 0.0f, b2 = 0.0f, wall_sum = 0.0f;
    WALL_TERM(p.c[0] - lo.c[0], b0, 1.0f)
    WALL_TERM(hi.c[0] - p.c[0], b0, -1.0f)
    WALL_TERM(p.c[1] - lo.c[1], b1, 1.0f)
    WALL_TERM(hi.c[1] - p.c[1], b1, -1.0f)
    WALL_TERM(p.c[2] - lo.c[2], b2, 1.0f)
    WALL_TERM(hi.c[2] - p.c[2], b2, -1.0f)
    const float rho = self_density + a.c[3] + mass * wall_sum;
    const float g0 = b0 * vol;
    const float g1 = b1 * vol;
    const float g2 = b2 * vol;
    wall_grad.data[i] = wp::vec3(g0, g1, g2);
    const float q0 = a.c[0] + g0;
    const float q1 = a.c[1] + g1;
    const float q2 = a.c[2] + g2;
    const float c = wp::max(rho / rest_density - 1.0f, 0.0f);
    particle_rho.data[i] = rho;
    particle_lambda.data[i] = -c / (sq + (q0 * q0 + q1 * q1 + q2 * q2) + relaxation);
}
#undef WALL_TERM
""")
def density_finish_walls(start: int, end: int, x_pred: wp.array(dtype=wp.vec3), acc: wp.array(dtype=wp.vec4),
                         acc_sq: wp.array(dtype=float), h: float, self_density: float, vol: float,
                         rest_density: float, relaxation: float, lo: wp.vec3, hi: wp.vec3,
                         wall: wp.array(dtype=wp.vec2), particle_rho: wp.array(dtype=float),
                         particle_lambda: wp.array(dtype=float), wall_grad: wp.array(dtype=wp.vec3)):
    """``density_finish_at`` for the particles [start, end) of a scene without obstacles."""
    ...


@wp.func_native("""
wp::vec3* x = x_pred.data;
wp::vec3* a3 = acc_dp.data;
const float lo0 = lo.c[0] + radius, lo1 = lo.c[1] + radius, lo2 = lo.c[2] + radius;
const float hi0 = hi.c[0] - radius, hi1 = hi.c[1] - radius, hi2 = hi.c[2] - radius;
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety)
#endif
for (int i = start; i < end; ++i) {
    const wp::vec3 a = a3[i];
    const wp::vec3 wg = wall_grad.data[i];
    const float lam = particle_lambda.data[i];
    float d0 = a.c[0] + wg.c[0] * lam;
    float d1 = a.c[1] + wg.c[1] * lam;
    float d2 = a.c[2] + wg.c[2] * lam;
    a3[i] = wp::vec3(0.0f, 0.0f, 0.0f);
    const float dl = wp::sqrt(d0 * d0 + d1 * d1 + d2 * d2);
    if (dl > radius) {
        const float s = radius / dl;
        d0 = d0 * s;
        d1 = d1 * s;
        d2 = d2 * s;
    }
    const wp::vec3 p = x[i];
    // collide()'s two rounds of the container clamp (the second changes nothing, kept for the same bits)
    const float x0 = wp::clamp(wp::clamp(p.c[0] + d0, lo0, hi0), lo0, hi0);
    const float x1 = wp::clamp(wp::clamp(p.c[1] + d1, lo1, hi1), lo1, hi1);
    const float x2 = wp::clamp(wp::clamp(p.c[2] + d2, lo2, hi2), lo2, hi2);
    x[i] = wp::vec3(x0, x1, x2);
    if (last != 0) {
        const wp::vec3 q = particle_x.data[i];
        v_out.data[i] = wp::vec3((x0 - q.c[0]) * inv_dt, (x1 - q.c[1]) * inv_dt, (x2 - q.c[2]) * inv_dt);
    }
}
""")
def correction_finish_walls(start: int, end: int, x_pred: wp.array(dtype=wp.vec3),
                            particle_lambda: wp.array(dtype=float), acc_dp: wp.array(dtype=wp.vec3),
                            wall_grad: wp.array(dtype=wp.vec3), lo: wp.vec3, hi: wp.vec3, radius: float,
                            particle_x: wp.array(dtype=wp.vec3), inv_dt: float, last: int,
                            v_out: wp.array(dtype=wp.vec3)):
    """``correction_finish_at`` for the particles [start, end) of a scene without obstacles."""
    ...


# -- all pair passes of a step as one gang launch (CPU) --------------------------------------------
# The passes a step runs through ``Launcher.scatter_passes`` on CUDA run on the CPU as one launch per
# thread (``Launcher.gang``): the same block schedule (even blocks, then odd, a pass's finish inside
# its phases), with the phases separated by native barriers instead of Python hand-offs, and each
# phase's blocks taken by whichever thread comes free. Pass kinds, in step order: the iterations'
# density (0) and correction (1) passes, then vorticity (2) and viscosity (3).
# The gang takes its arguments as two structs; the per-particle kernels above keep plain arguments:
# a kernel copies its struct arguments for every index it runs (1.2 KB here), which makes the
# finish kernels 2-7x slower, while the gang copies them once per block.


@wp.struct
class PassConstants:
    """The scalars of a step's pair passes (one per solver): the one description of what the passes
    and their finish kernels take, which ``pairs_block`` and ``finish_block`` unpack."""

    iterations: int  # density/correction iterations of a step
    h: float  # kernel support radius
    poly6_coef: float  # poly6 kernel's coefficient 315 / (64 pi h^9)
    spiky_coef: float  # spiky gradient's coefficient -45 / (pi h^6)
    mass: float  # particle mass
    vol: float  # particle volume, mass / rest density
    corr_k: float  # artificial pressure strength k (tensile instability)
    inv_corr_w_dq: float  # 1 / W(dq) of the artificial pressure
    corr_n: int  # artificial pressure exponent n
    self_density: float  # a particle's own poly6 contribution to its density
    rest_density: float  # rest density rho_0
    relaxation: float  # constraint force mixing epsilon in the lambda denominator
    lo: wp.vec3  # domain's lower corner (the walls)
    hi: wp.vec3  # domain's upper corner
    radius: float  # particle radius, kept off walls and obstacles
    inv_dt: float  # 1 / time step (velocity from positions)
    vorticity_eps: float  # vorticity confinement strength
    xsph_c: float  # XSPH viscosity c
    dt: float  # time step


@wp.struct
class PassArrays:
    """The arrays of a step's pair passes (the solver keeps one per arrangement of its buffers)."""

    x_pred: wp.array(dtype=wp.vec3)  # predicted positions, corrected by the iterations
    particle_x: wp.array(dtype=wp.vec3)  # positions at the step's start
    v_tmp: wp.array(dtype=wp.vec3)  # velocity from the corrected positions, before viscosity
    particle_v: wp.array(dtype=wp.vec3)  # the step's output velocity
    neighbour_start: wp.array(dtype=int)  # a particle's half list: neighbour_index[start:end]
    neighbour_end: wp.array(dtype=int)
    neighbour_index: wp.array(dtype=int)  # the half lists, padded by 8 for the vector loops
    pair: wp.array(dtype=wp.vec4)  # per-pair cache (gradient, kernel value) beside neighbour_index
    acc4: wp.array(dtype=wp.vec4)  # density pass sums: gradient sum and density
    acc1: wp.array(dtype=float)  # density pass sums: squared gradients
    acc3a: wp.array(dtype=wp.vec3)  # sums: position correction, or the viscosity pass's eta
    acc3b: wp.array(dtype=wp.vec3)  # sums: the viscosity pass's XSPH term
    particle_rho: wp.array(dtype=float)  # densities
    particle_lambda: wp.array(dtype=float)  # constraint multipliers
    wall_grad: wp.array(dtype=wp.vec3)  # the walls' and obstacles' density gradient per particle
    particle_omega: wp.array(dtype=wp.vec3)  # vorticity
    omega_length: wp.array(dtype=float)  # |vorticity|
    particle_vol: wp.array(dtype=float)  # volume per particle for the viscosity sums
    wall: wp.array(dtype=wp.vec2)  # the wall density table (value, gradient) by distance
    spheres: wp.array(dtype=wp.vec4)  # sphere obstacles (centre, radius)
    box_lo: wp.array(dtype=wp.vec3)  # box obstacles' lower corners
    box_hi: wp.array(dtype=wp.vec3)  # box obstacles' upper corners


@wp.func
def pass_kind(p: int, iterations: int) -> int:
    """The kind of the step's pass p (see above)."""
    if p < 2 * iterations:
        return p % 2
    return 2 + p - 2 * iterations


@wp.func
def pairs_block(kind: int, start: int, end: int, c: PassConstants, a: PassArrays):
    """The pair loops of one pass over the block [start, end)."""
    if kind == 0:
        for i in range(start, end):
            density_pair_loop(i, a.x_pred, a.neighbour_start, a.neighbour_end, a.neighbour_index, c.h, c.poly6_coef,
                              c.spiky_coef * c.vol, c.mass, c.corr_k, c.inv_corr_w_dq, c.corr_n, a.pair, a.acc4,
                              a.acc1)
    elif kind == 1:
        for i in range(start, end):
            correction_pair_loop(i, a.particle_lambda, a.neighbour_start, a.neighbour_end, a.neighbour_index, a.pair,
                                 a.acc3a)
    elif kind == 2:
        for i in range(start, end):
            vorticity_pair_loop(i, a.x_pred, a.v_tmp, a.neighbour_start, a.neighbour_end, a.neighbour_index, c.h,
                                c.poly6_coef, c.spiky_coef, c.vol, a.pair, a.particle_omega)
    else:
        for i in range(start, end):
            viscosity_pair_loop(i, a.v_tmp, a.omega_length, a.particle_vol, a.neighbour_start, a.neighbour_end,
                                a.neighbour_index, a.pair, a.acc3a, a.acc3b)


@wp.func
def finish_block(kind: int, last: int, start: int, end: int, c: PassConstants, a: PassArrays):
    """The finish of one pass over the block [start, end); ``last`` marks the last correction."""
    walls_only = a.spheres.shape[0] == 0 and a.box_lo.shape[0] == 0
    if kind == 0:
        if walls_only:
            density_finish_walls(start, end, a.x_pred, a.acc4, a.acc1, c.h, c.self_density, c.vol, c.rest_density,
                                 c.relaxation, c.lo, c.hi, a.wall, a.particle_rho, a.particle_lambda, a.wall_grad)
        else:
            for i in range(start, end):
                density_finish_at(i, a.x_pred, a.acc4, a.acc1, c.h, c.self_density, c.vol, c.rest_density,
                                  c.relaxation, c.lo, c.hi, a.wall, a.spheres, a.box_lo, a.box_hi, a.particle_rho,
                                  a.particle_lambda, a.wall_grad)
    elif kind == 1:
        if walls_only:
            correction_finish_walls(start, end, a.x_pred, a.particle_lambda, a.acc3a, a.wall_grad, c.lo, c.hi,
                                    c.radius, a.particle_x, c.inv_dt, last, a.v_tmp)
        else:
            for i in range(start, end):
                correction_finish_at(i, a.x_pred, a.particle_lambda, a.acc3a, a.wall_grad, c.lo, c.hi, c.radius,
                                     a.spheres, a.box_lo, a.box_hi, a.particle_x, c.inv_dt, last, a.v_tmp)
    elif kind == 2:
        for i in range(start, end):
            vorticity_finish_at(i, a.particle_omega, a.particle_rho, c.mass, a.omega_length, a.particle_vol)
    else:
        for i in range(start, end):
            viscosity_finish_at(i, a.v_tmp, a.particle_omega, a.acc3a, a.acc3b, c.vorticity_eps, c.xsph_c, c.dt,
                                a.particle_v)


@wp.kernel
def step_passes(thread: int, threads: int, sync: wp.array(dtype=int), yield_address: wp.uint64,
                blocks: wp.array(dtype=wp.vec2i), block_count: int, c: PassConstants, a: PassArrays):
    """Every pair pass of a step on ``blocks`` (start, end), one copy per thread (``Launcher.gang``).

    Phase 2p (even blocks) finishes pass p - 1 and runs pass p's pairs; phase 2p + 1 (odd blocks)
    runs pass p's pairs and finishes it; a last even phase finishes the last pass. That is
    ``Launcher.scatter_passes``' schedule, so the sums are added in the same order (bit-identical
    for the same blocks), whichever thread runs a block.
    """
    passes = 2 * c.iterations + 2
    last_correction = 2 * c.iterations - 1
    even = (block_count + 1) // 2
    odd = block_count // 2
    for p in range(passes + 1):
        b = gang.next_block(sync, 2 * p)
        while b < even:
            r = blocks[2 * b]
            if p > 0:
                finish_block(pass_kind(p - 1, c.iterations), int(p - 1 == last_correction), r[0], r[1], c, a)
            if p < passes:
                pairs_block(pass_kind(p, c.iterations), r[0], r[1], c, a)
            b = gang.next_block(sync, 2 * p)
        if p < passes:
            gang.barrier(sync, 2 * p, threads, yield_address)
            b = gang.next_block(sync, 2 * p + 1)
            while b < odd:
                r = blocks[2 * b + 1]
                kind = pass_kind(p, c.iterations)
                pairs_block(kind, r[0], r[1], c, a)
                finish_block(kind, int(p == last_correction), r[0], r[1], c, a)
                b = gang.next_block(sync, 2 * p + 1)
            gang.barrier(sync, 2 * p + 1, threads, yield_address)
