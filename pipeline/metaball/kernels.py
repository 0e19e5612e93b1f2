"""Warp kernels of the metaball system (Horvath, "Image-Space Metaballs Using Deep Learning",
master's thesis, TU Wien 2019, sections 4.1 and 5.2).

Field: f(X) = sum_i w_i(|X - P_i|) with w_i(d) = r_i^2 / d^2 (the thesis' equation 5.1), gradient
2 r_i^2 (P_i - X) / |P_i - X|^4 (equation 5.2). With a kernel radius R_i = k r_i (k > 0) each term is
multiplied by a smoothstep taper s(u) = 1 - u^2 (3 - 2u), u = (d - R_i / 2) / (R_i / 2), that is 1
inside R_i / 2 and falls to 0 at R_i with zero slope: the sum stays C1 (a hard cut would put a step
of r_i^2 / R_i^2 into the field, and spurious surfaces where it crosses the iso-level), and a hash
grid bounds it. k = 0 keeps the thesis' infinite support: every ball at every sample.

Targets: one ray per pixel, marched in view depth in steps between where it enters its first and
leaves its last ball support (a splat of the support spheres), the first iso crossing refined by
bisection; view depth, the view-space normal -grad f / |grad f|, and the colour
sum c_i w_i / sum w_i at the crossing.

Input (listing 5.1): per ball a camera-facing quad of half side the ball's projected minimal
radius, in which only the ring 0.45 < |uv - 0.5| < 0.5 is drawn, with a depth test on the depth of
the ball's centre (ties go to the lower index, as the first drawn wins under GL_LESS).

Per-pixel kernels take ``offset`` first and address pixel ``tid + offset`` of a row-major H x W
image; per-ball kernels draw into the rows [row0, row1) only, so row bands run on several threads.
"""

import warp as wp

from pipeline.screen.kernels import pixel_ray, ray_sphere, splat_bounds

wp.set_module_options({"enable_backward": False})

SAFE_STEP_CAP = wp.constant(0.25)
"""Longest empty-space step with a cut-off, a share of the largest support radius."""


@wp.func
def ball_weight(v: wp.vec3, r: float, cutoff: float) -> wp.vec4:
    """(w, grad w) of one ball at X, v = X - P: r^2 / d^2 tapered to 0 between cutoff / 2 and cutoff
    (cutoff 0: no taper); grad w = (dw/dd) v / d."""
    d2 = wp.max(wp.dot(v, v), 1.0e-12)
    d = wp.sqrt(d2)
    if cutoff > 0.0 and d >= cutoff:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    s = float(1.0)
    ds = float(0.0)
    half = 0.5 * cutoff
    if cutoff > 0.0 and d > half:
        u = (d - half) / half
        s = 1.0 - u * u * (3.0 - 2.0 * u)
        ds = -6.0 * u * (1.0 - u) / half
    w = r * r / d2
    # d/dd (w s) = w (s' - 2 s / d)
    g = v * (w * (ds - 2.0 * s / d) / d)
    return wp.vec4(w * s, g[0], g[1], g[2])


@wp.func
def ball_term(v: wp.vec3, j: int, radii: wp.array(dtype=float), shapes: wp.array(dtype=wp.mat33),
              cutoff_radii: float) -> wp.vec4:
    """(w, grad w) of ball j at X, v = X - P_j: the sphere's r_j^2 / d^2, or with ``shapes`` (one per
    ball; empty for spheres) the ellipsoid's 1 / |A_j v|^2 (A_j maps the ball onto the unit ball),
    cut off at ``cutoff_radii`` in the ball's own units either way."""
    if shapes.shape[0] == 0:
        return ball_weight(v, radii[j], cutoff_radii * radii[j])
    reach = cutoff_radii * radii[j]  # radii bound the ellipsoids: no term past this, skip the product
    if cutoff_radii > 0.0 and wp.dot(v, v) >= reach * reach:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    a = shapes[j]
    t = ball_weight(a * v, 1.0, cutoff_radii)
    g = wp.transpose(a) * wp.vec3(t[1], t[2], t[3])
    return wp.vec4(t[0], g[0], g[1], g[2])


