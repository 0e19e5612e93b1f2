"""The CPU's fast paths of the anisotropy and the density at the kernel centres (``kernels.py``
holds the methods): sums over a cell table in C++ (``wp.func_native``), 16 neighbours a vector.

Warp compiles its kernels to scalar CPU code, one neighbour at a time through the hash grid's query;
a particle's 500 neighbours within the covariance support (2h = 10 r) then cost about 4 ns each.
Here the particles sorted by the hash grid's cell order (``CellTable``) make each row of cells one
contiguous run of positions; for the anisotropy a row is cut to the support sphere's chord through
it, and its neighbours go 16 at a time through a loop the CPU compiler vectorises (square roots,
divisions and the ten weighted moments at once, in 16 partial sums a moment). The density reads
the kernels (centre, bounding radius, G, det G) copied into the table's order as planes
(``table_kernels``), so a row's kernels load side by side too. Sixteen lanes read sixteen entries
side by side even past a run's end (those lanes count nothing): a lane index that stops at the run
made the compiler gather each one, 1.6-2x slower. The sums' order is not the scalar loop's, so the
kernels and densities equal the hash grid path's to float rounding (tested), not bit for bit.
"""

import warp as wp

from pipeline.surface.kernels import Anisotropy, anisotropy_from_moments

wp.set_module_options({"enable_backward": False})


@wp.struct
class CellTable:
    """The particles in the hash grid's cell order: ``ids`` the particle of each entry, ``x`` their
    positions in that order, ``first[s]`` the first entry whose table slot is s or more
    (``first[cells]`` = the count), so the entries of slots s..t are first[s] .. first[t + 1] - 1.
    Slots as Warp's grid makes them: cell (i, j, k) = floor(x / ``cell``) (``inv`` its float32
    inverse) at slot (k mod dim_z) dim_x dim_y + (j mod dim_y) dim_x + (i mod dim_x)."""

    first: wp.array(dtype=int)
    ids: wp.array(dtype=int)
    x: wp.array(dtype=wp.vec3)
    dim_x: int
    dim_y: int
    dim_z: int
    cell: float
    inv: float


@wp.func
def _slot(t: CellTable, p: wp.vec3) -> int:
    """The table slot of a point (Warp's ``hash_grid_index``)."""
    cx = int(wp.floor(p[0] * t.inv)) % t.dim_x
    cy = int(wp.floor(p[1] * t.inv)) % t.dim_y
    cz = int(wp.floor(p[2] * t.inv)) % t.dim_z
    if cx < 0:
        cx += t.dim_x
    if cy < 0:
        cy += t.dim_y
    if cz < 0:
        cz += t.dim_z
    return cz * (t.dim_x * t.dim_y) + cy * t.dim_x + cx


@wp.kernel
def table_entries(offset: int, t: CellTable, particle_x: wp.array(dtype=wp.vec3), slots: wp.array(dtype=int)):
    """Each entry's position and slot (entries already in slot order: ``t.ids`` from the grid)."""
    k = wp.tid() + offset
    p = particle_x[t.ids[k]]
    t.x[k] = p
    slots[k] = _slot(t, p)


@wp.kernel
def table_first(offset: int, n: int, slots: wp.array(dtype=int), first: wp.array(dtype=int)):
    """``CellTable.first`` from the entries' sorted slots: entry k starts every slot after its
    predecessor's, up to its own (k = n closes the table)."""
    k = wp.tid() + offset
    lo = int(-1)
    if k > 0:
        lo = slots[k - 1]
    hi = first.shape[0] - 1
    if k < n:
        hi = slots[k]
    for s in range(lo + 1, hi + 1):
        first[s] = k


LANES = 16
"""Neighbours a vector: AVX-512's 16 floats (measured: 8 is 10% slower on this CPU; an AVX2 CPU
runs them as two vectors of 8)."""

Moments = wp.types.vector(length=11, dtype=wp.float32)
"""sum w, sum w r (3), sum w r r^T (xx, xy, xz, yy, yz, zz) and the neighbour count."""

