"""PBF invariants: finite, conserved, contained, at rest density after settling, deterministic."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.config import Cameras, Emitter, FluidShape, Obstacle, SceneConfig, SimulateConfig, from_dict
from pipeline.sim.pbf import PBFSolver
from tests.conftest import CAMERAS

CAMS = from_dict(Cameras, CAMERAS)


def _scene(**kw) -> SceneConfig:
    base = dict(name="t", cameras=CAMS, domain_lo=(0.0, 0.0, 0.0), domain_hi=(0.4, 0.6, 0.3))
    base.update(kw)
    return SceneConfig(**base)


def _density(x: np.ndarray, solver: PBFSolver) -> np.ndarray:
    """SPH density from scratch (poly6, same mass), independent of the solver's kernels."""
    tree = cKDTree(x)
    h = solver.h
    rho = np.zeros(len(x))
    for i, nb in enumerate(tree.query_ball_point(x, h)):
        r2 = np.sum((x[nb] - x[i]) ** 2, axis=1)
        rho[i] = np.sum((h * h - r2) ** 3)
    return rho * solver.mass * 315.0 / (64.0 * math.pi * h**9)


def test_dam_break_stays_finite_contained_and_conserved():
    obstacle = Obstacle(shape="sphere", center=(0.3, 0.05, 0.15), radius=0.06)
    box = Obstacle(shape="box", lo=(0.15, 0.0, 0.0), hi=(0.2, 0.05, 0.1))
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.3, 0.3)),), obstacles=(obstacle, box))
    params = SimulateConfig(particle_radius=0.0125, frames=20)
    solver = PBFSolver(scene, params, "cpu", seed=0)
    n0 = solver.n
    for f in range(1, 21):
        solver.advance_frame(f)
    x, v = solver.state()
    solver.close()
    assert len(x) == n0
    assert np.isfinite(x).all() and np.isfinite(v).all()
    r = params.particle_radius
    lo, hi = np.array(scene.domain_lo) + r, np.array(scene.domain_hi) - r
    assert np.all(x >= lo - 1e-5) and np.all(x <= hi + 1e-5)
    assert np.linalg.norm(x - obstacle.center, axis=1).min() >= obstacle.radius + r - 1e-4
    inside_box = np.all((x > np.array(box.lo) - r + 1e-4) & (x < np.array(box.hi) + r - 1e-4), axis=1)
    assert not inside_box.any()
    assert x[:, 0].max() > 0.25, "the column must actually collapse and flow"


def test_settled_pool_is_at_rest_density_and_calms_down():
    # A pool dropped from a little height: interior density within 3% of rest once settled.
    scene = _scene(domain_hi=(0.45, 0.5, 0.45), fluid=(FluidShape(shape="box", lo=(0, 0.05, 0), hi=(0.45, 0.3, 0.45)),))
    params = SimulateConfig(particle_radius=0.0125, frames=75)
    solver = PBFSolver(scene, params, "cpu", seed=0)
    energies = []
    for f in range(1, 76):
        solver.advance_frame(f)
        if f % 15 == 0:
            energies.append(0.5 * float(np.sum(solver.state()[1] ** 2)))
    x, _ = solver.state()
    rho = _density(x, solver)
    h = solver.h
    surface = np.percentile(x[:, 1], 99)
    interior = (np.all(x > np.array(scene.domain_lo) + h, axis=1) & np.all(x < np.array(scene.domain_hi) - h, axis=1)
                & (x[:, 1] < surface - h))
    assert interior.sum() > 200
    mean = rho[interior].mean() / params.rest_density
    print(f"interior density {mean:.4f} x rest over {interior.sum()} particles; energies {energies}")
    solver.close()
    assert abs(mean - 1.0) < 0.03, f"interior density {mean:.3f} x rest"
    assert energies[-1] < 0.2 * energies[0], f"kinetic energy {energies}"
    assert energies[-1] < energies[-2] * 1.5


