"""Warp kernels of screen-space fluid rendering (van der Laan et al. 2009; Green 2010) and of the
Narrow-Range Filter (Truong & Yuksel 2018).

Depth convention (see ``pipeline.camera``): positive view depth d = -z_view, 0 for empty pixels.
The narrow-range filter is written in that convention; in the paper's negative view-space z a
sample "in front by more than delta" is z_j > z_i + delta, here d_j < d_i - delta.

Per-pixel kernels take ``offset`` first and address pixel ``tid + offset`` of a row-major H x W
image, so the host can launch chunks from a thread pool.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def ray_ellipsoid(ray: wp.vec3, c: wp.vec3, m: wp.mat33) -> wp.vec2:
    """(t0, half chord in t) of the ray t * ray against the ellipsoid |M (x - c)| = 1; t0 < 0 on a miss.

    M is symmetric (the inverse of the semi-axis matrix), so the surface in the ray parameter is
    |t M ray - M c|^2 = 1, a quadratic a t^2 - 2 b t + cc = 0."""
    md = m * ray
    mc = m * c
    a = wp.dot(md, md)
    b = wp.dot(md, mc)
    cc = wp.dot(mc, mc) - 1.0
    disc = b * b - a * cc
    if disc <= 0.0:
        return wp.vec2(-1.0, 0.0)
    sq = wp.sqrt(disc)
    return wp.vec2((b - sq) / a, sq / a)


@wp.func
def ray_sphere(ray: wp.vec3, c: wp.vec3, cc: float) -> wp.vec3:
    """(entry t, exit t, chord length) of the ray t * ray against a sphere centred at c, with
    cc = |c|^2 - radius^2; the chord is -1 on a miss."""
    a = wp.dot(ray, ray)
    b = wp.dot(ray, c)
    disc = b * b - a * cc
    if disc <= 0.0:
        return wp.vec3(0.0, 0.0, -1.0)
    sq = wp.sqrt(disc)
    return wp.vec3((b - sq) / a, (b + sq) / a, 2.0 * sq / wp.sqrt(a))


@wp.func
def pixel_ray(px: int, py: int, width: int, height: int, focal: float) -> wp.vec3:
    """View-space ray through a pixel centre, scaled so that its z is -1 (t is the view depth)."""
    return wp.vec3((float(px) + 0.5 - float(width) * 0.5) / focal, -(float(py) + 0.5 - float(height) * 0.5) / focal,
                   -1.0)


@wp.func
def splat_bounds(c: wp.vec3, bound: float, focal: float, width: int, height: int, row0: int, row1: int) -> wp.vec4i:
    """Pixel box (x0, x1, y0, y1), rows clipped to [row0, row1), of a sphere of radius ``bound``
    around the view-space point c; x1 < x0 when it is behind the camera or off the band."""
    d = -c[2]
    if d <= bound:
        return wp.vec4i(0, -1, 0, -1)
    cx = float(width) * 0.5 + focal * c[0] / d
    cy = float(height) * 0.5 - focal * c[1] / d
    rp = focal * bound / wp.sqrt(d * d - bound * bound) + 1.0
    return wp.vec4i(wp.max(int(wp.floor(cx - rp)), 0), wp.min(int(wp.ceil(cx + rp)), width - 1),
                    wp.max(int(wp.floor(cy - rp)), row0), wp.min(int(wp.ceil(cy + rp)), row1 - 1))


@wp.kernel
def splat_spheres(
    offset: int,
    centers_view: wp.array(dtype=wp.vec3),
    radius: float,
    focal: float,
    width: int,
    height: int,
    row0: int,
    row1: int,
    depth: wp.array(dtype=float),
    thickness: wp.array(dtype=float),
):
    """Exact ray-sphere splat into the rows [row0, row1): nearest front-surface depth and summed
    chord length. Each launch owns a band of rows, so bands can run on several threads at once
    without races (the min and add are atomic on CUDA, where one launch covers all rows)."""
    i = wp.tid() + offset
    c = centers_view[i]
    box = splat_bounds(c, radius, focal, width, height, row0, row1)
    cc = wp.dot(c, c) - radius * radius
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            hit = ray_sphere(pixel_ray(px, py, width, height, focal), c, cc)
            if hit[2] >= 0.0:
                idx = py * width + px
                wp.atomic_min(depth, idx, hit[0])
                wp.atomic_add(thickness, idx, hit[2])


@wp.kernel
def view_centres(offset: int, centres: wp.array(dtype=wp.vec3), rot: wp.mat33d, shift: wp.vec3d,
                 out: wp.array(dtype=wp.vec3)):
    """``out[i] = rot centres[i] + shift``: world points into view space in float64, as
    ``Camera.to_view`` does on the host (equal to rounding: BLAS may sum in another order)."""
    i = wp.tid() + offset
    c = centres[i]
    v = wp.vec3()
    for a in range(3):
        acc = wp.float64(0.0)
        for j in range(3):
            acc = acc + rot[a, j] * wp.float64(c[j])
        v[a] = wp.float32(acc + shift[a])
    out[i] = v


@wp.kernel
def view_shapes(offset: int, shapes: wp.array(dtype=wp.mat33), rot: wp.mat33d, out: wp.array(dtype=wp.mat33)):
    """``out[i] = rot shapes[i] rot^T``: world-space ellipsoid shapes into view space, in float64 and
    in numpy's ``einsum("ij,njk,lk->nil")`` order (j outer, k inner, each term (R S) R summed from
    0), so the float32 result is the one the host computed before, bit for bit (tested)."""
    i = wp.tid() + offset
    s = shapes[i]
    m = wp.mat33()
    for a in range(3):
        for b in range(3):
            acc = wp.float64(0.0)
            for j in range(3):
                for k in range(3):
                    p = rot[a, j] * wp.float64(s[j, k])
                    q = p * rot[b, k]
                    acc = acc + q
            m[a, b] = wp.float32(acc)
    out[i] = m


@wp.kernel
def splat_ellipsoids(
    offset: int,
    centers_view: wp.array(dtype=wp.vec3),
    shapes: wp.array(dtype=wp.mat33),
    bounds: wp.array(dtype=float),
    focal: float,
    width: int,
    height: int,
    row0: int,
    row1: int,
    normals_pass: int,
    depth: wp.array(dtype=float),
    thickness: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
):
    """Exact ray-ellipsoid splat into the rows [row0, row1). Ellipsoid i is |shapes[i] (x - c_i)| <= 1
    in view space; ``bounds`` are the radii of their bounding spheres, which give each one's pixel
    box (cost: the pixels covered).

    First pass (``normals_pass`` 0): nearest front-surface depth and summed chord length. Second
    pass (1): the analytic view-space normal M^2 (x - c) of the ellipsoid that won each pixel's
    depth test (the one whose entry depth equals the splatted depth: the same arithmetic)."""
    i = wp.tid() + offset
    c = centers_view[i]
    box = splat_bounds(c, bounds[i], focal, width, height, row0, row1)
    m = shapes[i]
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            ray = pixel_ray(px, py, width, height, focal)
            hit = ray_ellipsoid(ray, c, m)
            if hit[0] > 0.0:
                idx = py * width + px
                if normals_pass == 0:
                    wp.atomic_min(depth, idx, hit[0])
                    wp.atomic_add(thickness, idx, 2.0 * hit[1] * wp.length(ray))
                elif hit[0] == depth[idx]:
                    normals[idx] = wp.normalize(m * (m * (ray * hit[0] - c)))


@wp.kernel
def finish_splat(offset: int, depth: wp.array(dtype=float), empty: float, mask: wp.array(dtype=float)):
    """Empty pixels (still at the ``empty`` sentinel) get depth 0 and mask 0; the rest mask 1."""
    idx = wp.tid() + offset
    if depth[idx] >= empty:
        depth[idx] = 0.0
        mask[idx] = 0.0
    else:
        mask[idx] = 1.0


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


@wp.kernel
def line_prefix(
    offset: int,
    depth_in: wp.array(dtype=float),
    width: int,
    height: int,
    axis: int,
    sums: wp.array(dtype=wp.vec3d),
):
    """Running (count, sum of depths, sum of squared depths) of the fluid pixels along one row
    (axis 0) or column (axis 1) per thread, for the stretches of ``bilateral_pass``'s wide taps.
    float64: a float32 sum over a 4K row loses the millimetres two sums are subtracted for."""
    line = wp.tid() + offset
    start = line * width
    step = 1
    n = width
    if axis == 1:
        start = line
        step = width
        n = height
    acc = wp.vec3d(0.0, 0.0, 0.0)
    for i in range(n):
        idx = start + i * step
        d = wp.float64(depth_in[idx])
        if d > wp.float64(0.0):
            acc += wp.vec3d(wp.float64(1.0), d, d * d)
        sums[idx] = acc


@wp.func
def stretch_tap(depth_in: wp.array(dtype=float), sums: wp.array(dtype=wp.vec3d), first: int, last: int,
                step: int, line_start: int, pos: int, d0: float, inv_s: float, inv_r: float,
                range_sigma: float) -> wp.vec2:
    """(sum of weight x depth, sum of weights) of the fluid pixels from line position ``first`` to
    ``last``: one tap at the stretch's mean depth and centre, weighted by its pixel count, where its
    depths spread less than a quarter of the range sigma; where they spread more (it straddles a
    depth edge, which one mean would blur across) every pixel on its own."""
    hi = sums[line_start + last * step]
    if first > 0:
        hi -= sums[line_start + (first - 1) * step]
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
    sums: wp.array(dtype=wp.vec3d),
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
    radius of 3 sigma over fluid pixels (the naive screen-space blur)."""
    idx = wp.tid() + offset
    d0 = fluid_depth(depth_in, depth_out, idx)
    if d0 <= 0.0:
        return
    col, row = pixel_of(idx, width)
    sigma = fixed_sigma
    reach = 3.0
    if fixed_sigma <= 0.0:
        sigma = bilateral_sigma(d0, focal, particle_radius, sigma_scale)
        reach = 2.0
    rad = wp.min(int(wp.ceil(reach * sigma)), max_radius)
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