_ROW_RUNS = """
const int* first = t.first.data;
// v's slot along an axis of d slots (Warp's hash_grid_index)
auto wrap = [](int v, int d) -> int { const int m = v % d; return m < 0 ? m + d : m; };
// the table entries of slots ca..cb of the row of slots starting at ``row`` as one run
// [runs[0], runs[1]), or two where the row wraps round the table's edge; returns how many
auto row_runs = [&](int row, int ca, int cb, int* runs) -> int {
    runs[0] = first[row + ca];
    if (ca <= cb) {
        runs[1] = first[row + cb + 1];
        return 1;
    }
    runs[1] = first[row + t.dim_x];
    runs[2] = first[row];
    runs[3] = first[row + cb + 1];
    return 2;
};
"""

_MOMENTS = f"""
const float* xs = reinterpret_cast<const float*>(t.x.data);
{_ROW_RUNS}const float inv = t.inv;
const float cell = t.cell;
const float s = support;
const float s2 = s * s;
float aw[{LANES}], a0[{LANES}], a1[{LANES}], a2[{LANES}], axx[{LANES}], axy[{LANES}], axz[{LANES}];
float ayy[{LANES}], ayz[{LANES}], azz[{LANES}];
int an[{LANES}];
for (int q = 0; q < {LANES}; ++q) {{
    aw[q] = a0[q] = a1[q] = a2[q] = axx[q] = axy[q] = axz[q] = ayy[q] = ayz[q] = azz[q] = 0.0f;
    an[q] = 0;
}}
const int entries = t.ids.shape[0];
// entry k's offset from xi, weighted into lane q's moments where it lies within the support
auto add = [&](int q, int k, bool live) {{
    const float r0 = xs[3 * k] - xi.c[0];
    const float r1 = xs[3 * k + 1] - xi.c[1];
    const float r2 = xs[3 * k + 2] - xi.c[2];
    const float d2 = r0 * r0 + r1 * r1 + r2 * r2;
    const bool in = live && d2 < s2;
    const float tt = wp::sqrt(d2) / s;
    const float w = in ? 1.0f - tt * tt * tt : 0.0f;
    aw[q] += w;
    a0[q] += r0 * w;
    a1[q] += r1 * w;
    a2[q] += r2 * w;
    axx[q] += r0 * r0 * w;
    axy[q] += r0 * r1 * w;
    axz[q] += r0 * r2 * w;
    ayy[q] += r1 * r1 * w;
    ayz[q] += r1 * r2 * w;
    azz[q] += r2 * r2 * w;
    an[q] += in ? 1 : 0;
}};
// the cells the hash grid's query visits (each axis at most once round the table: a table narrower
// than the query, which Warp's too caps so, is read without culling), rows along x cut to the
// support sphere's chord through them
const int x0 = (int)wp::floor((xi.c[0] - s) * inv);
const int y0 = (int)wp::floor((xi.c[1] - s) * inv);
const int z0 = (int)wp::floor((xi.c[2] - s) * inv);
const int x1 = wp::min((int)wp::floor((xi.c[0] + s) * inv), x0 + t.dim_x - 1);
const int y1 = wp::min((int)wp::floor((xi.c[1] + s) * inv), y0 + t.dim_y - 1);
const int z1 = wp::min((int)wp::floor((xi.c[2] + s) * inv), z0 + t.dim_z - 1);
const bool cull = x1 - x0 + 1 < t.dim_x && y1 - y0 + 1 < t.dim_y && z1 - z0 + 1 < t.dim_z;
for (int z = z0; z <= z1; ++z) {{
    const float lz = z * cell;
    const float gz = wp::max(0.0f, wp::max(lz - xi.c[2], xi.c[2] - (lz + cell)));
    const int cz = wrap(z, t.dim_z);
    for (int y = y0; y <= y1; ++y) {{
        const float ly = y * cell;
        const float gy = wp::max(0.0f, wp::max(ly - xi.c[1], xi.c[1] - (ly + cell)));
        // a little past the support, for rounding: the lanes still test d2 < s2 exactly
        const float rest = s2 * 1.002f - gz * gz - gy * gy;
        if (cull && rest < 0.0f) continue;
        int xa = x0, xb = x1;
        if (cull) {{
            const float half = wp::sqrt(rest);
            xa = wp::max(x0, (int)wp::floor((xi.c[0] - half) * inv));
            xb = wp::min(x1, (int)wp::floor((xi.c[0] + half) * inv));
            if (xb < xa) continue;
        }}
        int runs[4];
        const int nruns = row_runs((cz * t.dim_y + wrap(y, t.dim_y)) * t.dim_x, wrap(xa, t.dim_x), wrap(xb, t.dim_x),
                                   runs);
        for (int g = 0; g < nruns; ++g) {{
            const int end = runs[2 * g + 1];
            for (int k0 = runs[2 * g]; k0 < end; k0 += {LANES}) {{
                const int m = end - k0;
                if (k0 + {LANES} <= entries) {{  // the lanes read side by side, those past the run weigh 0
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
                    for (int q = 0; q < {LANES}; ++q) add(q, k0 + q, q < m);
                }} else {{  // at the table's end the lanes past the run reread its first entry instead
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
                    for (int q = 0; q < {LANES}; ++q) add(q, k0 + (q < m ? q : 0), q < m);
                }}
            }}
        }}
    }}
}}
wp::vec_t<11, wp::float32> out(0.0f);  // Moments
int n = 0;
for (int q = 0; q < {LANES}; ++q) {{
    out.c[0] += aw[q];
    out.c[1] += a0[q];
    out.c[2] += a1[q];
    out.c[3] += a2[q];
    out.c[4] += axx[q];
    out.c[5] += axy[q];
    out.c[6] += axz[q];
    out.c[7] += ayy[q];
    out.c[8] += ayz[q];
    out.c[9] += azz[q];
    n += an[q];
}}
out.c[10] = (float)n;
return out;
"""