def test_emitter_adds_the_configured_count():
    emitter = Emitter(position=(0.2, 0.45, 0.15), direction=(0, -1, 0), radius=0.04, speed=1.0, start=0.0, end=0.25)
    scene = _scene(emitters=(emitter,))
    params = SimulateConfig(particle_radius=0.0125, frames=12, fps=30.0, substeps=4)
    solver = PBFSolver(scene, params, "cpu", seed=0)
    assert solver.n == 0
    for f in range(1, 13):
        solver.advance_frame(f)
    # layers every 2r / speed = 0.025 s over [0, 0.25): 10 layers; a disc of radius 0.04 on a
    # 0.025 lattice holds the points (i, j) with i^2 + j^2 <= 2.56: 9 points.
    layers = 10
    per_layer = sum(1 for i in range(-1, 2) for j in range(-1, 2) if (i * i + j * j) * 0.025**2 <= 0.04**2)
    assert solver.n == layers * per_layer == solver.capacity
    x, _ = solver.state()
    assert np.isfinite(x).all()
    solver.close()


def test_emitter_starting_later_leaves_the_first_frames_empty():
    emitter = Emitter(position=(0.2, 0.45, 0.15), direction=(0, -1, 0), radius=0.04, speed=1.0, start=0.1, end=0.2)
    params = SimulateConfig(particle_radius=0.0125, frames=9, fps=30.0, substeps=4)
    solver = PBFSolver(_scene(emitters=(emitter,)), params, "cpu", seed=0)
    counts = [solver.advance_frame(f).particles for f in range(1, 10)]
    solver.close()
    assert counts[0] == 0 and counts[-1] == solver.capacity > 0
    assert counts == sorted(counts)


def test_same_seed_same_frames():
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.25, 0.3)),))
    params = SimulateConfig(particle_radius=0.0125, frames=5)
    runs = []
    for _ in range(2):
        solver = PBFSolver(scene, params, "cpu", seed=7)
        for f in range(1, 6):
            solver.advance_frame(f)
        runs.append(solver.state())
        solver.close()
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_resume_from_saved_state_matches_straight_run():
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.25, 0.3)),),
                   emitters=(Emitter(position=(0.3, 0.4, 0.15), direction=(0, -1, 0), radius=0.03,
                                     speed=1.0, start=0.0, end=1.0),))
    params = SimulateConfig(particle_radius=0.0125, frames=6)
    a = PBFSolver(scene, params, "cpu", seed=1)
    for f in range(1, 7):
        a.advance_frame(f)
        if f == 3:
            mid = a.state()
    b = PBFSolver(scene, params, "cpu", seed=1)
    b.set_state(*mid, step_index=3 * params.substeps)
    for f in range(4, 7):
        b.advance_frame(f)
    np.testing.assert_array_equal(a.state()[0], b.state()[0])
    a.close()
    b.close()


def test_blow_up_is_reported_with_frame():
    from pipeline.sim.pbf import SimulationError

    # A body thrown at 15 m/s against a speed limit of 5 m/s trips the runaway-speed check.
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.25, 0.3), velocity=(15.0, 0, 0)),))
    params = SimulateConfig(particle_radius=0.0125, frames=3, max_speed=5.0)
    solver = PBFSolver(scene, params, "cpu", seed=0)
    with pytest.raises(SimulationError, match=r"blow-up at frame 1: a particle moves at \d+ m/s"):
        solver.advance_frame(1)
    solver.close()


def _reference_step(x0: np.ndarray, v0: np.ndarray, s: PBFSolver) -> tuple[np.ndarray, np.ndarray]:
    """One PBF step in float64 NumPy over all pairs from a k-d tree (no gravity, no walls in reach).

    Like the solver, it finds the pairs once, at the predicted positions, for every pass of the step.
    """
    p, h, vol = s.params, s.h, s.mass / s.params.rest_density
    x = x0 + v0 * s.dt
    pairs = cKDTree(x).query_pairs(h, output_type="ndarray")
    i, j = np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])

    def poly6(r: np.ndarray) -> np.ndarray:
        return s.poly6_coef * np.clip(h * h - np.sum(r * r, axis=1), 0.0, None) ** 3

    def spiky(r: np.ndarray) -> np.ndarray:
        rl = np.linalg.norm(r, axis=1, keepdims=True)
        return r * (s.spiky_coef * np.clip(h - rl, 0.0, None) ** 2 / rl)

    def pair_sum(values: np.ndarray) -> np.ndarray:
        out = np.zeros((len(x0),) + values.shape[1:])
        np.add.at(out, i, values)
        return out

    for _ in range(p.iterations):
        r = x[i] - x[j]
        w = poly6(r)
        g = spiky(r) * vol
        rho = s.mass * (s.poly6_coef * h**6 + pair_sum(w))
        grad = pair_sum(g)
        lam = -np.maximum(rho / p.rest_density - 1.0, 0.0) / (pair_sum(np.sum(g * g, axis=1))
                                                              + np.sum(grad * grad, axis=1) + p.relaxation)
        scorr = -p.artificial_pressure_k * (w / s.corr_w_dq) ** p.artificial_pressure_n
        dp = pair_sum(g * (lam[i] + lam[j] + scorr)[:, None])
        dl = np.linalg.norm(dp, axis=1, keepdims=True)
        x = x + dp * np.minimum(1.0, s.radius / np.maximum(dl, 1e-30))
    v = (x - x0) / s.dt
    r = x[i] - x[j]
    g = spiky(r)
    omega = pair_sum(np.cross(v[j] - v[i], -g) * vol)
    wl = np.linalg.norm(omega, axis=1)
    volj = (s.mass / rho[j])[:, None]
    eta = pair_sum(g * (wl[j] - wl[i])[:, None] * volj)
    visc = pair_sum((v[j] - v[i]) * poly6(r)[:, None] * volj)
    n_hat = eta / np.maximum(np.linalg.norm(eta, axis=1, keepdims=True), 1e-30)
    v = v + p.xsph_viscosity * visc + p.vorticity_epsilon * s.dt * np.cross(n_hat, omega)
    return x, v