@wp.func
def view_position(depth: wp.array(dtype=float), x: int, y: int, width: int, height: int, focal: float) -> wp.vec3:
    """View-space point of pixel (x, y) at its depth."""
    d = depth[y * width + x]
    return wp.vec3((float(x) + 0.5 - float(width) * 0.5) / focal * d,
                   -(float(y) + 0.5 - float(height) * 0.5) / focal * d, -d)


@wp.kernel
def normals_from_depth(
    offset: int,
    depth: wp.array(dtype=float),
    width: int,
    height: int,
    focal: float,
    normals: wp.array(dtype=wp.vec3),
):
    """Normals from reconstructed view positions; at each pixel the one-sided difference with the
    smaller depth change is used, so silhouettes do not blend with what lies behind them."""
    idx = wp.tid() + offset
    d0 = depth[idx]
    if d0 <= 0.0:
        normals[idx] = wp.vec3(0.0, 0.0, 0.0)
        return
    y = idx // width
    x = idx - y * width
    p = view_position(depth, x, y, width, height, focal)
    ddx = wp.vec3(0.0, 0.0, 0.0)
    best = float(1.0e30)
    if x + 1 < width and depth[idx + 1] > 0.0:
        q = view_position(depth, x + 1, y, width, height, focal) - p
        ddx = q
        best = wp.abs(q[2])
    if x > 0 and depth[idx - 1] > 0.0:
        q = p - view_position(depth, x - 1, y, width, height, focal)
        if wp.abs(q[2]) < best:
            ddx = q
    ddy = wp.vec3(0.0, 0.0, 0.0)
    best = float(1.0e30)
    # +Y in view space is one row up
    if y > 0 and depth[idx - width] > 0.0:
        q = view_position(depth, x, y - 1, width, height, focal) - p
        ddy = q
        best = wp.abs(q[2])
    if y + 1 < height and depth[idx + width] > 0.0:
        q = p - view_position(depth, x, y + 1, width, height, focal)
        if wp.abs(q[2]) < best:
            ddy = q
    n = wp.cross(ddx, ddy)
    ln = wp.length(n)
    if ln < 1.0e-20:
        normals[idx] = wp.vec3(0.0, 0.0, 1.0)
    else:
        normals[idx] = n / ln


