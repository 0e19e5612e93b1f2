"""Warp kernels of the anisotropic-kernel surface (Yu & Turk, "Reconstructing Surfaces of
Particle-Based Fluids Using Anisotropic Kernels", TOG 2013) and of the mesh ray caster.

Per particle: a weighted mean and covariance of the neighbours within 2h (weights
w = 1 - (d / 2h)^3), Laplacian-smoothed centres, an eigen-decomposition with eigenvalue clamping
(k_r, k_s, k_n, N_eps) giving the kernel matrix G = (1/h) R S^-1 R^T, then the density
phi(x) = sum_j V_j det(G_j) P(|G_j (x - c_j)|) splatted on a grid, P the normalised poly6 profile.
"""

import warp as wp

from pipeline.screen.kernels import pixel_ray, ray_ellipsoid
from pipeline.sph import POLY6_NORM

wp.set_module_options({"enable_backward": False})

EMPTY_FRONT = wp.constant(1.0e30)
"""``nearest_front``'s depth of a tile no sphere covers (the silhouette's band counts as one)."""


@wp.struct
class Anisotropy:
    """Yu & Turk's parameters of ``particle_anisotropy``: the covariance ``support`` and the kernel
    radius h (m), the centre ``smoothing`` (lambda), the eigenvalue clamps k_r, k_s (as ``ks_scale``,
    which maps a full neighbourhood to scale 1) and k_n, and N_eps."""

    support: float
    kernel_radius: float
    smoothing: float
    kr: float
    ks_scale: float
    kn: float
    n_eps: int


@wp.struct
class TileView:
    """A camera (world-to-view ``rotation`` and ``translation``, ``focal`` length and image size in
    pixels) over screen tiles of ``tile_px`` pixels, ``border`` tiles past each image edge, and the
    particle ``radius`` (m): what ``nearest_front`` and ``mark_near_front`` share."""

    rotation: wp.mat33
    translation: wp.vec3
    focal: float
    width: int
    height: int
    tile_px: float
    border: int
    tiles_x: int
    tiles_y: int
    radius: float


@wp.func
def anisotropy_from_moments(
    i: int,
    xi: wp.vec3,
    wsum: float,
    wr: wp.vec3,
    wrr: wp.mat33,
    count: int,
    a: Anisotropy,
    centre_out: wp.array(dtype=wp.vec3),
    g_out: wp.array(dtype=wp.mat33),
    extent_out: wp.array(dtype=float),
):
    """Particle i's smoothed centre, kernel matrix G and bounding radius from the weighted moments
    of its neighbours' offsets r = x_j - x_i: sum w, sum w r, sum w r r^T and the neighbour count.

    ``a.ks_scale`` maps covariance eigenvalues to kernel scales so that a full neighbourhood gives
    1 (Yu & Turk's k_s = 1400 does this in their units).
    """
    kernel_radius = a.kernel_radius
    mean_r = wr / wsum
    centre_out[i] = xi + mean_r * a.smoothing
    if count - 1 < a.n_eps:
        s = a.kn * kernel_radius
        g_out[i] = wp.identity(3, dtype=float) * (1.0 / s)
        extent_out[i] = s
        return
    cov = wrr / wsum - wp.outer(mean_r, mean_r)
    Q = wp.mat33()
    e = wp.vec3()
    wp.eig3(cov, Q, e)
    top = wp.max(e[0], wp.max(e[1], e[2]))
    floor = top / a.kr
    s0 = a.ks_scale * wp.max(e[0], floor)
    s1 = a.ks_scale * wp.max(e[1], floor)
    s2 = a.ks_scale * wp.max(e[2], floor)
    inv = wp.mat33(1.0 / s0, 0.0, 0.0, 0.0, 1.0 / s1, 0.0, 0.0, 0.0, 1.0 / s2)
    g_out[i] = Q * inv * wp.transpose(Q) * (1.0 / kernel_radius)
    extent_out[i] = kernel_radius * wp.max(s0, wp.max(s1, s2))


