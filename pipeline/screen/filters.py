"""Warp kernels of the screen-space depth filters: the bilateral filter (the 2D window and its
separable passes, Pham & van Vliet 2005) and the Narrow-Range Filter (Truong & Yuksel 2018).

Depth convention (see ``pipeline.camera``): positive view depth d = -z_view, 0 for empty pixels.
The narrow-range filter is written in that convention; in the paper's negative view-space z a
sample "in front by more than delta" is z_j > z_i + delta, here d_j < d_i - delta.

Per-pixel kernels take ``offset`` first and address pixel ``tid + offset`` of a row-major H x W
image, so the host can launch chunks from a thread pool.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def fluid_depth(depth_in: wp.array(dtype=float), depth_out: wp.array(dtype=float), idx: int) -> float:
    """A filter's input depth at a pixel; an empty pixel (0) is passed through to the output as empty."""
    d0 = depth_in[idx]
    if d0 <= 0.0:
        depth_out[idx] = 0.0
    return d0


@wp.func
def pixel_of(idx: int, width: int):
    """(column, row) of a flat pixel index."""
    row = idx // width
    return idx - row * width, row


@wp.func
def tap_stride(radius: int, max_taps: int) -> int:
    """Pixels between taps so that at most ``max_taps`` fall on each side of a pass (0: every pixel).

    A kernel wider than max_taps samples every stride-th pixel: its cost per pixel no longer grows
    with the projected particle size, and with at least max_taps / 2 taps per sigma the sphere bumps
    (about two projected radii apart) are still sampled several times per period."""
    if max_taps <= 0 or radius <= max_taps:
        return 1
    return (radius + max_taps - 1) // max_taps


@wp.func
def bilateral_sigma(d0: float, focal: float, particle_radius: float, sigma_scale: float) -> float:
    """Spatial sigma of the bilateral filter at depth d0: a multiple of the projected radius (px)."""
    return wp.max(sigma_scale * focal * particle_radius / d0, 0.5)


@wp.kernel
def bilateral_filter(
    offset: int,
    depth_in: wp.array(dtype=float),
    width: int,
    height: int,
    focal: float,
    particle_radius: float,
    sigma_scale: float,
    range_sigma: float,
    max_radius: int,
    depth_out: wp.array(dtype=float),
):
    """Bilateral Gaussian: spatial sigma = scale x projected particle radius, range sigma in metres."""
    idx = wp.tid() + offset
    d0 = fluid_depth(depth_in, depth_out, idx)
    if d0 <= 0.0:
        return
    col, row = pixel_of(idx, width)
    sigma = bilateral_sigma(d0, focal, particle_radius, sigma_scale)
    rad = wp.min(int(wp.ceil(2.0 * sigma)), max_radius)
    inv_s = 1.0 / (2.0 * sigma * sigma)
    inv_r = 1.0 / (2.0 * range_sigma * range_sigma)
    s = float(0.0)
    ws = float(0.0)
    for dy in range(-rad, rad + 1):
        y = row + dy
        if y >= 0 and y < height:
            for dx in range(-rad, rad + 1):
                x = col + dx
                if x >= 0 and x < width:
                    dk = depth_in[y * width + x]
                    if dk > 0.0:
                        dz = dk - d0
                        w = wp.exp(-float(dx * dx + dy * dy) * inv_s - dz * dz * inv_r)
                        s += w * dk
                        ws += w
    depth_out[idx] = s / ws


@wp.func
def bilateral_radius(d0: float, focal: float, particle_radius: float, sigma_scale: float, fixed_sigma: float,
                     max_radius: int) -> wp.vec2:
    """(spatial sigma, kernel radius in px) of ``bilateral_pass`` at a pixel of depth d0: a fixed
    sigma and 3 sigma, or ``bilateral_sigma`` and 2 sigma, the radius capped at ``max_radius``."""
    sigma = fixed_sigma
    reach = 3.0
    if fixed_sigma <= 0.0:
        sigma = bilateral_sigma(d0, focal, particle_radius, sigma_scale)
        reach = 2.0
    return wp.vec2(sigma, float(wp.min(int(wp.ceil(reach * sigma)), max_radius)))