@pytest.mark.parametrize("pair_passes", ["scatter", "gather"])
def test_a_step_matches_a_brute_force_reference(pair_passes):
    # A jittered, slightly compressed block with a swirling velocity, far from every wall: the
    # density, lambda, correction, vorticity and XSPH passes all act, and the block is large
    # enough (8,000 particles) that the two-phase scatter runs two blocks at once in each phase.
    # The gather passes (full lists, CUDA's default) must give the same step.
    r = 0.0125
    axis = (np.arange(20) - 9.5) * 1.8 * r
    x0 = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(3)
    x0 = x0 + rng.uniform(-0.1 * r, 0.1 * r, x0.shape) + 0.5
    v0 = 0.3 * np.cross(x0 - 0.5, [0.0, 1.0, 0.0]) + rng.normal(0.0, 0.02, x0.shape)
    # the fluid box only sizes the solver's buffers; set_state replaces its particles
    scene = _scene(domain_hi=(1.0, 1.0, 1.0), fluid=(FluidShape(shape="box", lo=(0.2, 0.2, 0.2), hi=(0.8, 0.8, 0.8)),))
    params = SimulateConfig(particle_radius=r, frames=1, gravity=(0.0, 0.0, 0.0), iterations=2, threads=2,
                            vorticity_epsilon=0.5, xsph_viscosity=0.1, pair_passes=pair_passes)
    solver = PBFSolver(scene, params, "cpu", seed=0)
    assert solver.gather == (pair_passes == "gather")
    solver.set_state(x0.astype(np.float32), v0.astype(np.float32), 0)
    solver.step()
    if pair_passes == "scatter":
        span = int(solver.neighbour_span.numpy()[:solver.n].max())
        assert len(solver.launch.scatter_blocks(solver.n, span)) == 4, "two blocks per phase, one per thread"
    x, v = solver.state()
    solver.close()
    x_ref, v_ref = _reference_step(x0.astype(np.float32).astype(np.float64), v0.astype(np.float32), solver)
    moved = np.linalg.norm(x_ref - x0 - v0 * solver.dt, axis=1)
    assert moved.mean() > 1e-4, "the density constraint must actually move particles"
    np.testing.assert_allclose(x, x_ref, atol=1e-6)
    np.testing.assert_allclose(v, v_ref, atol=2e-4)


def test_scatter_blocks_are_long_enough_and_balanced():
    from pipeline.parallel import Launcher

    launch = Launcher("cpu", threads=3)
    work = np.r_[np.full(1800, 1), np.full(1200, 10)]  # the second part costs ten times more
    cumulative = np.r_[0, np.cumsum(work)]
    blocks = launch.scatter_blocks(3000, 99, cumulative)
    starts, counts = np.array(blocks).T
    assert len(blocks) == 6 and starts[0] == 0 and starts[-1] + counts[-1] == 3000
    np.testing.assert_array_equal(starts[1:], starts[:-1] + counts[:-1])
    assert counts.min() >= 100, "a block shorter than span + 1 would race with the one after next"
    cost = [cumulative[a + c] - cumulative[a] for a, c in blocks]
    assert max(cost) < 1.1 * min(cost), f"unbalanced {cost}"
    # where the span forbids balance, blocks keep their minimum length
    tight = launch.scatter_blocks(3000, 400, cumulative)
    launch.close()
    assert len(tight) == 6 and min(c for _, c in tight) >= 401


