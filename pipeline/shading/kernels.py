"""Deferred fluid shading (Warp): Fresnel-weighted environment reflection and refraction of the
background, Beer-Lambert absorption by thickness, a small diffuse term and Blinn-Phong or GGX
specular highlights from one directional light.

Refraction follows Snell's law: the view ray bends at the fluid surface and crosses the fluid's
thickness along the refracted direction; the background is looked up where that ray leaves the
fluid (the floor and walls a fluid rests on are seen through one interface). Normals that face
away from the camera or graze it, which screen-space normal estimates produce at silhouettes and
depth discontinuities, are bent towards the viewer before shading (otherwise Fresnel goes to 1 and
the pixel mirrors the ground: dark speckles).

Outputs are premultiplied: ``fluid`` is the fluid alone (RGB times coverage, A the coverage),
``beauty`` the fluid over the background, whose alpha is 1 (``background_alpha`` 1) or 0 (the
fluid over transparent black). All vectors are in view space except environment lookups, which
turn rays into world space. Colours are linear RGB.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

PI = 3.141592653589793


@wp.func
def fresnel_schlick(cos_theta: float, f0: float) -> float:
    """Schlick's approximation: F0 + (1 - F0)(1 - cos)^5."""
    m = wp.clamp(1.0 - cos_theta, 0.0, 1.0)
    m2 = m * m
    return f0 + (1.0 - f0) * m2 * m2 * m


@wp.func
def procedural_sky(d: wp.vec3, sun: wp.vec3) -> wp.vec3:
    """A daylight sky: blue zenith to pale horizon, dim ground, and a sun glow (world space, y up)."""
    up = d[1]
    if up < 0.0:
        t = wp.min(-up * 4.0, 1.0)
        return wp.vec3(0.30, 0.28, 0.25) * (1.0 - t) + wp.vec3(0.12, 0.11, 0.10) * t
    horizon = wp.vec3(0.85, 0.90, 0.95)
    zenith = wp.vec3(0.25, 0.45, 0.85)
    t = wp.sqrt(wp.min(up, 1.0))
    c = horizon * (1.0 - t) + zenith * t
    s = wp.max(wp.dot(d, sun), 0.0)
    s2 = s * s
    s8 = s2 * s2 * s2 * s2
    return c + wp.vec3(1.0, 0.9, 0.7) * (s8 * s8 * s8 * s8 * 20.0)


@wp.func
def latlong(env: wp.array2d(dtype=wp.vec3), d: wp.vec3) -> wp.vec3:
    """Bilinear lookup of a latitude-longitude map (row 0 = up) in world direction d."""
    h = env.shape[0]
    w = env.shape[1]
    u = (wp.atan2(d[0], -d[2]) / (2.0 * PI) + 0.5) * float(w) - 0.5
    v = wp.acos(wp.clamp(d[1], -1.0, 1.0)) / PI * float(h) - 0.5
    x0 = int(wp.floor(u))
    y0 = int(wp.floor(v))
    fx = u - float(x0)
    fy = v - float(y0)
    xa = (x0 % w + w) % w
    xb = (xa + 1) % w
    ya = wp.clamp(y0, 0, h - 1)
    yb = wp.clamp(y0 + 1, 0, h - 1)
    top = env[ya, xa] * (1.0 - fx) + env[ya, xb] * fx
    bottom = env[yb, xa] * (1.0 - fx) + env[yb, xb] * fx
    return top * (1.0 - fy) + bottom * fy


@wp.func
def environment(env: wp.array2d(dtype=wp.vec3), use_env_map: int, d: wp.vec3, sun: wp.vec3, rotation: wp.vec2,
                strength: float) -> wp.vec3:
    """Radiance from world direction d: the lat-long map turned by ``rotation`` (cos, sin of the
    angle about +Y) or the procedural sky, times ``strength``."""
    if use_env_map != 0:
        # the map turned by +angle shows at d what the unturned map shows at d turned by -angle
        c = rotation[0]
        s = rotation[1]
        return latlong(env, wp.vec3(c * d[0] - s * d[2], d[1], s * d[0] + c * d[2])) * strength
    return procedural_sky(d, sun) * strength