@wp.func_native(_MOMENTS)
def cell_moments(xi: wp.vec3, t: CellTable, support: float) -> Moments:
    """The weighted moments of the offsets to xi of the table's points within ``support``."""
    ...


@wp.kernel
def anisotropy_of_table(
    offset: int,
    which: wp.array(dtype=int),
    t: CellTable,
    particle_x: wp.array(dtype=wp.vec3),
    a: Anisotropy,
    centre_out: wp.array(dtype=wp.vec3),
    g_out: wp.array(dtype=wp.mat33),
    extent_out: wp.array(dtype=float),
):
    """``kernels.particle_anisotropy`` of the particles listed in ``which``, from ``cell_moments``."""
    i = which[wp.tid() + offset]
    xi = particle_x[i]
    m = cell_moments(xi, t, a.support)
    wrr = wp.mat33(m[4], m[5], m[6], m[5], m[7], m[8], m[6], m[8], m[9])
    anisotropy_from_moments(i, xi, m[0], wp.vec3(m[1], m[2], m[3]), wrr, int(m[10]), a, centre_out, g_out,
                            extent_out)


KERNEL_PLANES = 11
"""``table_kernels``' planes: the kernel centre (3), its squared bounding radius (a little past, as
``kernels.centre_density`` tests it), G's upper triangle (00, 01, 02, 11, 12, 22: G is symmetric,
to the rounding of the products that make it) and det G."""


@wp.kernel
def table_kernels(offset: int, t: CellTable, centres: wp.array(dtype=wp.vec3), kernel_g: wp.array(dtype=wp.mat33),
                  extents: wp.array(dtype=float), planes: wp.array(dtype=float)):
    """Each table entry's kernel in the table's order, ``KERNEL_PLANES`` planes of one float an entry:
    a row of cells' kernels then lie side by side for ``table_density``."""
    k = wp.tid() + offset
    n = t.ids.shape[0]
    j = t.ids[k]
    c = centres[j]
    e = extents[j]
    g = kernel_g[j]
    planes[k] = c[0]
    planes[n + k] = c[1]
    planes[2 * n + k] = c[2]
    planes[3 * n + k] = e * e * 1.001
    planes[4 * n + k] = g[0, 0]
    planes[5 * n + k] = g[0, 1]
    planes[6 * n + k] = g[0, 2]
    planes[7 * n + k] = g[1, 1]
    planes[8 * n + k] = g[1, 2]
    planes[9 * n + k] = g[2, 2]
    planes[10 * n + k] = wp.determinant(g)