@wp.func
def grid_field(grid: wp.uint64, reach: float, first: int, centres: wp.array(dtype=wp.vec3),
               radii: wp.array(dtype=float), shapes: wp.array(dtype=wp.mat33), cutoff_radii: float,
               x: wp.vec3) -> wp.vec4:
    """(f, grad f) at x of the balls within ``reach`` in ``grid``, whose point j is ball first + j."""
    total = wp.vec4(0.0, 0.0, 0.0, 0.0)
    q = wp.hash_grid_query(grid, x, reach)
    j = int(0)
    while wp.hash_grid_query_next(q, j):
        total += ball_term(x - centres[first + j], first + j, radii, shapes, cutoff_radii)
    return total


@wp.func
def split_field(narrow: wp.uint64, narrow_reach: float, wide: wp.uint64, wide_reach: float, wide_start: int,
                centres: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float), shapes: wp.array(dtype=wp.mat33),
                cutoff_radii: float, x: wp.vec3) -> wp.vec4:
    """(f, grad f) at x of balls sorted narrow first: those before ``wide_start`` in ``narrow``, the
    rest in ``wide`` (none when ``wide_reach`` <= 0), each grid queried with its own reach."""
    total = grid_field(narrow, narrow_reach, 0, centres, radii, shapes, cutoff_radii, x)
    if wide_reach > 0.0:
        total += grid_field(wide, wide_reach, wide_start, centres, radii, shapes, cutoff_radii, x)
    return total


@wp.func
def field_at(grid: wp.uint64, centres: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float),
             shapes: wp.array(dtype=wp.mat33), cutoff_radii: float, reach: float, x: wp.vec3) -> wp.vec4:
    """(f, grad f) at x: the balls within ``reach`` from the hash grid, or all of them when
    ``cutoff_radii`` is 0 (infinite support)."""
    total = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if cutoff_radii > 0.0:
        total = grid_field(grid, reach, 0, centres, radii, shapes, cutoff_radii, x)
    else:
        for j in range(centres.shape[0]):
            total += ball_term(x - centres[j], j, radii, shapes, 0.0)
    return total


@wp.func
def field_and_safe_step(grid: wp.uint64, centres: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float),
                        shapes: wp.array(dtype=wp.mat33), cutoff_radii: float, reach: float, iso: float,
                        x: wp.vec3) -> wp.vec2:
    """(f, rho) at x: the field, and a distance rho within which it stays below ``iso`` (0 when f is
    at or above it), for empty-space skipping.

    Every term obeys w_i(Y) <= r_i^2 / (d_i - rho)^2 within rho of x (d_i = |x - P_i|, taper <= 1), and
    d_i / (d_i - rho) <= 1 / (1 - beta) once rho <= beta d_min; so with S = sum r_i^2 / d_i^2 over the
    balls that can reach that far, the field stays below S / (1 - beta)^2, which is iso for
    beta = 1 - sqrt(S / iso). With a cut-off rho is capped at ``SAFE_STEP_CAP`` x ``reach`` (the largest
    support), and the balls that can reach are those with d_i < R_i + that cap, all inside the query
    radius (1 + cap) reach (a larger cap allows longer steps but makes every query dearer). With
    ``shapes`` the radii are the ellipsoids' largest semi-axes, which bound their terms the same way."""
    f = float(0.0)
    bound = float(0.0)
    d_min = float(1.0e30)
    if cutoff_radii > 0.0:
        cap = SAFE_STEP_CAP * reach
        q = wp.hash_grid_query(grid, x, reach + cap)
        j = int(0)
        while wp.hash_grid_query_next(q, j):
            v = x - centres[j]
            r = radii[j]
            d = wp.length(v)
            if d < cutoff_radii * r + cap:
                f += ball_term(v, j, radii, shapes, cutoff_radii)[0]
                bound += r * r / wp.max(d * d, 1.0e-12)
                d_min = wp.min(d_min, d)
    else:
        for j in range(centres.shape[0]):
            v = x - centres[j]
            r = radii[j]
            d = wp.length(v)
            f += ball_term(v, j, radii, shapes, 0.0)[0]
            bound += r * r / wp.max(d * d, 1.0e-12)
            d_min = wp.min(d_min, d)
    if f >= iso or bound >= iso:
        return wp.vec2(f, 0.0)
    rho = (1.0 - wp.sqrt(bound / iso)) * d_min
    if cutoff_radii > 0.0:
        rho = wp.min(rho, SAFE_STEP_CAP * reach)
    return wp.vec2(f, rho)