@wp.func
def sample_bilinear(img: wp.array(dtype=wp.vec3), width: int, height: int, x: float, y: float) -> wp.vec3:
    """Clamped bilinear lookup of a row-major image at pixel coordinates (centres at +0.5)."""
    u = wp.clamp(x - 0.5, 0.0, float(width - 1))
    v = wp.clamp(y - 0.5, 0.0, float(height - 1))
    x0 = int(wp.floor(u))
    y0 = int(wp.floor(v))
    x1 = wp.min(x0 + 1, width - 1)
    y1 = wp.min(y0 + 1, height - 1)
    fx = u - float(x0)
    fy = v - float(y0)
    top = img[y0 * width + x0] * (1.0 - fx) + img[y0 * width + x1] * fx
    bottom = img[y1 * width + x0] * (1.0 - fx) + img[y1 * width + x1] * fx
    return top * (1.0 - fy) + bottom * fy


@wp.func
def specular_ggx(n: wp.vec3, v: wp.vec3, l: wp.vec3, alpha: float, f0: float) -> float:
    """Cook-Torrance with GGX distribution, Smith-Schlick visibility and Schlick Fresnel, times N.L."""
    nl = wp.dot(n, l)
    nv = wp.dot(n, v)
    if nl <= 0.0 or nv <= 0.0:
        return 0.0
    h = wp.normalize(l + v)
    nh = wp.max(wp.dot(n, h), 0.0)
    a2 = alpha * alpha
    den = nh * nh * (a2 - 1.0) + 1.0
    d = a2 / (PI * den * den)
    k = alpha * 0.5
    g = (nl / (nl * (1.0 - k) + k)) * (nv / (nv * (1.0 - k) + k))
    f = fresnel_schlick(wp.max(wp.dot(v, h), 0.0), f0)
    return d * g * f / (4.0 * nl * nv) * nl


@wp.func
def specular_blinn(n: wp.vec3, v: wp.vec3, l: wp.vec3, alpha: float, f0: float) -> float:
    """Normalised Blinn-Phong, exponent 2 / alpha^2 - 2, with Schlick Fresnel, times N.L."""
    nl = wp.dot(n, l)
    if nl <= 0.0 or wp.dot(n, v) <= 0.0:
        return 0.0
    h = wp.normalize(l + v)
    s = 2.0 / (alpha * alpha) - 2.0
    nh = wp.max(wp.dot(n, h), 0.0)
    return (s + 8.0) / (8.0 * PI) * wp.pow(nh, s) * fresnel_schlick(wp.max(wp.dot(v, h), 0.0), f0) * nl


@wp.kernel
def fill_sky(
    offset: int,
    background: wp.array(dtype=wp.vec3),
    background_depth: wp.array(dtype=float),
    env: wp.array2d(dtype=wp.vec3),
    use_env_map: int,
    env_rotation: wp.vec2,
    env_strength: float,
    cam_to_world: wp.mat33,
    sun_world: wp.vec3,
    width: int,
    height: int,
    focal: float,
    out: wp.array(dtype=wp.vec3),
):
    """Where the rasteriser hit nothing, show the environment seen along the pixel's ray."""
    idx = wp.tid() + offset
    if background_depth[idx] > 0.0:
        out[idx] = background[idx]
        return
    row = idx // width
    col = idx - row * width
    ray = wp.vec3((float(col) + 0.5 - float(width) * 0.5) / focal, -(float(row) + 0.5 - float(height) * 0.5) / focal,
                  -1.0)
    out[idx] = environment(env, use_env_map, wp.normalize(cam_to_world * ray), sun_world, env_rotation, env_strength)


@wp.func
def face_viewer(n: wp.vec3, v: wp.vec3, min_facing: float) -> wp.vec3:
    """Unit n bent towards the unit view vector v until their cosine is about ``min_facing``
    (unchanged when it already is at least that); a zero n becomes v."""
    ln = wp.length(n)
    if ln < 1.0e-6:
        return v
    n = n / ln
    nv = wp.dot(n, v)
    if nv < min_facing:
        n = wp.normalize(n + v * (min_facing - nv))
    return n