@wp.kernel
def line_prefix(
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
    """Running (count, sum of depths, sum of squared depths) of the fluid pixels along one row
    (axis 0) or column (axis 1) per thread, for the stretches of ``bilateral_pass``'s wide taps:
    three planes of the image's size in ``sums``, so neighbouring pixels' sums lie side by side.
    float64: a float32 sum over a 4K row loses the millimetres two sums are subtracted for.
    A line whose nearest fluid pixel's kernel needs no stretches (the widest on the line, as the
    kernel narrows with depth) is left as it is: ``bilateral_pass`` reads a line's sums only for
    its own pixels with stretches (a 1080p frame of particles under 5 px: none)."""
    line = wp.tid() + offset
    start = line * width
    step = 1
    n = width
    if axis == 1:
        start = line
        step = width
        n = height
    nearest = float(0.0)
    for i in range(n):
        di = depth_in[start + i * step]
        if di > 0.0 and (nearest == 0.0 or di < nearest):
            nearest = di
    if nearest == 0.0:
        return
    rad = int(bilateral_radius(nearest, focal, particle_radius, sigma_scale, 0.0, max_radius)[1])
    if tap_stride(rad, max_taps) == 1:
        return
    plane = width * height
    acc = wp.vec3d(0.0, 0.0, 0.0)
    for i in range(n):
        idx = start + i * step
        d = wp.float64(depth_in[idx])
        if d > wp.float64(0.0):
            acc += wp.vec3d(wp.float64(1.0), d, d * d)
        sums[idx] = acc[0]
        sums[plane + idx] = acc[1]
        sums[2 * plane + idx] = acc[2]


@wp.func
def stretch_tap(depth_in: wp.array(dtype=float), sums: wp.array(dtype=wp.float64), first: int, last: int,
                step: int, line_start: int, pos: int, d0: float, inv_s: float, inv_r: float,
                range_sigma: float) -> wp.vec2:
    """(sum of weight x depth, sum of weights) of the fluid pixels from line position ``first`` to
    ``last``: one tap at the stretch's mean depth and centre, weighted by its pixel count, where its
    depths spread less than a quarter of the range sigma; where they spread more (it straddles a
    depth edge, which one mean would blur across) every pixel on its own."""
    plane = depth_in.shape[0]
    a = line_start + last * step
    hi = wp.vec3d(sums[a], sums[plane + a], sums[2 * plane + a])
    if first > 0:
        b = line_start + (first - 1) * step
        hi -= wp.vec3d(sums[b], sums[plane + b], sums[2 * plane + b])
    count = float(hi[0])
    if count == 0.0:
        return wp.vec2(0.0, 0.0)
    inv = wp.float64(1.0) / hi[0]
    mean = hi[1] * inv
    spread = float(hi[2] * inv - mean * mean)
    centre = 0.5 * float(first + last) - float(pos)
    if spread <= 0.0625 * range_sigma * range_sigma:
        dz = float(mean) - d0
        w = count * wp.exp(-centre * centre * inv_s - dz * dz * inv_r)
        return wp.vec2(w * float(mean), w)
    out = wp.vec2(0.0, 0.0)
    for i in range(first, last + 1):
        d = depth_in[line_start + i * step]
        if d > 0.0:
            k = float(i - pos)
            dz = d - d0
            w = wp.exp(-k * k * inv_s - dz * dz * inv_r)
            out += wp.vec2(w * d, w)
    return out


@wp.kernel
def bilateral_pass(
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
    fixed_sigma: float,
    max_taps: int,
    sums: wp.array(dtype=wp.float64),
    depth_out: wp.array(dtype=float),
):
    """One 1D pass of the separable bilateral filter (Pham & van Vliet 2005).

    The same spatial sigma, radius and range sigma as ``bilateral_filter``; the range reference is
    the pixel's value in this pass's input. Two passes (x, then y) cost O(radius) per pixel instead
    of O(radius^2). A radius wider than ``max_taps`` (> 0) is covered by at most ``max_taps`` taps a
    side, each standing for the ``tap_stride`` pixels of its stretch (``stretch_tap``): the cost per
    pixel stops growing with the projected particle size, and neighbouring pixels still average
    overlapping samples of the sphere bumps (single pixels every k apart made the normals 5x
    rougher).
    With ``fixed_sigma`` > 0 and ``range_sigma`` 0 it is a plain Gaussian pass of that sigma and a
    radius of 3 sigma over fluid pixels (the naive screen-space blur). The CPU runs the bilateral
    (not the Gaussian) sixteen pixels a vector instead: ``pipeline.screen.native``."""
    idx = wp.tid() + offset
    d0 = fluid_depth(depth_in, depth_out, idx)
    if d0 <= 0.0:
        return
    col, row = pixel_of(idx, width)
    kernel = bilateral_radius(d0, focal, particle_radius, sigma_scale, fixed_sigma, max_radius)
    sigma = kernel[0]
    rad = int(kernel[1])
    inv_s = 1.0 / (2.0 * sigma * sigma)
    inv_r = float(0.0)
    if range_sigma > 0.0:
        inv_r = 1.0 / (2.0 * range_sigma * range_sigma)
    step = 1
    pos = col
    limit = width
    line_start = row * width
    if axis == 1:
        step = width
        pos = row
        limit = height
        line_start = col
    s = d0
    ws = float(1.0)
    stride = tap_stride(rad, max_taps)
    if stride == 1:
        for k in range(1, rad + 1):
            ww = wp.exp(-float(k * k) * inv_s)
            if pos + k < limit:
                da = depth_in[idx + k * step]
                if da > 0.0:
                    dz = da - d0
                    w = ww * wp.exp(-dz * dz * inv_r)
                    s += w * da
                    ws += w
            if pos - k >= 0:
                db = depth_in[idx - k * step]
                if db > 0.0:
                    dz = db - d0
                    w = ww * wp.exp(-dz * dz * inv_r)
                    s += w * db
                    ws += w
    else:
        # tap t stands for offsets (t - 1) stride + 1 .. t stride on each side
        taps = (rad + stride - 1) // stride
        for t in range(1, taps + 1):
            near = (t - 1) * stride + 1
            far = t * stride
            if pos + near < limit:
                s_w = stretch_tap(depth_in, sums, pos + near, wp.min(pos + far, limit - 1), step, line_start, pos,
                                  d0, inv_s, inv_r, range_sigma)
                s += s_w[0]
                ws += s_w[1]
            if pos - near >= 0:
                s_w = stretch_tap(depth_in, sums, wp.max(pos - far, 0), pos - near, step, line_start, pos, d0,
                                  inv_s, inv_r, range_sigma)
                s += s_w[0]
                ws += s_w[1]
    depth_out[idx] = s / ws


@wp.func
def nrf_sample(dk: float, d0: float, mu: float) -> float:
    """Sample value after clamping: empty pixels and samples far behind count as d0 + mu."""
    if dk <= 0.0:
        return d0 + mu
    return dk


@wp.kernel
def narrow_range_pass(
    offset: int,
    depth_in: wp.array(dtype=float),
    width: int,
    height: int,
    axis: int,
    focal: float,
    particle_radius: float,
    radius_scale: float,
    max_radius: int,
    delta: float,
    mu: float,
    max_taps: int,
    depth_out: wp.array(dtype=float),
):
    """One 1D pass of the Narrow-Range Filter with bias correction and dynamic range.

    Walking outwards on both sides, a sample in front of the pixel by more than the current
    near bound gets weight 0, and so does its mirrored partner (bias correction: the kernel stays
    symmetric). A sample behind by more than the far bound is clamped to d0 + mu. An accepted
    sample widens the range to its own value +- delta (dynamic range), so an oblique plane is
    followed instead of being cut off as a discontinuity. Taps are ``tap_stride`` pixels apart, so
    a pass costs at most 2 max_taps + 1 taps at any projected particle size (0: every pixel).
    """
    idx = wp.tid() + offset
    d0 = fluid_depth(depth_in, depth_out, idx)
    if d0 <= 0.0:
        return
    col, row = pixel_of(idx, width)
    rad = wp.min(int(wp.ceil(radius_scale * focal * particle_radius / d0)), max_radius)
    if rad < 1:
        depth_out[idx] = d0
        return
    stride = tap_stride(rad, max_taps)
    taps = rad // stride
    sigma = float(rad) / 3.0
    inv = 1.0 / (2.0 * sigma * sigma)
    near1 = d0 - delta
    far1 = d0 + delta
    near2 = near1
    far2 = far1
    s = d0
    ws = float(1.0)
    for t in range(1, taps + 1):
        k = t * stride
        xa = col
        ya = row
        xb = col
        yb = row
        if axis == 0:
            xa = col + k
            xb = col - k
        else:
            ya = row + k
            yb = row - k
        # beyond the image border there is no information: drop the pair (keeps symmetry)
        if xa < 0 or xa >= width or ya < 0 or ya >= height or xb < 0 or xb >= width or yb < 0 or yb >= height:
            break
        da = depth_in[ya * width + xa]
        db = depth_in[yb * width + xb]
        w = wp.exp(-float(k * k) * inv)
        wa = w
        wb = w
        va = nrf_sample(da, d0, mu)
        vb = nrf_sample(db, d0, mu)
        a_front = da > 0.0 and va < near1
        b_front = db > 0.0 and vb < near2
        if a_front or b_front:
            wa = 0.0
            wb = 0.0
        # only a sample that is neither in front nor behind the range widens the range
        if va > far1:
            va = d0 + mu
        elif da > 0.0 and not a_front:
            near1 = wp.min(near1, va - delta)
            far1 = wp.max(far1, va + delta)
        if vb > far2:
            vb = d0 + mu
        elif db > 0.0 and not b_front:
            near2 = wp.min(near2, vb - delta)
            far2 = wp.max(far2, vb + delta)
        s += wa * va + wb * vb
        ws += wa + wb
    depth_out[idx] = s / ws


@wp.kernel
def narrow_range_cleanup(
    offset: int,
    depth_in: wp.array(dtype=float),
    width: int,
    height: int,
    radius: int,
    delta: float,
    mu: float,
    depth_out: wp.array(dtype=float),
):
    """Small fixed-radius 2D narrow-range pass that removes the stripes of the separable passes."""
    sigma = wp.max(float(radius) / 3.0, 0.5)
    inv = 1.0 / (2.0 * sigma * sigma)
    idx = wp.tid() + offset
    d0 = fluid_depth(depth_in, depth_out, idx)
    if d0 <= 0.0:
        return
    col, row = pixel_of(idx, width)
    s = d0
    ws = float(1.0)
    # each offset in the upper half-plane together with its mirror image
    for dy in range(0, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy > 0 or dx > 0:
                xa = col + dx
                ya = row + dy
                xb = col - dx
                yb = row - dy
                if xa < 0 or xa >= width or ya < 0 or ya >= height or xb < 0 or xb >= width or yb < 0 or yb >= height:
                    continue
                da = depth_in[ya * width + xa]
                db = depth_in[yb * width + xb]
                va = nrf_sample(da, d0, mu)
                vb = nrf_sample(db, d0, mu)
                if (da > 0.0 and va < d0 - delta) or (db > 0.0 and vb < d0 - delta):
                    continue
                if va > d0 + delta:
                    va = d0 + mu
                if vb > d0 + delta:
                    vb = d0 + mu
                w = wp.exp(-float(dx * dx + dy * dy) * inv)
                s += w * (va + vb)
                ws += 2.0 * w
    depth_out[idx] = s / ws
