"""The CPU's fast paths of the separable bilateral filter (``filters.bilateral_pass`` holds the
method) and of the ellipsoid splat's first pass (``kernels.splat_ellipsoids``): sixteen
neighbouring pixels of a row at a time in C++ (``wp.func_native``).

Warp compiles its kernels to scalar CPU code, one pixel and one tap at a time, each tap with its own
``exp`` call. Sixteen pixels side by side in a row have their taps side by side in memory in both
passes (a row pass's tap k of pixel c is pixel c + k, a column pass's the pixel k rows down), and so
are a wide kernel's stretch sums (``line_prefix``'s planes) where the pixels share a stride: a tap
is one vector load and one vector of arithmetic, with an ``exp`` the compiler can vectorise
(``fast_exp``, Cephes' polynomial, within 2.5e-7 of the exact value). Blocks at the image's edges
or with mixed strides gather their taps instead; a block of sixteen empty pixels costs one test.
Each pixel's taps are summed in the scalar pass's order (but a stretch that straddles a depth step,
whose pixels count one by one, after the block's other taps), so the filtered depth equals the
scalar pass's to float rounding (tested), not bit for bit. A pass over a 1080p frame of 38k
particles (kernels of 18 px, stretches of 2): 31 -> 8.6 ms; of 1M particles (6 px): 15 -> 3.6 ms.

The splat (``splat_ellipsoid_rows``) keeps the Warp kernel's culling and pixel box a particle, and
tests each row of the box sixteen pixels at once with the same arithmetic, so its depth, chord and
density are the Warp kernel's bit for bit (tested); a band owns its rows, so plain stores replace
the atomics. The 1M-particle frame's splat: 145-168 -> 114-122 ms, the 38k frame's 44-51 -> 30-35.

The running sums themselves (``line_prefix_blocks``) are the scalar kernel's bit for bit: each line's
nearest pixel by vector minima, and a column pass's lines sixteen at a time (a row pass's sums stay a
scalar loop). Both passes' sums: 14.5 -> 3.1 ms at 38k particles, 7.4 -> 1.5 ms at 1M.
"""

import warp as wp

from pipeline.screen.kernels import splat_bounds

wp.set_module_options({"enable_backward": False})

LANES = 16
"""Pixels a vector: AVX-512's 16 floats (an AVX2 CPU runs them as two vectors of 8)."""

_EXP = """
// Cephes' expf: e^x = 2^n e^r, r = x - n ln 2 in two parts, e^r by a degree-6 polynomial
const float c = wp::min(wp::max(x, -87.0f), 88.0f);
const float n = wp::floor(c * 1.44269504088896341f + 0.5f);
float r = c - n * 0.693359375f;
r = r - n * -2.12194440e-4f;
const float p = ((((((1.9875691500e-4f * r + 1.3981999507e-3f) * r + 8.3334519073e-3f) * r + 4.1665795894e-2f) * r
                  + 1.6666665459e-1f) * r + 5.0000001201e-1f) * r * r + r) + 1.0f;
return p * __builtin_bit_cast(float, ((int)n + 127) << 23);
"""


_SIZES = """
// bilateral_sigma, bilateral_radius and tap_stride, as the scalar pass has them
auto sigma_of = [=](float d) -> float { return wp::max(sigma_scale * focal * particle_radius / d, 0.5f); };
auto radius_of = [=](float sigma) -> int { return wp::min((int)wp::ceil(2.0f * sigma), max_radius); };
auto stride_of = [=](int rad) -> int {
    return (max_taps <= 0 || rad <= max_taps) ? 1 : (rad + max_taps - 1) / max_taps;
};
"""