@wp.func
def particle_anisotropy(
    i: int,
    grid: wp.uint64,
    particle_x: wp.array(dtype=wp.vec3),
    a: Anisotropy,
    centre_out: wp.array(dtype=wp.vec3),
    g_out: wp.array(dtype=wp.mat33),
    extent_out: wp.array(dtype=float),
):
    """Smoothed centre, kernel matrix G and bounding radius of particle i's ellipsoid, its
    neighbours found through the hash grid (the CPU's vectorised form: ``pipeline.surface.native``)."""
    support = a.support
    xi = particle_x[i]
    # one pass: weighted first and second moments of the offsets r = x_j - x_i (offsets rather than
    # positions keep the float32 moments far from cancellation), cov = E[r r^T] - E[r] E[r]^T
    q = wp.hash_grid_query(grid, xi, support)
    wsum = float(0.0)
    wr = wp.vec3(0.0, 0.0, 0.0)
    # the six distinct entries of sum w r r^T (the products are those of wp.outer, so the mirrored
    # matrix below is bit for bit the full one, for two thirds of the work)
    wxx = float(0.0)
    wxy = float(0.0)
    wxz = float(0.0)
    wyy = float(0.0)
    wyz = float(0.0)
    wzz = float(0.0)
    count = int(0)
    j = int(0)
    support2 = support * support
    while wp.hash_grid_query_next(q, j):
        r = particle_x[j] - xi
        d2 = wp.dot(r, r)
        if d2 < support2:
            t = wp.sqrt(d2) / support
            w = 1.0 - t * t * t
            wsum += w
            wr += r * w
            wxx += r[0] * r[0] * w
            wxy += r[0] * r[1] * w
            wxz += r[0] * r[2] * w
            wyy += r[1] * r[1] * w
            wyz += r[1] * r[2] * w
            wzz += r[2] * r[2] * w
            count += 1
    wrr = wp.mat33(wxx, wxy, wxz, wxy, wyy, wyz, wxz, wyz, wzz)
    anisotropy_from_moments(i, xi, wsum, wr, wrr, count, a, centre_out, g_out, extent_out)


@wp.kernel
def compute_anisotropy_of(
    offset: int,
    which: wp.array(dtype=int),
    grid: wp.uint64,
    particle_x: wp.array(dtype=wp.vec3),
    a: Anisotropy,
    centre_out: wp.array(dtype=wp.vec3),
    g_out: wp.array(dtype=wp.mat33),
    extent_out: wp.array(dtype=float),
):
    """``particle_anisotropy`` of the particles listed in ``which`` (the others keep their values; every
    particle in the grid's cell order keeps each thread's neighbours in cache)."""
    particle_anisotropy(which[wp.tid() + offset], grid, particle_x, a, centre_out, g_out, extent_out)


@wp.kernel
def grid_order(offset: int, grid: wp.uint64, order_out: wp.array(dtype=int)):
    """The particles in the hash grid's cell order (neighbours near each other in memory)."""
    k = wp.tid() + offset
    order_out[k] = wp.hash_grid_point_id(grid, k)


@wp.func
def tile_of(view: TileView, p: wp.vec3) -> wp.vec3:
    """(column, row, view depth) of a world point, its column and row in tiles (fractional, counted
    from the border's first tile); depth <= the radius: in front of no tile."""
    v = view.rotation * p + view.translation
    d = -v[2]
    if d <= view.radius:
        return wp.vec3(-1.0, -1.0, d)
    return wp.vec3((float(view.width) * 0.5 + view.focal * v[0] / d) / view.tile_px + float(view.border),
                   (float(view.height) * 0.5 - view.focal * v[1] / d) / view.tile_px + float(view.border), d)


@wp.func
def sphere_front(x: wp.vec3, view: TileView, front_out: wp.array(dtype=float)):
    """Into ``front_out``: the nearest surface of the sphere of ``view.radius`` around world point x
    through each tile centre it covers."""
    c = tile_of(view, x)
    d = c[2]
    if d <= view.radius:
        return
    r = view.radius
    reach = view.focal * r / d / view.tile_px  # the sphere's projected radius in tiles
    world_per_tile = view.tile_px * d / view.focal
    for ty in range(wp.max(int(wp.floor(c[1] - reach)), 0), wp.min(int(wp.floor(c[1] + reach)) + 1, view.tiles_y)):
        for tx in range(wp.max(int(wp.floor(c[0] - reach)), 0),
                        wp.min(int(wp.floor(c[0] + reach)) + 1, view.tiles_x)):
            dx = float(tx) + 0.5 - c[0]
            dy = float(ty) + 0.5 - c[1]
            rho2 = (dx * dx + dy * dy) * world_per_tile * world_per_tile
            if rho2 < r * r:
                wp.atomic_min(front_out, ty * view.tiles_x + tx, d - wp.sqrt(r * r - rho2))