@wp.func
def colour_at(grid: wp.uint64, centres: wp.array(dtype=wp.vec3), radii: wp.array(dtype=float),
              shapes: wp.array(dtype=wp.mat33), colours: wp.array(dtype=wp.vec3), cutoff_radii: float, reach: float,
              x: wp.vec3) -> wp.vec3:
    """Field-weighted blend sum c_i w_i / sum w_i of the ball colours at x."""
    c = wp.vec3(0.0, 0.0, 0.0)
    total = float(0.0)
    if cutoff_radii > 0.0:
        q = wp.hash_grid_query(grid, x, reach)
        j = int(0)
        while wp.hash_grid_query_next(q, j):
            w = ball_term(x - centres[j], j, radii, shapes, cutoff_radii)[0]
            c += colours[j] * w
            total += w
    else:
        for j in range(centres.shape[0]):
            w = ball_term(x - centres[j], j, radii, shapes, 0.0)[0]
            c += colours[j] * w
            total += w
    if total > 0.0:
        c = c / total
    return c


@wp.kernel
def splat_supports(
    offset: int,
    centres_view: wp.array(dtype=wp.vec3),
    supports: wp.array(dtype=float),
    focal: float,
    width: int,
    height: int,
    row0: int,
    row1: int,
    t_in: wp.array(dtype=float),
    t_out: wp.array(dtype=float),
):
    """View depths at which each pixel's ray enters its first and leaves its last support sphere
    (radius ``supports``) of a ball: an exact ray-sphere splat into the rows [row0, row1), the min of
    the entries and the max of the exits over the balls."""
    i = wp.tid() + offset
    c = centres_view[i]
    rad = supports[i]
    box = splat_bounds(c, rad, focal, width, height, row0, row1)
    r2 = rad * rad
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            hit = ray_sphere(pixel_ray(px, py, width, height, focal), c, r2)
            if hit[2] >= 0.0:
                wp.atomic_min(t_in, py * width + px, hit[0])
                wp.atomic_max(t_out, py * width + px, hit[1])


@wp.kernel
def splat_behind_and_normals(
    offset: int,
    centres_view: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    focal: float,
    width: int,
    height: int,
    row0: int,
    row1: int,
    gap: float,
    t_front: wp.array(dtype=float),
    t_behind: wp.array(dtype=float),
    normals: wp.array(dtype=wp.vec3),
):
    """The second pass of a sphere splat over its first entries ``t_front``, rows [row0, row1): per
    pixel the nearest entry into a sphere more than ``gap`` behind ``t_front`` (a ball behind the
    front one, not its neighbour in the same layer), and the unit view-space normal of the sphere
    entered first (the one whose entry equals ``t_front`` to the bit: it is computed alike)."""
    i = wp.tid() + offset
    c = centres_view[i]
    rad = radii[i]
    box = splat_bounds(c, rad, focal, width, height, row0, row1)
    r2 = rad * rad
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            ray = pixel_ray(px, py, width, height, focal)
            hit = ray_sphere(ray, c, r2)
            idx = py * width + px
            if hit[2] >= 0.0:
                if hit[0] == t_front[idx]:
                    normals[idx] = (ray * hit[0] - c) / rad
                elif hit[0] > t_front[idx] + gap:
                    wp.atomic_min(t_behind, idx, hit[0])


