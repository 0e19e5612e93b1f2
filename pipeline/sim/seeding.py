"""Initial particle placement and emitter schedules (NumPy, host side)."""

from __future__ import annotations

import math

import numpy as np

from pipeline.config import Emitter, SceneConfig
from pipeline.sph import lattice_offsets, poly6, spacing


def lattice_rest_sum(step: float, h: float) -> float:
    """Sum of poly6 over an interior particle's neighbours on a cubic lattice (self included).

    Dividing the rest density by this gives the particle mass that makes the initial lattice sit
    exactly at rest density.
    """
    r2 = np.sum(lattice_offsets(step, h) ** 2, axis=1)
    return float(poly6(r2, h).sum())


def wall_density_table(step: float, h: float, samples: int = 65) -> np.ndarray:
    """Poly6 density per unit mass of fluid at rest behind a wall, and its derivative, vs distance.

    Row k is for a particle at distance d_k = k h / (samples - 1) from the wall plane; the virtual
    fluid is a lattice (spacing 2r) whose first layer sits r behind the plane, mirroring the
    particles resting at r in front of it, so a resting first layer sees full rest density.
    """
    k = int(math.ceil(h / step)) + 1
    lateral = np.arange(-k, k + 1) * step
    layers = -0.5 * step - np.arange(0, k + 1) * step
    gx, gy, gz = np.meshgrid(lateral, lateral, layers, indexing="ij")
    d = np.linspace(0.0, h, samples)
    rho = np.empty(samples)
    for i, di in enumerate(d):
        rho[i] = np.sum(poly6(gx**2 + gy**2 + (di - gz) ** 2, h))
    grad = np.gradient(rho, d)
    rho[-1], grad[-1] = 0.0, 0.0
    return np.stack([rho, grad], axis=1).astype(np.float32)


def _lattice_in_box(lo, hi, step: float) -> np.ndarray:
    axes = [np.arange(lo[a] + 0.5 * step, hi[a] - 0.25 * step, step) for a in range(3)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([c.ravel() for c in g], axis=1)


# More initial particles than this is taken for a unit mistake (a radius in mm given as m, 1e-9):
# 20 million particles already need several GB and hours a frame here.
MAX_INITIAL_PARTICLES = 20_000_000


def initial_particle_estimate(scene: SceneConfig, radius: float) -> float:
    """Upper estimate of the particles ``seed_fluid`` would place (before building any lattice)."""
    total = 0.0
    for shape in scene.fluid:
        if shape.shape == "box":
            extent = np.maximum(np.asarray(shape.hi, float) - np.asarray(shape.lo, float), 0.0)
            total += float(np.prod(extent / spacing(radius) + 1.0))
        else:
            total += float((shape.radius / radius + 1.0) ** 3)
    return total


def seed_fluid(scene: SceneConfig, radius: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Particles filling the scene's fluid shapes on a lattice of spacing 2r.

    A tiny seeded jitter (1% of r) breaks the lattice symmetry; shapes are clipped to the
    container and overlapping shapes do not double-fill.
    """
    estimate = initial_particle_estimate(scene, radius)
    if estimate > MAX_INITIAL_PARTICLES:
        volume_share = (estimate / MAX_INITIAL_PARTICLES) ** (1 / 3)
        raise ValueError(f"simulate.particle_radius {radius:g} would fill the fluid of scene {scene.name!r} with about "
                         f"{estimate:.2g} particles (the limit is {MAX_INITIAL_PARTICLES:,}); use a radius of at "
                         f"least {radius * volume_share:.3g} in the scene's units")
    step = spacing(radius)
    dlo = np.asarray(scene.domain_lo, float) + radius
    dhi = np.asarray(scene.domain_hi, float) - radius
    xs, vs = [], []
    taken = np.zeros((0, 3))
    for shape in scene.fluid:
        if shape.shape == "box":
            pts = _lattice_in_box(shape.lo, shape.hi, step)
        else:
            c, R = np.asarray(shape.center, float), shape.radius
            pts = _lattice_in_box(c - R, c + R, step)
            pts = pts[np.linalg.norm(pts - c, axis=1) <= R]
        pts = pts[np.all((pts >= dlo) & (pts <= dhi), axis=1)]
        if len(taken) and len(pts):
            # drop points that fall inside an earlier shape's particles
            from scipy.spatial import cKDTree

            d, _ = cKDTree(taken).query(pts, k=1)
            pts = pts[d > 0.75 * step]
        xs.append(pts)
        vs.append(np.tile(np.asarray(shape.velocity, float), (len(pts), 1)))
        taken = np.concatenate([taken, pts]) if len(pts) else taken
    if not xs:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    x = np.concatenate(xs)
    x = x + rng.uniform(-0.01 * radius, 0.01 * radius, size=x.shape)
    return x.astype(np.float32), np.concatenate(vs).astype(np.float32)


def _disc(radius_nozzle: float, step: float) -> np.ndarray:
    """Lattice points of a disc in its own (u, v) plane."""
    k = int(math.floor(radius_nozzle / step))
    ax = np.arange(-k, k + 1) * step
    u, v = np.meshgrid(ax, ax, indexing="ij")
    keep = u**2 + v**2 <= radius_nozzle**2 + 1e-12
    return np.stack([u[keep], v[keep]], axis=1)


def _basis(direction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    helper = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    return d, u, np.cross(d, u)


class EmitterSchedule:
    """Which particles each emitter injects at each solver step.

    An emitter releases a disc of particles every 2r / speed seconds while open. Layer L is due at
    time start + L * interval; it is placed at the step that crosses that time, advanced along the
    jet by the time remaining in the step, so layers stay exactly 2r apart. Everything depends only
    on the step index: resuming from a frame reproduces the same emission.
    """

    def __init__(self, emitters: tuple[Emitter, ...], radius: float, dt: float):
        self.dt = dt
        self.items = []
        for e in emitters:
            d, u, v = _basis(e.direction)
            disc = _disc(e.radius, spacing(radius))
            layer = np.asarray(e.position, float) + disc[:, :1] * u + disc[:, 1:] * v
            self.items.append((e, d, layer, spacing(radius) / e.speed))

    def _layers_due(self, item, t0: float, t1: float) -> list[float]:
        """Emission times of the layers due in [t0, t1)."""
        e, _, _, interval = item
        if e.end <= e.start:
            return []
        first = max(0, math.ceil((t0 - e.start) / interval - 1e-9))
        times = []
        L = first
        while True:
            t = e.start + L * interval
            if t >= t1 - 1e-12 or t >= e.end:
                break
            if t >= t0 - 1e-12:
                times.append(t)
            L += 1
        return times

    def emit(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities injected at the start of ``step``."""
        t0, t1 = step * self.dt, (step + 1) * self.dt
        xs, vs = [], []
        for item in self.items:
            e, d, layer, _ = item
            for t in self._layers_due(item, t0, t1):
                # the layer left the nozzle at t; place it where it would be at t0 + (t1 - t)
                # ahead of the nozzle so consecutive layers keep their spacing
                xs.append(layer + d * e.speed * (t1 - t))
                vs.append(np.tile(d * e.speed, (len(layer), 1)))
        if not xs:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
        return np.concatenate(xs).astype(np.float32), np.concatenate(vs).astype(np.float32)

    def total_particles(self, steps: int) -> int:
        """Particles emitted over the first ``steps`` steps (sizes the solver's arrays)."""
        total = 0
        for item in self.items:
            total += len(item[2]) * len(self._layers_due(item, 0.0, steps * self.dt))
        return total