@wp.kernel
def nearest_front(offset: int, particle_x: wp.array(dtype=wp.vec3), view: TileView, front_out: wp.array(dtype=float)):
    """A coarse depth buffer of the particles as spheres: each screen tile keeps the nearest sphere
    surface through its centre."""
    sphere_front(particle_x[wp.tid() + offset], view, front_out)


@wp.kernel
def nearest_kernel_front(
    offset: int,
    particle_x: wp.array(dtype=wp.vec3),
    own: wp.array(dtype=wp.uint8),
    centres: wp.array(dtype=wp.vec3),
    kernel_g: wp.array(dtype=wp.mat33),
    extents: wp.array(dtype=float),
    scale: float,
    view: TileView,
    front_out: wp.array(dtype=float),
):
    """``nearest_front`` of the particles as the ellipsoids their kernels draw (``scale G``, bounding
    radius ``extent / scale``: ``scale_ellipsoids``), each tile keeping the nearest ellipsoid surface
    through its centre: where kernels shrank or moved, what their spheres hid shows through. A
    particle without its ``own`` kernel has the interior one, its sphere of radius r."""
    i = wp.tid() + offset
    if own[i] == wp.uint8(0):
        sphere_front(particle_x[i], view, front_out)
        return
    c = view.rotation * centres[i] + view.translation
    d = -c[2]
    bound = extents[i] / scale
    if d <= bound:
        return
    m = view.rotation * (kernel_g[i] * scale) * wp.transpose(view.rotation)
    tile_x = (float(view.width) * 0.5 + view.focal * c[0] / d) / view.tile_px + float(view.border)
    tile_y = (float(view.height) * 0.5 - view.focal * c[1] / d) / view.tile_px + float(view.border)
    reach = view.focal * bound / wp.sqrt(d * d - bound * bound) / view.tile_px
    for ty in range(wp.max(int(wp.floor(tile_y - reach)), 0), wp.min(int(wp.floor(tile_y + reach)) + 1, view.tiles_y)):
        for tx in range(wp.max(int(wp.floor(tile_x - reach)), 0),
                        wp.min(int(wp.floor(tile_x + reach)) + 1, view.tiles_x)):
            px = (float(tx) + 0.5 - float(view.border)) * view.tile_px
            py = (float(ty) + 0.5 - float(view.border)) * view.tile_px
            ray = wp.vec3((px - float(view.width) * 0.5) / view.focal, -(py - float(view.height) * 0.5) / view.focal,
                          -1.0)
            hit = ray_ellipsoid(ray, c, m)
            if hit[0] > 0.0:
                wp.atomic_min(front_out, ty * view.tiles_x + tx, hit[0])


@wp.kernel
def depth_behind_front(
    offset: int,
    particle_x: wp.array(dtype=wp.vec3),
    view: TileView,
    front: wp.array(dtype=float),
    behind_out: wp.array(dtype=float),
):
    """How far each particle lies under the sphere surface seen through its tile (``nearest_front``),
    measured along that surface's normal (from the tiles' depth differences): -1 next to an empty
    tile (the silhouette: always kept), ``EMPTY_FRONT`` behind the camera or off the tiles."""
    i = wp.tid() + offset
    behind_out[i] = EMPTY_FRONT
    c = tile_of(view, particle_x[i])
    d = c[2]
    if d <= view.radius:
        return
    tx = int(wp.floor(c[0]))
    ty = int(wp.floor(c[1]))
    w = view.tiles_x
    if tx < 0 or ty < 0 or tx >= w or ty >= view.tiles_y:
        return
    right = front[ty * w + wp.min(tx + 1, w - 1)]
    left = front[ty * w + wp.max(tx - 1, 0)]
    below = front[wp.min(ty + 1, view.tiles_y - 1) * w + tx]
    above = front[wp.max(ty - 1, 0) * w + tx]
    if wp.max(wp.max(right, left), wp.max(below, above)) >= EMPTY_FRONT:  # at the silhouette: kept
        behind_out[i] = -1.0
        return
    # the depth behind the seen surface, as a distance along that surface's normal: a surface seen
    # at a grazing angle lies far behind its nearest front along the view ray, yet close to it
    world_per_tile = view.tile_px * d / view.focal
    sx = (right - left) / world_per_tile
    sy = (below - above) / world_per_tile
    behind_out[i] = (d - view.radius - front[ty * w + tx]) / wp.sqrt(1.0 + 0.25 * (sx * sx + sy * sy))