@wp.kernel
def splat_motion(
    offset: int,
    centers_view: wp.array(dtype=wp.vec3),
    motion: wp.array(dtype=wp.vec4),
    radius: float,
    focal: float,
    width: int,
    height: int,
    row0: int,
    row1: int,
    depth: wp.array(dtype=float),
    band: float,
    motion_sum: wp.array(dtype=wp.vec4),
    weight: wp.array(dtype=float),
):
    """Second pass of a sphere splat into the rows [row0, row1): every particle whose front surface
    at a pixel lies within ``band`` of the splatted (nearest) depth adds its screen motion there, so
    a pixel gets the mean motion of the front-most particles it shows. Bands own their rows, as in
    ``splat_spheres``."""
    i = wp.tid() + offset
    c = centers_view[i]
    box = splat_bounds(c, radius, focal, width, height, row0, row1)
    cc = wp.dot(c, c) - radius * radius
    m = motion[i]
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            hit = ray_sphere(pixel_ray(px, py, width, height, focal), c, cc)
            if hit[2] >= 0.0:
                idx = py * width + px
                if hit[0] <= depth[idx] + band:
                    wp.atomic_add(motion_sum, idx, m)
                    wp.atomic_add(weight, idx, 1.0)


@wp.kernel
def finish_motion(offset: int, motion_sum: wp.array(dtype=wp.vec4), weight: wp.array(dtype=float),
                  motion: wp.array(dtype=wp.vec4)):
    """Mean motion per pixel (0 where no particle was splatted)."""
    idx = wp.tid() + offset
    w = weight[idx]
    if w > 0.0:
        motion[idx] = motion_sum[idx] / w
    else:
        motion[idx] = wp.vec4(0.0, 0.0, 0.0, 0.0)


