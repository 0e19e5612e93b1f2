"""The CPU's fast path of the anisotropy (``kernels.py`` holds the method): each particle's weighted
neighbour moments summed in C++ (``wp.func_native``) over a cell table, 16 neighbours a vector.

Warp compiles its kernels to scalar CPU code, one neighbour at a time through the hash grid's query;
a particle's 500 neighbours within the covariance support (2h = 10 r) then cost about 4 ns each.
Here the particles sorted by the hash grid's cell order (``CellTable``) make each row of cells one
contiguous run of positions; a row is cut to the support sphere's chord through it, and its
neighbours go 16 at a time through a loop the CPU compiler vectorises (square roots, divisions and
the ten weighted moments at once, in 16 partial sums a moment). The sums' order is not the scalar
loop's, so the kernels equal the hash grid path's to float rounding (tested), not bit for bit.
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

_MOMENTS = f"""
const float* xs = reinterpret_cast<const float*>(t.x.data);
const int* first = t.first.data;
const float inv = t.inv;
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
const int dx = t.dim_x;
for (int z = z0; z <= z1; ++z) {{
    const float lz = z * cell;
    const float gz = wp::max(0.0f, wp::max(lz - xi.c[2], xi.c[2] - (lz + cell)));
    int cz = z % t.dim_z;
    if (cz < 0) cz += t.dim_z;
    for (int y = y0; y <= y1; ++y) {{
        const float ly = y * cell;
        const float gy = wp::max(0.0f, wp::max(ly - xi.c[1], xi.c[1] - (ly + cell)));
        // a little past the support, for rounding: the lanes still test d2 < s2 exactly
        const float rest = s2 * 1.002f - gz * gz - gy * gy;
        if (cull && rest < 0.0f) continue;
        int cy = y % t.dim_y;
        if (cy < 0) cy += t.dim_y;
        const int row = (cz * t.dim_y + cy) * dx;
        int xa = x0, xb = x1;
        if (cull) {{
            const float half = wp::sqrt(rest);
            xa = wp::max(x0, (int)wp::floor((xi.c[0] - half) * inv));
            xb = wp::min(x1, (int)wp::floor((xi.c[0] + half) * inv));
            if (xb < xa) continue;
        }}
        int ca = xa % dx;
        if (ca < 0) ca += dx;
        int cb = xb % dx;
        if (cb < 0) cb += dx;
        int runs[4];
        int nruns = 1;
        runs[0] = first[row + ca];
        if (ca <= cb) {{
            runs[1] = first[row + cb + 1];
        }} else {{  // the row wraps round the table's edge
            runs[1] = first[row + dx];
            runs[2] = first[row];
            runs[3] = first[row + cb + 1];
            nruns = 2;
        }}
        for (int g = 0; g < nruns; ++g) {{
            const int end = runs[2 * g + 1];
            for (int k0 = runs[2 * g]; k0 < end; k0 += {LANES}) {{
                const int m = end - k0;
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
                for (int q = 0; q < {LANES}; ++q) {{
                    const int k = k0 + (q < m ? q : 0);  // lanes past the run reread its first entry, weight 0
                    const float r0 = xs[3 * k] - xi.c[0];
                    const float r1 = xs[3 * k + 1] - xi.c[1];
                    const float r2 = xs[3 * k + 2] - xi.c[2];
                    const float d2 = r0 * r0 + r1 * r1 + r2 * r2;
                    const bool in = q < m && d2 < s2;
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