@wp.kernel
def interior_kernels(offset: int, particle_x: wp.array(dtype=wp.vec3), kernel_radius: float,
                     centre_out: wp.array(dtype=wp.vec3), g_out: wp.array(dtype=wp.mat33),
                     extent_out: wp.array(dtype=float)):
    """The kernel of a full interior neighbourhood for every particle: its own place, G = I / h."""
    i = wp.tid() + offset
    centre_out[i] = particle_x[i]
    g_out[i] = wp.identity(3, dtype=float) * (1.0 / kernel_radius)
    extent_out[i] = kernel_radius


@wp.kernel
def centre_density(offset: int, which: wp.array(dtype=int), grid: wp.uint64, particle_x: wp.array(dtype=wp.vec3),
                   reach: float, centres: wp.array(dtype=wp.vec3), kernel_g: wp.array(dtype=wp.mat33),
                   extents: wp.array(dtype=float), amplitude: float, cap: float, density_out: wp.array(dtype=float)):
    """The anisotropic density sum_j A det(G_j) P(|G_j (c_i - c_j)|) at the kernel centre of each
    particle listed in ``which``, over the kernels of the particles the grid finds within ``reach``
    of its position (``KernelMaker.densities``), up to ``cap``. A candidate further than its kernel's
    bounding radius is skipped before the matrix product (it adds nothing: ``grid_kernel_sum``)."""
    i = which[wp.tid() + offset]
    x = centres[i]
    q = wp.hash_grid_query(grid, particle_x[i], reach)
    phi = float(0.0)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        r = x - centres[j]
        e = extents[j]
        if wp.dot(r, r) >= e * e * 1.001:
            continue
        G = kernel_g[j]
        u = G * r
        q2 = wp.dot(u, u)
        if q2 < 1.0:
            t = 1.0 - q2
            phi += wp.determinant(G) * t * t * t
            if phi * amplitude >= cap:
                break
    density_out[i] = wp.min(phi * amplitude, cap)


@wp.kernel
def scale_ellipsoids(offset: int, kernel_g: wp.array(dtype=wp.mat33), extents: wp.array(dtype=float), scale: float,
                     shapes: wp.array(dtype=wp.mat33), bounds: wp.array(dtype=float)):
    """The ellipsoids of the kernels (``surface.kernel_ellipsoids``) where the kernels lie: shape
    ``scale G`` and bounding radius ``extent / scale``, the host's float32 products and quotients."""
    i = wp.tid() + offset
    shapes[i] = kernel_g[i] * scale
    bounds[i] = extents[i] / scale