_PASS = f"""
auto fast_exp = [](float x) -> float {{{_EXP}}};  // inlined, so the loops vectorise it
{_SIZES}const float* din = depth_in.data;
const double* sm = sums.data;  // line_prefix's planes: count, sum, sum of squares
const int plane = width * height;
float* dout = depth_out.data;
const int per_row = (width + {LANES} - 1) / {LANES};
const int row = block / per_row;
const int col0 = (block - row * per_row) * {LANES};
const int base = row * width + col0;
const int lanes = wp::min({LANES}, width - col0);
const float inv_r = range_sigma > 0.0f ? 1.0f / (2.0f * range_sigma * range_sigma) : 0.0f;
const float flat = 0.0625f * range_sigma * range_sigma;
const int step = axis == 0 ? 1 : width;
const int limit = axis == 0 ? width : height;
float d0[{LANES}], inv_s[{LANES}], s[{LANES}], ws[{LANES}];
int taps[{LANES}], stride[{LANES}], pos[{LANES}], start[{LANES}], idx[{LANES}];
int one = 0, wide = 0;
for (int q = 0; q < {LANES}; ++q) {{
    const float d = q < lanes ? din[base + q] : 0.0f;
    d0[q] = d;
    s[q] = d;
    ws[q] = 1.0f;
    idx[q] = q < lanes ? base + q : 0;
    pos[q] = axis == 0 ? col0 + q : row;
    start[q] = axis == 0 ? row * width : col0 + q;
    taps[q] = 0;
    stride[q] = 1;
    inv_s[q] = 0.0f;
    if (d > 0.0f) {{
        const float sigma = sigma_of(d);
        const int rad = radius_of(sigma);
        const int st = stride_of(rad);
        inv_s[q] = 1.0f / (2.0f * sigma * sigma);
        stride[q] = st;
        taps[q] = (rad + st - 1) / st;
        if (st == 1) one = wp::max(one, taps[q]);
        else wide = wp::max(wide, taps[q]);
    }}
}}
if (one == 0 && wide == 0) {{
    for (int q = 0; q < lanes; ++q) dout[base + q] = 0.0f;
    return;
}}
// every pixel of the taps on each side, one exp for the spatial weight and one for the range's:
// pixel q's tap k at depths da (right) and db (left), where they lie on its line
auto pixel_taps = [&](int q, int k, float da, float db, bool right, bool left) {{
    const float ww = fast_exp(-(float)(k * k) * inv_s[q]);
    const float za = da - d0[q];
    const float zb = db - d0[q];
    const float wa = right && da > 0.0f ? ww * fast_exp(-za * za * inv_r) : 0.0f;
    const float wb = left && db > 0.0f ? ww * fast_exp(-zb * zb * inv_r) : 0.0f;
    s[q] += wa * da;
    ws[q] += wa;
    s[q] += wb * db;
    ws[q] += wb;
}};
const int size = width * height;
for (int k = 1; k <= one; ++k) {{
    const int ra = base + k * step, la = base - k * step;  // pixel q's taps: ra + q and la + q
    if (la >= 0 && ra + {LANES} <= size) {{  // the sixteen taps lie side by side in the image
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
        for (int q = 0; q < {LANES}; ++q) {{
            const bool on = stride[q] == 1 && k <= taps[q];
            pixel_taps(q, k, din[ra + q], din[la + q], on && pos[q] + k < limit, on && pos[q] - k >= 0);
        }}
    }} else {{
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
        for (int q = 0; q < {LANES}; ++q) {{
            const bool on = stride[q] == 1 && k <= taps[q];
            const bool right = on && pos[q] + k < limit;
            const bool left = on && pos[q] - k >= 0;
            pixel_taps(q, k, din[right ? idx[q] + k * step : 0], din[left ? idx[q] - k * step : 0], right, left);
        }}
    }}
}}
// wider kernels: a tap a stretch of stride pixels, at the stretch's mean depth from the line's
// running sums where its depths spread little (stretch_tap); the others each pixel on its own.
// Pixel q's stretch first..last, its sums at hi minus (below) those at lo: 1 where its depths
// spread (lines without wide kernels have no sums, stale numbers: only selected, never used)
auto stretch_tap = [&](int q, bool in, int first, int last, int hi, bool below, int lo) -> unsigned int {{
    const double n = sm[hi] - (below ? sm[lo] : 0.0);
    const double sum = sm[plane + hi] - (below ? sm[plane + lo] : 0.0);
    const double sq = sm[2 * plane + hi] - (below ? sm[2 * plane + lo] : 0.0);
    const bool some = in && n > 0.0;
    const double inv = 1.0 / (some ? n : 1.0);
    const double mean = some ? sum * inv : 0.0;
    const float spread = (float)(sq * inv - mean * mean);
    const float centre = 0.5f * (float)(first + last) - (float)pos[q];
    const float dz = (float)mean - d0[q];
    const bool one_tap = some && spread <= flat;
    const float w = one_tap ? (float)n * fast_exp(-centre * centre * inv_s[q] - dz * dz * inv_r) : 0.0f;
    s[q] += one_tap ? w * (float)mean : 0.0f;
    ws[q] += w;
    return (some && !one_tap) ? 1u : 0u;
}};
unsigned int apart[{LANES}];
int common = 0;  // the stride of every pixel with wide taps, -1 where they differ
for (int q = 0; q < {LANES}; ++q) {{
    apart[q] = 0u;
    if (taps[q] > 0 && stride[q] > 1) common = (common == 0 || common == stride[q]) ? stride[q] : -1;
}}
const int p_lo = axis == 0 ? col0 : row;
const int p_hi = axis == 0 ? col0 + {LANES} - 1 : row;
for (int t = 1; t <= wide; ++t) {{
    const int nc = (t - 1) * common + 1, fc = t * common;
    if (common > 0 && lanes == {LANES} && p_hi + fc <= limit - 1 && p_lo - fc >= 1) {{
        // one stride and no stretch cut by the line's ends: the sixteen pixels' sums lie side by side
        const int r1 = base + fc * step, r0 = base + (nc - 1) * step;  // pixel q's: r1 + q, ...
        const int l1 = base - nc * step, l0 = base - (fc + 1) * step;
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
        for (int q = 0; q < {LANES}; ++q) {{
            const bool on = stride[q] > 1 && t <= taps[q];
            unsigned int split = stretch_tap(q, on, pos[q] + nc, pos[q] + fc, r1 + q, true, r0 + q);
            split |= stretch_tap(q, on, pos[q] - fc, pos[q] - nc, l1 + q, true, l0 + q) << 1;
            apart[q] |= split << (2 * ((t - 1) & 15));
        }}
    }} else {{
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
        for (int q = 0; q < {LANES}; ++q) {{
            const bool on = stride[q] > 1 && t <= taps[q];
            const int near = (t - 1) * stride[q] + 1;
            const int far = t * stride[q];
            const bool right = on && pos[q] + near < limit;  // the right side's tap, then the left's
            const int r_first = pos[q] + near, r_last = wp::min(pos[q] + far, limit - 1);
            unsigned int split = stretch_tap(q, right, r_first, r_last, right ? start[q] + r_last * step : 0,
                                             right, right ? start[q] + (r_first - 1) * step : 0);
            const bool left = on && pos[q] - near >= 0;
            const int l_first = wp::max(pos[q] - far, 0), l_last = pos[q] - near;
            const bool below = left && l_first > 0;
            split |= stretch_tap(q, left, l_first, l_last, left ? start[q] + l_last * step : 0, below,
                                 below ? start[q] + (l_first - 1) * step : 0) << 1;
            apart[q] |= split << (2 * ((t - 1) & 15));
        }}
    }}
    if ((t & 15) == 0 || t == wide) {{  // the stretches whose depths spread: each pixel on its own
        const int t0 = (t - 1) & ~15;
        for (int q = 0; q < lanes; ++q) {{
            if (!apart[q]) continue;
            for (int u = t0 + 1; u <= t; ++u) {{
                const unsigned int bits = apart[q] >> (2 * ((u - 1) & 15));
                for (int side = 0; side < 2; ++side) {{
                    if (!((bits >> side) & 1u)) continue;
                    const int near = (u - 1) * stride[q] + 1;
                    const int far = u * stride[q];
                    const int first = side == 0 ? pos[q] + near : wp::max(pos[q] - far, 0);
                    const int last = side == 0 ? wp::min(pos[q] + far, limit - 1) : pos[q] - near;
                    for (int i = first; i <= last; ++i) {{
                        const float d = din[start[q] + i * step];
                        if (d > 0.0f) {{
                            const float k = (float)(i - pos[q]);
                            const float z = d - d0[q];
                            const float w = fast_exp(-k * k * inv_s[q] - z * z * inv_r);
                            s[q] += w * d;
                            ws[q] += w;
                        }}
                    }}
                }}
            }}
            apart[q] = 0u;
        }}
    }}
}}
for (int q = 0; q < lanes; ++q) dout[base + q] = d0[q] > 0.0f ? s[q] / ws[q] : 0.0f;
"""