@wp.kernel
def field_normals(
    offset: int,
    narrow: wp.uint64,
    narrow_reach: float,
    wide: wp.uint64,
    wide_reach: float,
    wide_start: int,
    centres_view: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    shapes: wp.array(dtype=wp.mat33),
    cutoff_radii: float,
    iso: float,
    width: int,
    height: int,
    focal: float,
    t_front: wp.array(dtype=float),
    steps: int,
    max_step: float,
    normals: wp.array(dtype=wp.vec3),
):
    """The field's normal -grad f / |grad f| where each pixel's ray enters its front sphere
    (``t_front``, view depth; pixels without one are left alone), after ``steps`` Newton steps
    t += (iso - f) / (df/dt) along the ray towards the iso-surface, each at most ``max_step``: a
    sphere splat a little larger than the balls starts next to the blended surface, so one field
    sample there already gives its orientation, which a sphere's own normal cannot. The balls come
    narrow first (``split_field``)."""
    idx = wp.tid() + offset
    t = t_front[idx]
    if t <= 0.0 or t >= 1.0e29:
        return
    row = idx // width
    col = idx - row * width
    d = pixel_ray(col, row, width, height, focal)  # view z = -1: t is the view depth
    g = split_field(narrow, narrow_reach, wide, wide_reach, wide_start, centres_view, radii, shapes, cutoff_radii,
                    d * t)
    for _ in range(steps):
        slope = g[1] * d[0] + g[2] * d[1] + g[3] * d[2]
        if wp.abs(slope) > 1.0e-12:
            t = t + wp.clamp((iso - g[0]) / slope, -max_step, max_step)
            g = split_field(narrow, narrow_reach, wide, wide_reach, wide_start, centres_view, radii, shapes,
                            cutoff_radii, d * t)
    n = wp.vec3(-g[1], -g[2], -g[3])
    ln = wp.length(n)
    if ln > 0.0:
        normals[idx] = n / ln


@wp.kernel
def march_metaballs(
    offset: int,
    grid: wp.uint64,
    centres: wp.array(dtype=wp.vec3),
    radii: wp.array(dtype=float),
    shapes: wp.array(dtype=wp.mat33),
    colours: wp.array(dtype=wp.vec3),
    cutoff_radii: float,
    reach: float,
    iso: float,
    eye: wp.vec3,
    cam_to_world: wp.mat33,
    width: int,
    height: int,
    focal: float,
    t_entry: wp.array(dtype=float),
    t_exit: wp.array(dtype=float),
    t_near: float,
    t_far: float,
    step: float,
    adaptive: int,
    bisections: int,
    depth_out: wp.array(dtype=float),
    normal_out: wp.array(dtype=wp.vec3),
    colour_out: wp.array(dtype=wp.vec3),
    mask_out: wp.array(dtype=float),
):
    """March each pixel's ray to its first crossing of f = iso; write view depth, view normal,
    blended colour and mask (all 0 where the ray meets no surface).

    The ray runs in view depth t from max(t_entry, t_near) to min(t_exit, t_far), where it enters
    its first and leaves its last ball support, sampling every ``step`` or, with ``adaptive``, every
    max(step, rho) where rho is the distance within which the field provably stays below the
    iso-level (``field_and_safe_step``: empty space is crossed in a few samples, not one per step); a
    crossing between two samples is halved ``bisections`` times and placed mid-interval. A ray that
    starts inside the surface (cut by the near plane) hits at its start."""
    idx = wp.tid() + offset
    depth_out[idx] = 0.0
    normal_out[idx] = wp.vec3(0.0, 0.0, 0.0)
    colour_out[idx] = wp.vec3(0.0, 0.0, 0.0)
    mask_out[idx] = 0.0
    t = wp.max(t_entry[idx], t_near)
    t_end = wp.min(t_exit[idx], t_far)
    if t >= t_end:
        return
    row = idx // width
    col = idx - row * width
    d = cam_to_world * pixel_ray(col, row, width, height, focal)  # view z = -1: t is the view depth
    t_hit = float(-1.0)
    inv_len = 1.0 / wp.length(d)  # a step of dt in view depth moves the sample dt |d|
    sample = field_and_safe_step(grid, centres, radii, shapes, cutoff_radii, reach, iso, eye + d * t)
    if sample[0] >= iso:
        t_hit = t
    while t_hit < 0.0 and t < t_end:
        advance = step
        if adaptive != 0:
            advance = wp.max(step, sample[1] * inv_len)
        t_next = wp.min(t + advance, t_end)
        sample = field_and_safe_step(grid, centres, radii, shapes, cutoff_radii, reach, iso, eye + d * t_next)
        if sample[0] >= iso:
            ta = t
            tb = t_next
            for _ in range(bisections):
                tm = 0.5 * (ta + tb)
                if field_at(grid, centres, radii, shapes, cutoff_radii, reach, eye + d * tm)[0] >= iso:
                    tb = tm
                else:
                    ta = tm
            t_hit = 0.5 * (ta + tb)
        t = t_next
    if t_hit < 0.0:
        return
    x = eye + d * t_hit
    grad = field_at(grid, centres, radii, shapes, cutoff_radii, reach, x)
    n = wp.transpose(cam_to_world) * wp.vec3(-grad[1], -grad[2], -grad[3])
    ln = wp.length(n)
    if ln > 0.0:
        n = n / ln
    depth_out[idx] = t_hit
    normal_out[idx] = n
    colour_out[idx] = colour_at(grid, centres, radii, shapes, colours, cutoff_radii, reach, x)
    mask_out[idx] = 1.0


