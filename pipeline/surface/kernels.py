"""Warp kernels of the anisotropic-kernel surface (Yu & Turk, "Reconstructing Surfaces of
Particle-Based Fluids Using Anisotropic Kernels", TOG 2013) and of the mesh ray caster.

Per particle: a weighted mean and covariance of the neighbours within 2h (weights
w = 1 - (d / 2h)^3), Laplacian-smoothed centres, an eigen-decomposition with eigenvalue clamping
(k_r, k_s, k_n, N_eps) giving the kernel matrix G = (1/h) R S^-1 R^T, then the density
phi(x) = sum_j V_j det(G_j) P(|G_j (x - c_j)|) splatted on a grid, P the normalised poly6 profile.
"""

import warp as wp

from pipeline.sph import POLY6_NORM

wp.set_module_options({"enable_backward": False})


@wp.kernel
def compute_anisotropy(
    offset: int,
    grid: wp.uint64,
    particle_x: wp.array(dtype=wp.vec3),
    support: float,
    kernel_radius: float,
    smoothing: float,
    kr: float,
    ks_scale: float,
    kn: float,
    n_eps: int,
    centre_out: wp.array(dtype=wp.vec3),
    g_out: wp.array(dtype=wp.mat33),
    extent_out: wp.array(dtype=float),
):
    """Smoothed centre, kernel matrix G and bounding radius of each particle's ellipsoid.

    ``ks_scale`` maps covariance eigenvalues to kernel scales so that a full neighbourhood gives
    1 (Yu & Turk's k_s = 1400 does this in their units).
    """
    k = wp.tid() + offset
    i = wp.hash_grid_point_id(grid, k)
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
    mean_r = wr / wsum
    centre_out[i] = xi + mean_r * smoothing
    if count - 1 < n_eps:
        s = kn * kernel_radius
        g_out[i] = wp.identity(3, dtype=float) * (1.0 / s)
        extent_out[i] = s
        return
    cov = wrr / wsum - wp.outer(mean_r, mean_r)
    Q = wp.mat33()
    e = wp.vec3()
    wp.eig3(cov, Q, e)
    top = wp.max(e[0], wp.max(e[1], e[2]))
    floor = top / kr
    s0 = ks_scale * wp.max(e[0], floor)
    s1 = ks_scale * wp.max(e[1], floor)
    s2 = ks_scale * wp.max(e[2], floor)
    inv = wp.mat33(1.0 / s0, 0.0, 0.0, 0.0, 1.0 / s1, 0.0, 0.0, 0.0, 1.0 / s2)
    g_out[i] = Q * inv * wp.transpose(Q) * (1.0 / kernel_radius)
    extent_out[i] = kernel_radius * wp.max(s0, wp.max(s1, s2))


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

    Each chunk of particles writes a private grid (summed on the host), so no atomics race.
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
def raycast_mesh(
    offset: int,
    mesh: wp.uint64,
    vertex_normals: wp.array(dtype=wp.vec3),
    faces: wp.array(dtype=int),
    eye: wp.vec3,
    cam_to_world: wp.mat33,
    width: int,
    height: int,
    focal: float,
    max_t: float,
    normal_out: wp.array(dtype=wp.vec3),
    depth_out: wp.array(dtype=float),
):
    """Cast one ray per pixel; write the interpolated view-space normal and the view depth."""
    idx = wp.tid() + offset
    row = idx // width
    col = idx - row * width
    ray_view = wp.vec3((float(col) + 0.5 - float(width) * 0.5) / focal,
                       -(float(row) + 0.5 - float(height) * 0.5) / focal, -1.0)
    dir_world = cam_to_world * ray_view
    length = wp.length(dir_world)
    q = wp.mesh_query_ray(mesh, eye, dir_world / length, max_t)
    if not q.result:
        normal_out[idx] = wp.vec3(0.0, 0.0, 0.0)
        depth_out[idx] = 0.0
        return
    f = q.face
    n0 = vertex_normals[faces[3 * f + 0]]
    n1 = vertex_normals[faces[3 * f + 1]]
    n2 = vertex_normals[faces[3 * f + 2]]
    n = n0 * q.u + n1 * q.v + n2 * (1.0 - q.u - q.v)
    # world to view is the transpose of the camera rotation
    nv = wp.transpose(cam_to_world) * n
    ln = wp.length(nv)
    if ln > 1.0e-12:
        nv = nv / ln
    normal_out[idx] = nv
    # the view-space ray has z = -1, so the view depth is the hit distance over its length
    depth_out[idx] = q.t / length


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
    ray_view = wp.vec3((float(col) + 0.5 - float(width) * 0.5) / focal,
                       -(float(row) + 0.5 - float(height) * 0.5) / focal, -1.0)
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