def test_thread_counts_agree():
    # Blocks follow the thread count, so sums are added in another order: equal to rounding.
    scene = _scene(domain_hi=(0.5, 0.5, 0.4), fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.25, 0.4, 0.4)),))
    runs = []
    for threads in (1, 2):
        solver = PBFSolver(scene, SimulateConfig(particle_radius=0.01, frames=2, threads=threads), "cpu", seed=0)
        for f in range(1, 3):
            solver.advance_frame(f)
        runs.append(solver.state())
        solver.close()
    np.testing.assert_allclose(runs[0][0], runs[1][0], atol=1e-4)  # 1% of a radius
    np.testing.assert_allclose(runs[0][1], runs[1][1], atol=1e-2)


def test_gather_passes_repeat_bit_for_bit_at_any_thread_count_and_follow_the_scatter():
    """Over full lists each particle sums its own pairs in list order: runs with 1 and 2 threads
    are bit-identical (a GPU's runs too, where the scatter's atomics are not), the neighbour
    counts are the half lists' doubled, and the flow is the scatter's to the rounding of a few
    steps (a chaotic flow parts from it slowly after that)."""
    scene = _scene(domain_hi=(0.5, 0.5, 0.4), fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.25, 0.4, 0.4)),))
    runs, stats = {}, {}
    for mode, threads in (("gather", 1), ("gather", 2), ("scatter", 2)):
        solver = PBFSolver(scene, SimulateConfig(particle_radius=0.01, frames=1, threads=threads, pair_passes=mode),
                           "cpu", seed=0)
        stats[mode, threads] = solver.advance_frame(1)
        runs[mode, threads] = solver.state()
        solver.close()
    for a, b in zip(runs["gather", 1], runs["gather", 2], strict=True):
        np.testing.assert_array_equal(a, b)
    (xg, vg), (xs, vs) = runs["gather", 2], runs["scatter", 2]
    np.testing.assert_allclose(xg, xs, atol=1e-5)
    np.testing.assert_allclose(vg, vs, atol=1e-3)
    assert stats["gather", 2].particles == stats["scatter", 2].particles
    assert abs(stats["gather", 2].mean_neighbours - stats["scatter", 2].mean_neighbours) < 0.05
    assert abs(stats["gather", 2].max_density_ratio - stats["scatter", 2].max_density_ratio) < 0.01


def test_full_neighbour_lists_are_the_pairs_within_h_in_order():
    """``find_all_neighbours``: each particle's list is every other particle within h, ascending,
    against a k-d tree."""
    scene = _scene(domain_hi=(0.5, 0.5, 0.4), fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.25, 0.4, 0.4)),))
    solver = PBFSolver(scene, SimulateConfig(particle_radius=0.01, frames=1, pair_passes="gather"), "cpu", seed=0)
    solver.advance_frame(1)
    solver.predict_and_search()
    x = solver.x_pred.numpy()[:solver.n].astype(np.float64)
    lists = _half_lists(solver)
    solver.close()
    tree = cKDTree(x)
    for k in range(0, len(x), 97):
        want = sorted(j for j in tree.query_ball_point(x[k], solver.h * (1 - 1e-6)) if j != k)
        got = list(lists[k])
        assert got == sorted(got), k
        assert set(want) <= set(got) and len(got) <= len(want) + 2, k  # pairs at h itself may go either way


def _half_lists(solver: PBFSolver) -> list[np.ndarray]:
    n = solver.n
    start, end = solver.neighbour_start.numpy()[:n], solver.neighbour_end.numpy()[:n]
    index = solver.neighbour_index.numpy()
    return [index[a:b].copy() for a, b in zip(start, end, strict=True)]