@wp.kernel
def splat_density(
    offset: int,
    centres: wp.array(dtype=wp.vec3),
    kernel_g: wp.array(dtype=wp.mat33),
    extents: wp.array(dtype=float),
    volume: float,
    lo: wp.vec3,
    cell: float,
    nx: int,
    ny: int,
    nz: int,
    density: wp.array(dtype=float),
):
    """Add V det(G) P(|G (x - c)|) of each particle to the grid nodes inside its ellipsoid.

    On the CPU each chunk of particles writes a private grid (the chunks are summed after), so no
    atomics race; on CUDA one launch adds atomically.
    """
    i = wp.tid() + offset
    c = centres[i]
    G = kernel_g[i]
    amp = volume * wp.determinant(G) * POLY6_NORM
    # the ellipsoid's axis-aligned half-widths, |row k of G^-1| (G is symmetric), padded by one cell
    # so that rounding cannot drop a node inside; they never exceed the bounding radius
    e = extents[i]
    M = wp.inverse(G)
    hx = wp.min(wp.length(wp.vec3(M[0, 0], M[0, 1], M[0, 2])) + cell, e)
    hy = wp.min(wp.length(wp.vec3(M[1, 0], M[1, 1], M[1, 2])) + cell, e)
    ax0 = wp.max(int(wp.ceil((c[0] - hx - lo[0]) / cell)), 0)
    ax1 = wp.min(int(wp.floor((c[0] + hx - lo[0]) / cell)), nx - 1)
    ay0 = wp.max(int(wp.ceil((c[1] - hy - lo[1]) / cell)), 0)
    ay1 = wp.min(int(wp.floor((c[1] + hy - lo[1]) / cell)), ny - 1)
    az0 = wp.max(int(wp.ceil((c[2] - e - lo[2]) / cell)), 0)
    az1 = wp.min(int(wp.floor((c[2] + e - lo[2]) / cell)), nz - 1)
    # along a column (ix, iy) q^2(iz) = |a + iz b|^2 is a quadratic in iz: visit only its chord
    # inside the ellipsoid, widened by a cell each way; the q^2 < 1 test below decides
    b = wp.vec3(G[0, 2], G[1, 2], G[2, 2]) * cell
    bb = wp.dot(b, b)
    for ix in range(ax0, ax1 + 1):
        for iy in range(ay0, ay1 + 1):
            a = G * (lo + wp.vec3(float(ix), float(iy), 0.0) * cell - c)
            ab = wp.dot(a, b)
            disc = ab * ab - bb * (wp.dot(a, a) - 1.001)  # a margin against rounding
            if disc < 0.0:
                continue
            root = wp.sqrt(disc)
            z0 = wp.max(int(wp.floor((-ab - root) / bb)) - 1, az0)
            z1 = wp.min(int(wp.ceil((-ab + root) / bb)) + 1, az1)
            for iz in range(z0, z1 + 1):
                p = lo + wp.vec3(float(ix), float(iy), float(iz)) * cell
                u = G * (p - c)
                q2 = wp.dot(u, u)
                if q2 < 1.0:
                    t = 1.0 - q2
                    density[(ix * ny + iy) * nz + iz] += amp * t * t * t


@wp.kernel
def grid_gradient(
    offset: int,
    grid: wp.array3d(dtype=float),
    nodes: wp.array(dtype=wp.vec3i),
    gradient_out: wp.array(dtype=wp.vec3),
):
    """``np.gradient``'s differences of a grid at a few nodes (unit spacing): central inside, one-sided
    on the grid's faces. The grid stays where it is (on a GPU: never copied to the host)."""
    k = wp.tid() + offset
    node = nodes[k]
    out = wp.vec3()
    for axis in range(3):
        lo = wp.vec3i(node)
        hi = wp.vec3i(node)
        lo[axis] = wp.max(node[axis] - 1, 0)
        hi[axis] = wp.min(node[axis] + 1, grid.shape[axis] - 1)
        d = grid[hi[0], hi[1], hi[2]] - grid[lo[0], lo[1], lo[2]]
        if hi[axis] - lo[axis] == 2:
            d = d / 2.0
        out[axis] = d
    gradient_out[k] = out


NO_TRIANGLE = wp.constant(2147483647)
"""A pixel no triangle covers, in ``raster_mesh``'s triangle buffer."""


@wp.func
def ray_triangle(a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3) -> wp.vec3:
    """(t, u, v) where the ray t d from the view origin meets triangle abc at a + u (b - a) + v (c - a)
    (Moller-Trumbore); t = 0 where it misses. The barycentric bounds give by 1e-4 so that a ray
    through an edge shared by two triangles cannot slip between them by rounding."""
    e1 = b - a
    e2 = c - a
    pv = wp.cross(d, e2)
    det = wp.dot(e1, pv)
    if wp.abs(det) < 1.0e-30:
        return wp.vec3(0.0, 0.0, 0.0)
    inv = 1.0 / det
    tv = -a
    u = wp.dot(tv, pv) * inv
    if u < -1.0e-4 or u > 1.0001:
        return wp.vec3(0.0, 0.0, 0.0)
    qv = wp.cross(tv, e1)
    v = wp.dot(d, qv) * inv
    if v < -1.0e-4 or u + v > 1.0001:
        return wp.vec3(0.0, 0.0, 0.0)
    t = wp.dot(e2, qv) * inv
    if t <= 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    return wp.vec3(t, u, v)