@wp.kernel
def shade_fluid(
    offset: int,
    normals: wp.array(dtype=wp.vec3),
    depth: wp.array(dtype=float),
    thickness: wp.array(dtype=float),
    mask: wp.array(dtype=float),
    background: wp.array(dtype=wp.vec3),
    background_depth: wp.array(dtype=float),
    background_alpha: float,
    env: wp.array2d(dtype=wp.vec3),
    use_env_map: int,
    env_rotation: wp.vec2,
    env_strength: float,
    cam_to_world: wp.mat33,
    light_view: wp.vec3,
    sun_world: wp.vec3,
    width: int,
    height: int,
    focal: float,
    f0: float,
    eta: float,
    absorb: wp.vec3,
    fluid_color: wp.vec3,
    diffuse_weight: float,
    light_intensity: float,
    alpha: float,
    use_ggx: int,
    refraction_scale: float,
    min_facing: float,
    beauty: wp.array(dtype=wp.vec4),
    fluid: wp.array(dtype=wp.vec4),
    depth_out: wp.array(dtype=float),
    normals_view: wp.array(dtype=wp.vec3),
    normals_world: wp.array(dtype=wp.vec3),
):
    """Shade the fluid where it is visible (in the mask, in front of the background) and composite
    it over the background; also the depth of the nearest surface (+inf where there is none) and
    the shaded normals in view and world space (0 outside the fluid)."""
    idx = wp.tid() + offset
    bg = background[idx]
    d = depth[idx]
    t = thickness[idx]
    bd = background_depth[idx]
    if mask[idx] <= 0.0 or t <= 0.0 or d <= 0.0 or (bd > 0.0 and bd < d):
        beauty[idx] = wp.vec4(bg[0] * background_alpha, bg[1] * background_alpha, bg[2] * background_alpha,
                              background_alpha)
        fluid[idx] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        if bd > 0.0:
            depth_out[idx] = bd
        else:
            depth_out[idx] = wp.inf
        normals_view[idx] = wp.vec3(0.0, 0.0, 0.0)
        normals_world[idx] = wp.vec3(0.0, 0.0, 0.0)
        return
    row = idx // width
    col = idx - row * width
    ray = wp.vec3((float(col) + 0.5 - float(width) * 0.5) / focal, -(float(row) + 0.5 - float(height) * 0.5) / focal,
                  -1.0)
    v = -wp.normalize(ray)
    n = face_viewer(normals[idx], v, min_facing)
    nv = wp.dot(n, v)
    fresnel = fresnel_schlick(nv, f0)
    r = n * (2.0 * nv) - v
    reflected = environment(env, use_env_map, wp.normalize(cam_to_world * r), sun_world, env_rotation, env_strength)
    # Snell: the refracted ray crosses the thickness; look up the background where it leaves the
    # fluid, displaced from where the straight ray leaves it (projected at that depth)
    k = 1.0 - eta * eta * (1.0 - nv * nv)
    bent = -v * eta + n * (eta * nv - wp.sqrt(wp.max(k, 0.0)))
    shift = (bent / wp.max(-bent[2], 0.05) - ray) * t * refraction_scale
    exit_depth = d + t
    refr = sample_bilinear(background, width, height, float(col) + 0.5 + focal * shift[0] / exit_depth,
                           float(row) + 0.5 - focal * shift[1] / exit_depth)
    transmit = wp.vec3(wp.exp(-absorb[0] * t), wp.exp(-absorb[1] * t), wp.exp(-absorb[2] * t))
    refracted = wp.cw_mul(refr, transmit)
    spec = float(0.0)
    if use_ggx != 0:
        spec = specular_ggx(n, v, light_view, alpha, f0)
    else:
        spec = specular_blinn(n, v, light_view, alpha, f0)
    diffuse = fluid_color * (diffuse_weight * wp.max(wp.dot(n, light_view), 0.0) * light_intensity)
    c = reflected * fresnel + refracted * (1.0 - fresnel) + diffuse + wp.vec3(1.0, 1.0, 1.0) * (spec * light_intensity)
    beauty[idx] = wp.vec4(c[0], c[1], c[2], 1.0)
    fluid[idx] = wp.vec4(c[0], c[1], c[2], 1.0)
    depth_out[idx] = d
    normals_view[idx] = n
    normals_world[idx] = cam_to_world * n