_PREFIX = f"""
{_SIZES}const float* din = depth_in.data;
double* sm = sums.data;
const int plane = width * height;
if (axis == 0) {{  // row ``block``: the nearest pixel's kernel by a vector minimum, then the sums in order
    const float* line = din + block * width;
    float least[{LANES}];
    for (int q = 0; q < {LANES}; ++q) least[q] = 3.0e38f;
    int i0 = 0;
    for (; i0 + {LANES} <= width; i0 += {LANES}) {{
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
        for (int q = 0; q < {LANES}; ++q) {{
            const float d = line[i0 + q];
            least[q] = d > 0.0f && d < least[q] ? d : least[q];
        }}
    }}
    for (int i = i0; i < width; ++i) least[0] = line[i] > 0.0f && line[i] < least[0] ? line[i] : least[0];
    float nearest = least[0];
    for (int q = 1; q < {LANES}; ++q) nearest = least[q] < nearest ? least[q] : nearest;
    if (nearest == 3.0e38f || stride_of(radius_of(sigma_of(nearest))) == 1) return;
    double n = 0.0, sum = 0.0, sq = 0.0;
    for (int i = 0; i < width; ++i) {{
        const double d = (double)line[i];
        if (d > 0.0) {{
            n += 1.0;
            sum += d;
            sq += d * d;
        }}
        const int idx = block * width + i;
        sm[idx] = n;
        sm[plane + idx] = sum;
        sm[2 * plane + idx] = sq;
    }}
    return;
}}
// columns {LANES} at a time (block ``block``), each lane's own sums, every row's {LANES} side by side
const int col0 = block * {LANES};
const int lanes = wp::min({LANES}, width - col0);
float nearest[{LANES}];
for (int q = 0; q < {LANES}; ++q) nearest[q] = 3.0e38f;
for (int i = 0; i < height; ++i) {{
    const float* line = din + i * width + col0;
    if (lanes == {LANES}) {{
        for (int q = 0; q < {LANES}; ++q) nearest[q] = line[q] > 0.0f && line[q] < nearest[q] ? line[q] : nearest[q];
    }} else {{
        for (int q = 0; q < lanes; ++q) nearest[q] = line[q] > 0.0f && line[q] < nearest[q] ? line[q] : nearest[q];
    }}
}}
bool need[{LANES}];
bool any = false;
for (int q = 0; q < {LANES}; ++q) {{
    need[q] = q < lanes && nearest[q] != 3.0e38f && stride_of(radius_of(sigma_of(nearest[q]))) > 1;
    any = any || need[q];
}}
if (!any) return;
double n[{LANES}], sum[{LANES}], sq[{LANES}];
for (int q = 0; q < {LANES}; ++q) n[q] = sum[q] = sq[q] = 0.0;
for (int i = 0; i < height; ++i) {{
    const int row = i * width + col0;
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
    for (int q = 0; q < {LANES}; ++q) {{
        const double d = (double)din[need[q] ? row + q : 0];
        const bool in = d > 0.0;
        n[q] += in ? 1.0 : 0.0;
        sum[q] += in ? d : 0.0;
        sq[q] += in ? d * d : 0.0;
        if (need[q]) {{
            sm[row + q] = n[q];
            sm[plane + row + q] = sum[q];
            sm[2 * plane + row + q] = sq[q];
        }}
    }}
}}
"""