@wp.func
def on_outline(px: int, py: int, cx: float, cy: float, outer: float, inner: float) -> bool:
    """Whether the centre of pixel (px, py) lies strictly inside the ring inner < rho < outer around
    (cx, cy) (pixels)."""
    dx = float(px) + 0.5 - cx
    dy = float(py) + 0.5 - cy
    rho = wp.sqrt(dx * dx + dy * dy)
    return rho > inner and rho < outer


@wp.func
def outline_box(cx: float, cy: float, outer: float, width: int, row0: int, row1: int) -> wp.vec4i:
    """Pixel box (x0, x1, y0, y1) of a ring of outer radius ``outer`` around (cx, cy), rows clipped to
    [row0, row1); empty (x1 < x0) off the band."""
    return wp.vec4i(wp.max(int(wp.floor(cx - outer)), 0), wp.min(int(wp.ceil(cx + outer)), width - 1),
                    wp.max(int(wp.floor(cy - outer)), row0), wp.min(int(wp.ceil(cy + outer)), row1 - 1))


@wp.kernel
def draw_outlines(
    offset: int,
    circles: wp.array(dtype=wp.vec4),
    centre_depth: wp.array(dtype=float),
    width: int,
    row0: int,
    row1: int,
    owner_pass: int,
    depth: wp.array(dtype=float),
    owner: wp.array(dtype=int),
):
    """Rasterise each ball's ring (``circles``: centre column, centre row, outer and inner radius in
    pixels) into the rows [row0, row1) with a depth test on the centre's view depth.

    Pass 0 keeps the nearest depth per pixel; pass 1 marks the lowest index among the balls at that
    depth as the pixel's owner (ties resolved as the first drawn wins)."""
    i = wp.tid() + offset
    c = circles[i]
    z = centre_depth[i]
    if c[2] <= 0.0:
        return
    box = outline_box(c[0], c[1], c[2], width, row0, row1)
    for py in range(box[2], box[3] + 1):
        for px in range(box[0], box[1] + 1):
            if on_outline(px, py, c[0], c[1], c[2], c[3]):
                idx = py * width + px
                if owner_pass == 0:
                    wp.atomic_min(depth, idx, z)
                elif depth[idx] == z:
                    wp.atomic_min(owner, idx, i)


@wp.kernel
def finish_outlines(
    offset: int,
    owner: wp.array(dtype=int),
    colours: wp.array(dtype=wp.vec3),
    depth_code: wp.array(dtype=float),
    count: int,
    plane: int,
    image: wp.array(dtype=float),
):
    """Write the owner's colour and centre depth code into the 4 x H x W image (planes ``plane``
    apart); pixels without an owner stay 0 (the cleared background)."""
    idx = wp.tid() + offset
    k = owner[idx]
    if k >= count:
        for ch in range(4):
            image[ch * plane + idx] = 0.0
        return
    c = colours[k]
    image[idx] = c[0]
    image[plane + idx] = c[1]
    image[2 * plane + idx] = c[2]
    image[3 * plane + idx] = depth_code[k]
