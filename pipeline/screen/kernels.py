"""Warp kernels of screen-space fluid rendering (van der Laan et al. 2009; Green 2010): the sphere
and ellipsoid splats, normals from depth, the motion pass and the nearest-fluid transforms. The
depth filters are in ``pipeline.screen.filters``.

Depth convention (see ``pipeline.camera``): positive view depth d = -z_view, 0 for empty pixels.

Per-pixel kernels take ``offset`` first and address pixel ``tid + offset`` of a row-major H x W
image, so the host can launch chunks from a thread pool.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def ray_ellipsoid(ray: wp.vec3, c: wp.vec3, m: wp.mat33) -> wp.vec2:
    """(t0, half chord in t) of the ray t * ray against the ellipsoid |M (x - c)| = 1; t0 < 0 on a miss.

    M is symmetric (the inverse of the semi-axis matrix), so the surface in the ray parameter is
    |t M ray - M c|^2 = 1, a quadratic a t^2 - 2 b t + cc = 0 with cc = |M c|^2 - 1. Its discriminant
    b^2 - a cc is taken as a - |M ray x M c|^2 (Lagrange's identity): for a particle of millimetres
    metres away b^2 and a cc agree to a part in 10^5, and their float32 difference put the rim
    anywhere within a tenth of its radius."""
    md = m * ray
    mc = m * c
    a = wp.dot(md, md)
    b = wp.dot(md, mc)
    off = wp.cross(md, mc)
    disc = a - wp.dot(off, off)
    if disc <= 0.0:
        return wp.vec2(-1.0, 0.0)
    sq = wp.sqrt(disc)
    return wp.vec2((b - sq) / a, sq / a)


@wp.func
def ray_sphere(ray: wp.vec3, c: wp.vec3, r2: float) -> wp.vec3:
    """(entry t, exit t, chord length) of the ray t * ray against the sphere of squared radius r2
    centred at c; the chord is -1 on a miss. The discriminant is a r2 - |ray x c|^2, not
    b^2 - a (|c|^2 - r2), for the reason ``ray_ellipsoid`` gives."""
    a = wp.dot(ray, ray)
    b = wp.dot(ray, c)
    off = wp.cross(ray, c)
    disc = a * r2 - wp.dot(off, off)
    if disc <= 0.0:
        return wp.vec3(0.0, 0.0, -1.0)
    sq = wp.sqrt(disc)
    return wp.vec3((b - sq) / a, (b + sq) / a, 2.0 * sq / wp.sqrt(a))


@wp.func
def pixel_ray(px: int, py: int, width: int, height: int, focal: float) -> wp.vec3:
    """View-space ray through a pixel centre, scaled so that its z is -1 (t is the view depth)."""
    return wp.vec3((float(px) + 0.5 - float(width) * 0.5) / focal, -(float(py) + 0.5 - float(height) * 0.5) / focal,
                   -1.0)


SPLAT_BOX_SLACK = wp.constant(0.01)
"""Pixels ``splat_bounds`` adds on each side of a silhouette's exact span, for float rounding: a
float32 pixel coordinate of a 4K image rounds by 2e-4 px at most, so a centre that far outside the
span cannot be hit."""


@wp.func
def tangent_span(a: float, d: float, r: float) -> wp.vec2:
    """The slopes a' / d' of the two lines through the eye tangent to the circle of radius r around
    (a, d), d > r: along one image axis, the ray slopes that meet a sphere lie between them."""
    k = d * d - r * r
    s = r * wp.sqrt(a * a + k)
    return wp.vec2((a * d - s) / k, (a * d + s) / k)


@wp.func
def splat_bounds(c: wp.vec3, bound: float, focal: float, width: int, height: int, row0: int, row1: int) -> wp.vec4i:
    """Pixel box (x0, x1, y0, y1), rows clipped to [row0, row1), of the pixels whose centre rays can
    meet the sphere of radius ``bound`` around the view-space point c: its silhouette's exact span
    along each image axis (an off-axis sphere's silhouette is an ellipse, longer than its on-axis
    circle). x1 < x0 when it is behind the camera or off the band."""
    d = -c[2]
    if d <= bound:
        return wp.vec4i(0, -1, 0, -1)
    # pixel px's ray has slope (px + 0.5 - w / 2) / f across, -(py + 0.5 - h / 2) / f up (pixel_ray);
    # spans clamped to the image before they become integers (a sphere at the lens spans a lot).
    # Rows first: each band of a splat culls every particle, and most lie off the band.
    v = tangent_span(c[1], d, bound)
    hh = float(height) * 0.5
    y0 = wp.clamp(hh - focal * v[1] - 0.5 - SPLAT_BOX_SLACK, -1.0, float(height))
    y1 = wp.clamp(hh - focal * v[0] - 0.5 + SPLAT_BOX_SLACK, -1.0, float(height))
    top = wp.max(int(wp.ceil(y0)), row0)
    bottom = wp.min(int(wp.floor(y1)), row1 - 1)
    if bottom < top:
        return wp.vec4i(0, -1, 0, -1)
    u = tangent_span(c[0], d, bound)
    hw = float(width) * 0.5
    x0 = wp.clamp(hw + focal * u[0] - 0.5 - SPLAT_BOX_SLACK, -1.0, float(width))
    x1 = wp.clamp(hw + focal * u[1] - 0.5 + SPLAT_BOX_SLACK, -1.0, float(width))
    return wp.vec4i(wp.max(int(wp.ceil(x0)), 0), wp.min(int(wp.floor(x1)), width - 1), top, bottom)


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
    r2 = radius * radius
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            hit = ray_sphere(pixel_ray(px, py, width, height, focal), c, r2)
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
    with_density: int,
    density: wp.array(dtype=float),
    density_out: wp.array(dtype=float),
):
    """Exact ray-ellipsoid splat into the rows [row0, row1). Ellipsoid i is |shapes[i] (x - c_i)| <= 1
    in view space; ``bounds`` are the radii of their bounding spheres, which give each one's pixel
    box (cost: the pixels covered).

    First pass (``normals_pass`` 0): nearest front-surface depth and summed chord length, and
    ``with_density`` the largest ``density`` of the ellipsoids a pixel's ray meets. Second pass (1):
    the analytic view-space normal M^2 (x - c) of the ellipsoid that won each pixel's depth test
    (the one whose entry depth equals the splatted depth: the same arithmetic)."""
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
                    if with_density != 0:
                        wp.atomic_max(density_out, idx, density[i])
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
    r2 = radius * radius
    m = motion[i]
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            hit = ray_sphere(pixel_ray(px, py, width, height, focal), c, r2)
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