_DENSITY = f"""
{_ROW_RUNS}
const float* kp = planes.data;
const int n = t.ids.shape[0];
const float inv = t.inv;
float phi[{LANES}];
for (int q = 0; q < {LANES}; ++q) phi[q] = 0.0f;
float total = 0.0f;
// entry k's kernel at ci into lane q's sum
auto add = [&](int q, int k, bool live) {{
    const float r0 = ci.c[0] - kp[k];
    const float r1 = ci.c[1] - kp[n + k];
    const float r2 = ci.c[2] - kp[2 * n + k];
    const bool in = live && r0 * r0 + r1 * r1 + r2 * r2 < kp[3 * n + k];
    const float g01 = kp[5 * n + k], g02 = kp[6 * n + k], g12 = kp[8 * n + k];
    const float u0 = kp[4 * n + k] * r0 + g01 * r1 + g02 * r2;
    const float u1 = g01 * r0 + kp[7 * n + k] * r1 + g12 * r2;
    const float u2 = g02 * r0 + g12 * r1 + kp[9 * n + k] * r2;
    const float q2 = u0 * u0 + u1 * u1 + u2 * u2;
    const float w = 1.0f - q2;
    phi[q] += in && q2 < 1.0f ? kp[10 * n + k] * w * w * w : 0.0f;
}};
// every cell the hash grid's query visits around xi (the kernel's bounding radius decides, not the
// distance to xi: no cell is culled), each axis at most once round the table
const int x0 = (int)wp::floor((xi.c[0] - reach) * inv);
const int y0 = (int)wp::floor((xi.c[1] - reach) * inv);
const int z0 = (int)wp::floor((xi.c[2] - reach) * inv);
const int x1 = wp::min((int)wp::floor((xi.c[0] + reach) * inv), x0 + t.dim_x - 1);
const int y1 = wp::min((int)wp::floor((xi.c[1] + reach) * inv), y0 + t.dim_y - 1);
const int z1 = wp::min((int)wp::floor((xi.c[2] + reach) * inv), z0 + t.dim_z - 1);
const int ca = wrap(x0, t.dim_x), cb = wrap(x1, t.dim_x);  // every row spans the same columns
for (int z = z0; z <= z1; ++z) {{
    const int cz = wrap(z, t.dim_z);
    for (int y = y0; y <= y1; ++y) {{
        int runs[4];
        const int nruns = row_runs((cz * t.dim_y + wrap(y, t.dim_y)) * t.dim_x, ca, cb, runs);
        for (int g = 0; g < nruns; ++g) {{
            const int end = runs[2 * g + 1];
            for (int k0 = runs[2 * g]; k0 < end; k0 += {LANES}) {{
                const int m = end - k0;
                if (k0 + {LANES} <= n) {{  // the lanes read side by side, those past the run count nothing
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
                    for (int q = 0; q < {LANES}; ++q) add(q, k0 + q, q < m);
                }} else {{  // at the table's end the lanes past the run reread its first entry instead
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
                    for (int q = 0; q < {LANES}; ++q) add(q, k0 + (q < m ? q : 0), q < m);
                }}
            }}
        }}
        // the cap, a row of cells at a time (past it the sum is the cap whatever follows)
        total = 0.0f;
        for (int q = 0; q < {LANES}; ++q) total += phi[q];
        if (total * amplitude >= cap) return cap;
    }}
}}
return wp::min(total * amplitude, cap);
"""


@wp.func_native(_DENSITY)
def table_density(xi: wp.vec3, ci: wp.vec3, t: CellTable, planes: wp.array(dtype=float), reach: float,
                  amplitude: float, cap: float) -> float:
    """``kernels.centre_density`` at ``ci`` of the kernels (``table_kernels``' planes) of the table's
    entries in the cells within ``reach`` of ``xi``."""
    ...


@wp.kernel
def density_of_table(offset: int, which: wp.array(dtype=int), t: CellTable, particle_x: wp.array(dtype=wp.vec3),
                     centres: wp.array(dtype=wp.vec3), planes: wp.array(dtype=float), reach: float, amplitude: float,
                     cap: float, density_out: wp.array(dtype=float)):
    """``kernels.centre_density`` of the particles listed in ``which``, 16 candidates a vector."""
    i = which[wp.tid() + offset]
    density_out[i] = table_density(particle_x[i], centres[i], t, planes, reach, amplitude, cap)