@wp.func
def clip_extend(p: wp.vec3, q: wp.vec3, near: float, box: wp.vec4, focal: float) -> wp.vec4:
    """Grow the pixel-space box (col min, col max, row min, row max, before the image centre is
    added) by vertex p if it lies in front of the near plane z = -near, and by the point where
    edge pq crosses that plane."""
    out = box
    if p[2] <= -near:
        x = focal * p[0] / -p[2]
        y = -focal * p[1] / -p[2]
        out = wp.vec4(wp.min(out[0], x), wp.max(out[1], x), wp.min(out[2], y), wp.max(out[3], y))
    if (p[2] + near) * (q[2] + near) < 0.0:
        s = (-near - p[2]) / (q[2] - p[2])
        m = p + (q - p) * s
        x = focal * m[0] / near
        y = -focal * m[1] / near
        out = wp.vec4(wp.min(out[0], x), wp.max(out[1], x), wp.min(out[2], y), wp.max(out[3], y))
    return out


@wp.kernel
def raster_mesh(
    offset: int,
    vertices: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=int),
    width: int,
    height: int,
    focal: float,
    near: float,
    nearest: wp.array(dtype=float),
    depth_out: wp.array(dtype=float),
    triangle_out: wp.array(dtype=int),
):
    """Ray-cast every pixel of a triangle's screen box against the triangle (view-space vertices).

    Two passes: ``triangle_out`` of length 0 keeps the nearest hit depth per pixel in
    ``depth_out``; otherwise each pixel keeps the lowest-numbered triangle whose hit lies at
    ``nearest``, the first pass's depth, so a tie goes the same way in any launch order. The box
    comes from the triangle clipped to the near plane, so a triangle crossing it costs no more."""
    f = wp.tid() + offset
    a = vertices[faces[3 * f + 0]]
    b = vertices[faces[3 * f + 1]]
    c = vertices[faces[3 * f + 2]]
    box = wp.vec4(1.0e30, -1.0e30, 1.0e30, -1.0e30)
    box = clip_extend(a, b, near, box, focal)
    box = clip_extend(b, c, near, box, focal)
    box = clip_extend(c, a, near, box, focal)
    if box[0] > box[1]:
        return  # wholly behind the near plane
    # pixel centres sit at whole numbers once the image centre is added: visit those inside the
    # box, widened by 0.01 px (far more than the ray test's slack)
    cx = float(width) * 0.5 - 0.5
    cy = float(height) * 0.5 - 0.5
    c0 = wp.max(int(wp.ceil(wp.max(box[0] + cx, -1.0) - 0.01)), 0)
    c1 = wp.min(int(wp.floor(wp.min(box[1] + cx, float(width)) + 0.01)), width - 1)
    r0 = wp.max(int(wp.ceil(wp.max(box[2] + cy, -1.0) - 0.01)), 0)
    r1 = wp.min(int(wp.floor(wp.min(box[3] + cy, float(height)) + 0.01)), height - 1)
    resolve = triangle_out.shape[0] > 0
    for row in range(r0, r1 + 1):
        for col in range(c0, c1 + 1):
            hit = ray_triangle(a, b, c, pixel_ray(col, row, width, height, focal))
            if hit[0] > 0.0:
                idx = row * width + col
                if resolve:
                    if hit[0] == nearest[idx]:
                        wp.atomic_min(triangle_out, idx, f)
                else:
                    wp.atomic_min(depth_out, idx, hit[0])


@wp.kernel
def raster_mesh_resolve(
    offset: int,
    vertices: wp.array(dtype=wp.vec3),
    vertex_normals: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=int),
    triangle: wp.array(dtype=int),
    width: int,
    height: int,
    focal: float,
    normal_out: wp.array(dtype=wp.vec3),
    depth_out: wp.array(dtype=float),
):
    """Each pixel's interpolated unit normal (view space) and view depth from its nearest triangle."""
    idx = wp.tid() + offset
    f = triangle[idx]
    if f == NO_TRIANGLE:
        normal_out[idx] = wp.vec3(0.0, 0.0, 0.0)
        depth_out[idx] = 0.0
        return
    row = idx // width
    col = idx - row * width
    i0 = faces[3 * f + 0]
    i1 = faces[3 * f + 1]
    i2 = faces[3 * f + 2]
    hit = ray_triangle(vertices[i0], vertices[i1], vertices[i2], pixel_ray(col, row, width, height, focal))
    n = vertex_normals[i0] * (1.0 - hit[1] - hit[2]) + vertex_normals[i1] * hit[1] + vertex_normals[i2] * hit[2]
    ln = wp.length(n)
    if ln > 1.0e-12:
        n = n / ln
    normal_out[idx] = n
    depth_out[idx] = hit[0]