@wp.func_native(_EXP)
def fast_exp(x: float) -> float:
    """e^x for x in [-87, 88] (the clamp's ends beyond), vectorisable."""
    ...


@wp.func_native(_PASS)
def bilateral_block(block: int, depth_in: wp.array(dtype=float), sums: wp.array(dtype=wp.float64),
                    depth_out: wp.array(dtype=float), width: int, height: int, axis: int, focal: float,
                    particle_radius: float, sigma_scale: float, range_sigma: float, max_radius: int,
                    max_taps: int):
    """``filters.bilateral_pass`` of the 16 pixels of block ``block`` (row-major blocks of 16
    pixels of a row)."""
    ...


@wp.kernel
def bilateral_pass_blocks(
    offset: int,
    depth_in: wp.array(dtype=float),
    width: int,
    height: int,
    axis: int,
    focal: float,
    particle_radius: float,
    sigma_scale: float,
    range_sigma: float,
    max_radius: int,
    max_taps: int,
    sums: wp.array(dtype=wp.float64),
    depth_out: wp.array(dtype=float),
):
    """``filters.bilateral_pass`` (a particle-sized kernel, no fixed sigma) over blocks of
    ``LANES`` pixels: launch ``blocks(width, height)``."""
    bilateral_block(wp.tid() + offset, depth_in, sums, depth_out, width, height, axis, focal, particle_radius,
                    sigma_scale, range_sigma, max_radius, max_taps)


@wp.func_native(_PREFIX)
def prefix_block(block: int, depth_in: wp.array(dtype=float), sums: wp.array(dtype=wp.float64), width: int,
                 height: int, axis: int, focal: float, particle_radius: float, sigma_scale: float, max_radius: int,
                 max_taps: int):
    """``filters.line_prefix`` of row ``block`` (axis 0) or of the ``LANES`` columns of block
    ``block`` (axis 1)."""
    ...


@wp.kernel
def line_prefix_blocks(
    offset: int,
    depth_in: wp.array(dtype=float),
    width: int,
    height: int,
    axis: int,
    focal: float,
    particle_radius: float,
    sigma_scale: float,
    max_radius: int,
    max_taps: int,
    sums: wp.array(dtype=wp.float64),
):
    """``filters.line_prefix``, the same sums bit for bit (the same additions in the same order),
    with the nearest pixel found by vector minima and a column pass's lines ``LANES`` at a time:
    launch ``lines(width, height, axis)``."""
    prefix_block(wp.tid() + offset, depth_in, sums, width, height, axis, focal, particle_radius, sigma_scale,
                 max_radius, max_taps)