@wp.kernel
def nearest_in_column(fluid: wp.array2d(dtype=wp.uint8), site_row: wp.array2d(dtype=int)):
    """First pass of the exact Euclidean feature transform (Maurer et al. 2003, the algorithm and
    tie rules of ``scipy.ndimage.distance_transform_edt``): each pixel's nearest fluid pixel within
    its own column, the upper one (lower row) on a tie; -1 in a column without fluid. One thread
    per column, two sweeps."""
    x = wp.tid()
    h = fluid.shape[0]
    last = int(-1)
    for y in range(h):
        if fluid[y, x] != wp.uint8(0):
            last = y
        site_row[y, x] = last
    below = int(-1)
    for k in range(h):
        y = h - 1 - k
        if fluid[y, x] != wp.uint8(0):
            below = y
        above = site_row[y, x]
        if below >= 0 and (above < 0 or below - y < y - above):
            site_row[y, x] = below


@wp.func
def _square_distance(site_row: int, site_col: int, y: int, x: int) -> wp.int64:
    dy = wp.int64(site_row - y)
    dx = wp.int64(site_col - x)
    return dy * dy + dx * dx


@wp.kernel
def nearest_in_row(
    site_row: wp.array2d(dtype=int),
    envelope: wp.array2d(dtype=int),
    rows_out: wp.array2d(dtype=int),
    cols_out: wp.array2d(dtype=int),
    distance_out: wp.array2d(dtype=wp.float64),
):
    """Second pass: along each row, the lower envelope of the columns' nearest pixels (``envelope``
    is the row's scratch list of site columns) and each pixel's nearest site on it, with scipy's
    exact integer tests and ties, so the nearest fluid pixel (row, column) and its distance equal
    scipy's bit for bit. No fluid at all: -1 and an infinite distance. One thread per row."""
    y = wp.tid()
    w = site_row.shape[1]
    top = int(-1)
    for col in range(w):
        r = site_row[y, col]
        if r >= 0:
            wr = wp.int64(r - y) * wp.int64(r - y)
            while top >= 1:
                c1 = envelope[y, top]
                c2 = envelope[y, top - 1]
                a = wp.int64(c1 - c2)
                b = wp.int64(col - c1)
                c = a + b
                ur = wp.int64(site_row[y, c2] - y) * wp.int64(site_row[y, c2] - y)
                vr = wp.int64(site_row[y, c1] - y) * wp.int64(site_row[y, c1] - y)
                if c * vr - b * ur - a * wr - a * b * c <= wp.int64(0):
                    break
                top -= 1
            top += 1
            envelope[y, top] = col
    if top < 0:
        for x in range(w):
            rows_out[y, x] = -1
            cols_out[y, x] = -1
            distance_out[y, x] = wp.float64(wp.inf)
        return
    k = int(0)
    for x in range(w):
        site = envelope[y, k]
        d1 = _square_distance(site_row[y, site], site, y, x)
        while k < top:
            following = envelope[y, k + 1]
            d2 = _square_distance(site_row[y, following], following, y, x)
            if d1 <= d2:
                break
            d1 = d2
            k += 1
        site = envelope[y, k]
        rows_out[y, x] = site_row[y, site]
        cols_out[y, x] = site
        distance_out[y, x] = wp.sqrt(wp.float64(d1))