@wp.func
def grid_kernel_sum(grid: wp.uint64, reach: float, base: int, centres: wp.array(dtype=wp.vec3),
                    kernel_g: wp.array(dtype=wp.mat33), extents: wp.array(dtype=float), x: wp.vec3,
                    gradient: int) -> wp.vec4:
    """``kernel_sum`` over the kernels of one hash grid (its points are kernels base, base + 1, ...).

    A kernel is nonzero only within its bounding radius e_j (|G_j r| >= |r| / e_j), so candidates
    further away are skipped before the matrix product. The 0.1% margin keeps every kernel with
    |G_j r| < 1."""
    phi = float(0.0)
    grad = wp.vec3(0.0, 0.0, 0.0)
    q = wp.hash_grid_query(grid, x, reach)
    k = int(0)
    while wp.hash_grid_query_next(q, k):
        j = base + k
        r = x - centres[j]
        e = extents[j]
        if wp.dot(r, r) >= e * e * 1.001:
            continue
        G = kernel_g[j]
        u = G * r
        q2 = wp.dot(u, u)
        if q2 < 1.0:
            t = 1.0 - q2
            det = wp.determinant(G)
            phi += det * t * t * t
            if gradient != 0:
                grad += (wp.transpose(G) * u) * (-6.0 * det * t * t)
    return wp.vec4(phi, grad[0], grad[1], grad[2])


@wp.func
def kernel_sum(narrow: wp.uint64, narrow_reach: float, wide: wp.uint64, wide_reach: float, wide_start: int,
               centres: wp.array(dtype=wp.vec3), kernel_g: wp.array(dtype=wp.mat33), extents: wp.array(dtype=float),
               x: wp.vec3, gradient: int) -> wp.vec4:
    """(sum_j det(G_j) P(|G_j r|), and with ``gradient`` its gradient) at x, r = x - c_j, P the
    poly6 profile (1 - q^2)^3 with grad det(G) P = -6 det(G) (1 - q^2)^2 G^T G r.

    The kernels come as ``KernelLookup`` sorts them: the narrow ones (0 .. wide_start - 1) in one
    hash grid queried with their largest bounding radius, the few wide ones in another queried with
    theirs (none when wide_reach < 0)."""
    s = grid_kernel_sum(narrow, narrow_reach, 0, centres, kernel_g, extents, x, gradient)
    if wide_reach >= 0.0:
        s += grid_kernel_sum(wide, wide_reach, wide_start, centres, kernel_g, extents, x, gradient)
    return s


@wp.func
def density_at(narrow: wp.uint64, narrow_reach: float, wide: wp.uint64, wide_reach: float, wide_start: int,
               centres: wp.array(dtype=wp.vec3), kernel_g: wp.array(dtype=wp.mat33), extents: wp.array(dtype=float),
               amplitude: float, x: wp.vec3) -> float:
    """phi(x) = sum_j V det(G_j) P(|G_j (x - c_j)|), with amplitude = V times the poly6 norm."""
    s = kernel_sum(narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents, x, 0)
    return s[0] * amplitude


@wp.func
def density_gradient_at(narrow: wp.uint64, narrow_reach: float, wide: wp.uint64, wide_reach: float, wide_start: int,
                        centres: wp.array(dtype=wp.vec3), kernel_g: wp.array(dtype=wp.mat33),
                        extents: wp.array(dtype=float), x: wp.vec3) -> wp.vec3:
    """The direction of grad phi at x (without the constant V times the poly6 norm)."""
    s = kernel_sum(narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents, x, 1)
    return wp.vec3(s[1], s[2], s[3])


@wp.kernel
def density_gradient_normals(
    offset: int,
    narrow: wp.uint64,
    narrow_reach: float,
    wide: wp.uint64,
    wide_reach: float,
    wide_start: int,
    centres: wp.array(dtype=wp.vec3),
    kernel_g: wp.array(dtype=wp.mat33),
    extents: wp.array(dtype=float),
    vertices: wp.array(dtype=wp.vec3),
    normals_out: wp.array(dtype=wp.vec3),
):
    """Outward unit normal -grad(phi)/|grad(phi)| of the anisotropic density at each vertex.

    Evaluated from the kernels themselves, not from grid differences, so thin ellipsoids do not
    alias into the normals (the grid only places the vertices).
    grad V det(G) (1 - |G r|^2)^3 = -6 V det(G) (1 - |G r|^2)^2 G^T G r, with r = x - c.
    """
    k = wp.tid() + offset
    grad = density_gradient_at(narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents,
                               vertices[k])
    ln = wp.length(grad)
    if ln > 0.0:
        normals_out[k] = -grad / ln
    else:
        normals_out[k] = wp.vec3(0.0, 0.0, 0.0)