def lines(width: int, height: int, axis: int) -> int:
    """The launch size of ``line_prefix_blocks``: rows, or blocks of ``LANES`` columns."""
    return height if axis == 0 else (width + LANES - 1) // LANES


def blocks(width: int, height: int) -> int:
    """The blocks of ``bilateral_pass_blocks`` for an image."""
    return (width + LANES - 1) // LANES * height


_SPLAT_ROW = f"""
// row py's pixels x0..x1 of ellipsoid |M (x - c)| <= 1 (mc = M c), {LANES} side by side:
// kernels.ray_ellipsoid per pixel, then the nearest depth, the summed chord and the largest density
const float ry = -((float)py + 0.5f - (float)height * 0.5f) / focal;
const int row = py * width;
float* dr = depth.data + row;
float* tr = thickness.data + row;
float* nr = density_out.data + (with_density ? row : 0);
for (int x = x0; x <= x1; x += {LANES}) {{
    const int n = x1 - x + 1;
#if defined(__clang__) && !defined(__CUDA_ARCH__)
#pragma clang loop vectorize(assume_safety) vectorize_width({LANES}) interleave(disable)
#endif
    for (int q = 0; q < {LANES}; ++q) {{
        if (q < n) {{
            const float rx = ((float)(x + q) + 0.5f - (float)width * 0.5f) / focal;
            const float d0 = m.data[0][0] * rx + m.data[0][1] * ry - m.data[0][2];
            const float d1 = m.data[1][0] * rx + m.data[1][1] * ry - m.data[1][2];
            const float d2 = m.data[2][0] * rx + m.data[2][1] * ry - m.data[2][2];
            const float a = d0 * d0 + d1 * d1 + d2 * d2;
            const float b = d0 * mc.c[0] + d1 * mc.c[1] + d2 * mc.c[2];
            const float o0 = d1 * mc.c[2] - d2 * mc.c[1];
            const float o1 = d2 * mc.c[0] - d0 * mc.c[2];
            const float o2 = d0 * mc.c[1] - d1 * mc.c[0];
            const float disc = a - (o0 * o0 + o1 * o1 + o2 * o2);
            if (disc > 0.0f) {{
                const float sq = wp::sqrt(disc);
                const float t0 = (b - sq) / a;
                if (t0 > 0.0f) {{
                    dr[x + q] = wp::min(dr[x + q], t0);
                    tr[x + q] += 2.0f * (sq / a) * wp::sqrt(rx * rx + ry * ry + 1.0f);
                    if (with_density) nr[x + q] = wp::max(nr[x + q], dens);
                }}
            }}
        }}
    }}
}}
"""


@wp.func_native(_SPLAT_ROW)
def splat_row(py: int, x0: int, x1: int, m: wp.mat33, mc: wp.vec3, focal: float, width: int, height: int,
              depth: wp.array(dtype=float), thickness: wp.array(dtype=float), with_density: int, dens: float,
              density_out: wp.array(dtype=float)):
    """``kernels.splat_ellipsoids``' first pass over one row of an ellipsoid's pixel box."""
    ...


@wp.kernel
def splat_ellipsoid_rows(
    offset: int,
    centers_view: wp.array(dtype=wp.vec3),
    shapes: wp.array(dtype=wp.mat33),
    bounds: wp.array(dtype=float),
    focal: float,
    width: int,
    height: int,
    row0: int,
    row1: int,
    depth: wp.array(dtype=float),
    thickness: wp.array(dtype=float),
    with_density: int,
    density: wp.array(dtype=float),
    density_out: wp.array(dtype=float),
):
    """``kernels.splat_ellipsoids``' first pass (depth, chord, density; no normals) into the rows
    [row0, row1), each row of an ellipsoid's box sixteen pixels a vector (``splat_row``). A band's
    rows are its own: plain stores, no atomics."""
    i = wp.tid() + offset
    c = centers_view[i]
    box = splat_bounds(c, bounds[i], focal, width, height, row0, row1)
    m = shapes[i]
    dens = float(0.0)
    if with_density != 0:
        dens = density[i]
    mc = m * c
    for py in range(box[2], box[3] + 1):
        splat_row(py, box[0], box[1], m, mc, focal, width, height, depth, thickness, with_density, dens, density_out)
