"""Deferred fluid shading (Warp): Fresnel-weighted environment reflection and refraction of the
background, Beer-Lambert absorption by thickness, a small diffuse term and Blinn-Phong or GGX
specular highlights from one directional light.

All vectors are in view space except the reflection lookup, which turns the reflected ray into
world space for the environment. Colours are linear RGB.
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
    d = wp.normalize(cam_to_world * ray)
    if use_env_map != 0:
        out[idx] = latlong(env, d)
    else:
        out[idx] = procedural_sky(d, sun_world)


@wp.kernel
def shade_fluid(
    offset: int,
    normals: wp.array(dtype=wp.vec3),
    depth: wp.array(dtype=float),
    thickness: wp.array(dtype=float),
    mask: wp.array(dtype=float),
    background: wp.array(dtype=wp.vec3),
    background_depth: wp.array(dtype=float),
    env: wp.array2d(dtype=wp.vec3),
    use_env_map: int,
    cam_to_world: wp.mat33,
    light_view: wp.vec3,
    sun_world: wp.vec3,
    width: int,
    height: int,
    focal: float,
    f0: float,
    absorb: wp.vec3,
    fluid_color: wp.vec3,
    diffuse_weight: float,
    light_intensity: float,
    alpha: float,
    use_ggx: int,
    refraction_px: float,
    beauty: wp.array(dtype=wp.vec4),
):
    """Composite the fluid over the background with a depth test; alpha = 1 where fluid shows."""
    idx = wp.tid() + offset
    bg = background[idx]
    d = depth[idx]
    t = thickness[idx]
    bd = background_depth[idx]
    if mask[idx] <= 0.0 or t <= 0.0 or d <= 0.0 or (bd > 0.0 and bd < d):
        beauty[idx] = wp.vec4(bg[0], bg[1], bg[2], 0.0)
        return
    row = idx // width
    col = idx - row * width
    p = wp.vec3((float(col) + 0.5 - float(width) * 0.5) / focal, -(float(row) + 0.5 - float(height) * 0.5) / focal,
                -1.0) * d
    v = -wp.normalize(p)
    n = normals[idx]
    ln = wp.length(n)
    if ln < 1.0e-6:
        n = v
    else:
        n = n / ln
    nv = wp.max(wp.dot(n, v), 0.0)
    fresnel = fresnel_schlick(nv, f0)
    r = n * (2.0 * wp.dot(n, v)) - v
    rw = wp.normalize(cam_to_world * r)
    reflected = wp.vec3(0.0, 0.0, 0.0)
    if use_env_map != 0:
        reflected = latlong(env, rw)
    else:
        reflected = procedural_sky(rw, sun_world)
    # refraction: look up the background displaced along the normal, more for thicker fluid
    refr = sample_bilinear(background, width, height, float(col) + 0.5 + n[0] * t * refraction_px,
                           float(row) + 0.5 - n[1] * t * refraction_px)
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