@wp.kernel
def raymarch_density(
    offset: int,
    narrow: wp.uint64,
    narrow_reach: float,
    wide: wp.uint64,
    wide_reach: float,
    wide_start: int,
    centres: wp.array(dtype=wp.vec3),
    kernel_g: wp.array(dtype=wp.mat33),
    extents: wp.array(dtype=float),
    amplitude: float,
    iso: float,
    eye: wp.vec3,
    cam_to_world: wp.mat33,
    width: int,
    height: int,
    focal: float,
    t_start: wp.array(dtype=float),
    lo: wp.vec3,
    hi: wp.vec3,
    step: float,
    bisections: int,
    with_thickness: int,
    normal_out: wp.array(dtype=wp.vec3),
    depth_out: wp.array(dtype=float),
    thickness_out: wp.array(dtype=float),
):
    """March each pixel's ray through the density to its first crossing of the iso-level.

    The march starts where the ray enters the first kernel support (``t_start``, a view depth from
    splatting the supports; 0 = the ray meets none) and ends where it leaves the box [lo, hi] of
    all supports. A crossing found between two samples ``step`` apart is refined by bisection; the
    normal is -grad phi there (analytic, view space). With ``with_thickness`` the march goes on to
    the box's end and sums the length of the ray inside the surface.

    Starting later (two radii before the particle ellipsoids' splat, backing off where the density
    there was already above the iso-level) was 1.6-2.5x faster but missed front surfaces that lie
    further out than that on the SPlisHSPlasH frame (95th percentile of the angle to the mesh 51
    degrees instead of 5): the support entry is the only start that cannot skip a crossing."""
    idx = wp.tid() + offset
    normal_out[idx] = wp.vec3(0.0, 0.0, 0.0)
    depth_out[idx] = 0.0
    thickness_out[idx] = 0.0
    t0 = t_start[idx]
    if t0 <= 0.0:
        return
    row = idx // width
    col = idx - row * width
    ray_view = pixel_ray(col, row, width, height, focal)
    d = cam_to_world * ray_view  # |d| = |ray_view|: t stays the view depth
    # exit of the box of all supports (slab test)
    t_end = float(1.0e30)
    for axis in range(3):
        if d[axis] > 1.0e-12:
            t_end = wp.min(t_end, (hi[axis] - eye[axis]) / d[axis])
        elif d[axis] < -1.0e-12:
            t_end = wp.min(t_end, (lo[axis] - eye[axis]) / d[axis])
    t = t0
    inside = bool(False)
    t_hit = float(0.0)
    thick = float(0.0)
    while t < t_end:
        t_next = t + step
        phi = density_at(narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents, amplitude,
                         eye + d * t_next)
        now_inside = phi >= iso
        if now_inside != inside:
            # bisection for the crossing in (t, t_next]
            ta = t
            tb = t_next
            for _ in range(bisections):
                tm = 0.5 * (ta + tb)
                phi_m = density_at(narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents,
                                   amplitude, eye + d * tm)
                if (phi_m >= iso) == now_inside:
                    tb = tm
                else:
                    ta = tm
            crossing = 0.5 * (ta + tb)
            if now_inside:
                if t_hit == 0.0:
                    t_hit = crossing
                    if with_thickness == 0:
                        break
                thick -= crossing
            else:
                thick += crossing
            inside = now_inside
        t = t_next
    if t_hit == 0.0:
        return
    if inside:
        thick += t_end
    grad = density_gradient_at(narrow, narrow_reach, wide, wide_reach, wide_start, centres, kernel_g, extents,
                               eye + d * t_hit)
    n = wp.transpose(cam_to_world) * (-grad)
    ln = wp.length(n)
    if ln > 0.0:
        normal_out[idx] = n / ln
    depth_out[idx] = t_hit
    thickness_out[idx] = thick * wp.length(d)