@pytest.mark.parametrize("max_neighbours", [64, 10])
def test_neighbour_lists_are_the_pairs_within_h_with_either_scan(max_neighbours):
    # A falling column, two threads (two chunks writing their own packed regions). Each list must
    # hold the particles j > k within h in ascending order; capped at max_neighbours, the first
    # ones of that order. The vector (AVX-512, where the CPU has it) and scalar row scans must
    # build the same lists, and so the same step.
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.15, 0.3, 0.2)),))
    params = SimulateConfig(particle_radius=0.0125, frames=1, threads=2, max_neighbours=max_neighbours)
    lists, states = [], []
    for vector in (True, False):
        solver = PBFSolver(scene, params, "cpu", seed=1, vector_scan=vector)
        solver.step()  # a step, so the search runs on sorted, moving particles
        solver.predict_and_search()
        x = solver.x_pred.numpy()[:solver.n].copy()
        lists.append(_half_lists(solver))
        solver.step()
        states.append(solver.state())
        solver.close()
    x = x.astype(np.float32)
    h2 = np.float32(solver.h) ** 2
    capped = 0
    for k, near in enumerate(cKDTree(x).query_ball_point(x, 1.01 * solver.h)):
        near = np.array(sorted(j for j in near if j > k), dtype=np.int64)
        d = x[near] - x[k] if len(near) else np.zeros((0, 3), np.float32)
        expect = near[d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2] < h2]
        capped += len(expect) > max_neighbours
        np.testing.assert_array_equal(lists[0][k], expect[:max_neighbours], err_msg=f"particle {k}")
        np.testing.assert_array_equal(lists[1][k], lists[0][k])
    assert (capped > 0) == (max_neighbours < 30), "the small cap must actually cut lists, the large one none"
    for a, b in zip(states[0], states[1], strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("threads, per_thread", [(2, 1), (2, 3), (3, 1)])
def test_the_gang_step_adds_the_sums_of_the_phase_by_phase_step(threads, per_thread, monkeypatch):
    # The CPU runs a step's pair passes as one gang launch per thread; launched phase by phase
    # (``Launcher.scatter_passes``) on the same blocks, the step must come out bit for bit the same,
    # with several blocks per thread (taken as threads come free) and with more threads than cores.
    import pipeline.sim.pbf as pbf

    monkeypatch.setattr(pbf, "BLOCKS_PER_THREAD", per_thread)
    # a column long in z, the slowest axis of the cell order, so the blocks are many and short
    scene = _scene(domain_hi=(0.2, 0.6, 1.5), fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.1, 0.3, 1.5)),))
    params = SimulateConfig(particle_radius=0.0125, frames=1, threads=threads)
    states = []
    for gang in (True, False):
        solver = PBFSolver(scene, params, "cpu", seed=2, gang=gang)
        for _ in range(3):
            solver.step()
        span = int(solver.neighbour_span.numpy()[:solver.n].max())
        blocks = solver.launch.scatter_blocks(solver.n, span, per_thread=per_thread)
        states.append(solver.state())
        solver.close()
    assert len(blocks) == 2 * per_thread * threads, "the column must be long enough for every block"
    for a, b in zip(states[0], states[1], strict=True):
        np.testing.assert_array_equal(a, b)


def test_the_native_finish_loops_give_the_general_functions_bits():
    # A scene without obstacles finishes its density and correction passes in native loops over
    # each block in the gang; the general Warp functions (which obstacles need, and the phase-by-phase
    # launches use) must give the same bits. The column falls against the floor and two walls, so
    # the wall terms act.
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.15, 0.3, 0.2)),))
    params = SimulateConfig(particle_radius=0.0125, frames=1, threads=2)
    states = []
    for native in (True, False):
        solver = PBFSolver(scene, params, "cpu", seed=4, gang=native)
        for _ in range(6):
            solver.step()
        states.append((*solver.state(), solver.particle_rho.numpy()[:solver.n].copy()))
        solver.close()
    assert np.abs(states[0][1]).max() > 0.1, "the column must be moving"
    for a, b in zip(states[0], states[1], strict=True):
        np.testing.assert_array_equal(a, b)