@wp.kernel
def static_motion(
    offset: int,
    depth: wp.array(dtype=float),
    width: int,
    height: int,
    focal: wp.float64,
    view_rotation: wp.mat33d,
    view_shift: wp.vec3d,
    other_rotation: wp.mat33d,
    other_shift: wp.vec3d,
    other_focal: wp.float64,
    other_width: int,
    other_height: int,
    sign: wp.float64,
    gap: wp.float64,
    slot: int,
    motion_out: wp.array(dtype=wp.vec4),
):
    """The motion of a static surface at each pixel's view ``depth`` (0 or inf: none) caused by the
    camera moving: where the point lies in the other camera's image minus where it lies in this
    one (pixels, +Y up), times ``sign`` (``Vector``'s slot's) over the frame ``gap``, into
    components ``2 slot`` and ``2 slot + 1``; 0 where the point is behind the other camera. Float64
    as ``pipeline.screen.motion`` did it in numpy, from the same float32 view-space point."""
    k = wp.tid() + offset
    d = depth[k]
    if not (wp.isfinite(d) and d > 0.0):
        return
    x = k % width
    y = k // width
    half_w = wp.float64(width) / wp.float64(2.0)
    half_h = wp.float64(height) / wp.float64(2.0)
    ray_x = wp.float32((wp.float64(x) + wp.float64(0.5) - half_w) / focal)
    ray_y = wp.float32(-(wp.float64(y) + wp.float64(0.5) - half_h) / focal)
    p = wp.vec3d(wp.float64(ray_x * d), wp.float64(ray_y * d), wp.float64(-d))
    col = half_w + focal * p[0] / -p[2]
    row = half_h - focal * p[1] / -p[2]
    world = wp.transpose(view_rotation) * (p - view_shift)
    q = other_rotation * world + other_shift
    there = -q[2]
    out = motion_out[k]
    if there > wp.float64(1.0e-6):
        other_col = wp.float64(other_width) / wp.float64(2.0) + other_focal * q[0] / there
        other_row = wp.float64(other_height) / wp.float64(2.0) - other_focal * q[1] / there
        out[2 * slot] = wp.float32((other_col - col) * sign / gap)
        out[2 * slot + 1] = wp.float32(-(other_row - row) * sign / gap)
    else:
        out[2 * slot] = 0.0
        out[2 * slot + 1] = 0.0
    motion_out[k] = out


@wp.func
def ring_neighbour(k: int) -> wp.vec2i:
    """The k-th 8-neighbour offset (row, column) in ``pipeline.methods.RING_NEIGHBOURS``' order."""
    if k == 0:
        return wp.vec2i(0, 1)
    if k == 1:
        return wp.vec2i(0, -1)
    if k == 2:
        return wp.vec2i(1, 0)
    if k == 3:
        return wp.vec2i(-1, 0)
    if k == 4:
        return wp.vec2i(1, 1)
    if k == 5:
        return wp.vec2i(1, -1)
    if k == 6:
        return wp.vec2i(-1, 1)
    return wp.vec2i(-1, -1)


@wp.kernel
def fill_ring(
    covered: wp.array2d(dtype=wp.uint8),
    hole: wp.array2d(dtype=wp.uint8),
    values: wp.array3d(dtype=float),
    filled: wp.array2d(dtype=wp.uint8),
    count: wp.array(dtype=int),
):
    """One ring of ``pipeline.methods.fill_rims``: each hole pixel takes the values of its first
    covered 8-neighbour (indices clipped at the border) and is marked ``filled``. Only covered
    pixels are read and only holes written, so the ring is the same in any thread order."""
    y, x = wp.tid()
    if hole[y, x] == wp.uint8(0):
        return
    h = covered.shape[0]
    w = covered.shape[1]
    for k in range(8):
        step = ring_neighbour(k)
        r = wp.clamp(y + step[0], 0, h - 1)
        c = wp.clamp(x + step[1], 0, w - 1)
        if covered[r, c] != wp.uint8(0):
            for j in range(values.shape[2]):
                values[y, x, j] = values[r, c, j]
            filled[y, x] = wp.uint8(1)
            wp.atomic_add(count, 0, 1)
            return


@wp.kernel
def close_ring(covered: wp.array2d(dtype=wp.uint8), hole: wp.array2d(dtype=wp.uint8),
               filled: wp.array2d(dtype=wp.uint8)):
    """After ``fill_ring``: the filled pixels count as covered for the next ring."""
    y, x = wp.tid()
    if filled[y, x] != wp.uint8(0):
        covered[y, x] = wp.uint8(1)
        hole[y, x] = wp.uint8(0)
        filled[y, x] = wp.uint8(0)