def test_frame_diagnostics_reduce_like_numpy_and_skip_non_finite_particles():
    import warp as wp

    from pipeline.sim import kernels as K

    rng = np.random.default_rng(3)
    x = rng.uniform(0.0, 1.0, (500, 3)).astype(np.float32)
    v = rng.normal(size=(500, 3)).astype(np.float32)
    rho = rng.uniform(900.0, 1100.0, 500).astype(np.float32)
    counts = rng.integers(0, 40, 500).astype(np.int32)
    x[7] = (1.5, 0.5, 0.5)  # outside on +x
    x[8] = (0.5, -0.2, 0.5)  # outside on -y
    v[9, 1] = np.nan  # not finite: counted, and its huge density kept out of the maximum
    rho[9] = 1e9
    x[10, 2] = np.inf
    out = wp.zeros(K.DIAG_SIZE, dtype=float, device="cpu")
    wp.launch(K.frame_diagnostics, 500, [wp.array(x, dtype=wp.vec3), wp.array(v, dtype=wp.vec3), wp.array(rho),
                                         wp.array(counts, dtype=int), wp.vec3(0, 0, 0), wp.vec3(1, 1, 1), out],
              device="cpu")
    d = out.numpy()
    finite = np.ones(500, bool)
    finite[[9, 10]] = False
    assert d[K.DIAG_NONFINITE] == 2
    assert d[K.DIAG_OUTSIDE] == 2
    assert d[K.DIAG_MAX_DENSITY] == rho[finite].max()
    np.testing.assert_allclose(d[K.DIAG_MAX_SPEED2], (v[finite] ** 2).sum(1).max(), rtol=1e-6)
    assert d[K.DIAG_NEIGHBOURS] == counts.sum()


def test_finished_frame_reports_what_the_particles_hold():
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.25, 0.3)),))
    solver = PBFSolver(scene, SimulateConfig(particle_radius=0.0125, frames=4), "cpu", seed=2)
    for f in range(1, 4):
        stats, x, v = solver.finish_frame(solver.begin_frame(f))
        n = solver.n
        x_ref, v_ref = solver.state()
        np.testing.assert_array_equal(x, x_ref)
        np.testing.assert_array_equal(v, v_ref)
        assert stats.particles == n == len(x)
        assert stats.max_density_ratio == pytest.approx(solver.particle_rho.numpy()[:n].max() / 1000.0, rel=1e-6)
        assert stats.mean_neighbours == pytest.approx(2 * solver.neighbour_count.numpy()[:n].mean(), rel=1e-6)
    solver.close()


def test_the_stage_loop_writes_the_frames_of_a_plain_loop(tmp_path):
    """The pipelined stage loop (frame k + 1 queued before frame k is checked and written) saves
    exactly the frames of advance_frame + state, with an emitter changing the count mid-run."""
    from pipeline.frames import frame_name, load_frame
    from pipeline.sim.runner import simulate_sequence

    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0, 0), hi=(0.12, 0.2, 0.3)),),
                   emitters=(Emitter(position=(0.3, 0.4, 0.15), direction=(0, -1, 0), radius=0.03,
                                     speed=1.0, start=0.05, end=0.15),))
    params = SimulateConfig(particle_radius=0.0125, frames=6)
    extra = simulate_sequence(tmp_path, scene, params, "cpu", seed=4)
    solver = PBFSolver(scene, params, "cpu", seed=4)
    counts = set()
    for f in range(1, 7):
        solver.advance_frame(f)
        x_ref, v_ref = solver.state()
        x, v = load_frame(tmp_path / frame_name(f))
        np.testing.assert_array_equal(x, x_ref)
        np.testing.assert_array_equal(v, v_ref)
        counts.add(len(x))
    solver.close()
    assert len(counts) > 1 and extra["particles"] == max(counts)


def test_the_stage_keeps_the_frames_before_a_blow_up_and_not_the_blown_one(tmp_path):
    from pipeline.frames import frame_name, load_frame
    from pipeline.sim.runner import SimulationFailed, simulate_sequence

    # a body thrown at 3 m/s, falling and splashing, passes a 3.5 m/s limit at some frame k > 1
    scene = _scene(fluid=(FluidShape(shape="box", lo=(0, 0.3, 0), hi=(0.1, 0.5, 0.3), velocity=(3.0, 0, 0)),))
    params = SimulateConfig(particle_radius=0.0125, frames=12, max_speed=3.5)
    with pytest.raises(SimulationFailed, match=r"blow-up at frame (\d+): a particle moves") as err:
        simulate_sequence(tmp_path, scene, params, "cpu", seed=0)
    blown = int(err.value.args[0].split("frame ")[1].split(":")[0])
    assert blown > 1
    for f in range(1, blown):
        assert np.isfinite(load_frame(tmp_path / frame_name(f))[0]).all()
    assert not (tmp_path / frame_name(blown)).exists()
    assert not (tmp_path / frame_name(blown + 1)).exists()
