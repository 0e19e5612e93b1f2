"""The neighbour estimate that guards every neighbour search against a crowded frame."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.sph import anisotropy_support, lattice_offsets, neighbour_count, spacing


@pytest.mark.parametrize("jitter", [0.0, 0.2])
def test_a_fluid_at_rest_has_the_lattice_count_of_neighbours(jitter):
    """Particles on the rest lattice (spacing 2r, jittered by a share of it) filling 8^3 cells of the
    support's side: the estimate is within 5% of the lattice points within the support."""
    r = 0.01
    support, step = anisotropy_support(r, 5.0), spacing(r)
    g = np.arange(40) * step
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    x += np.random.default_rng(1).uniform(-jitter / 2, jitter / 2, x.shape) * step
    d = np.linalg.norm(lattice_offsets(step, support), axis=1)
    lattice = ((d < support).sum() + (d <= support).sum()) / 2 - 1  # 499: the boundary's points half in
    estimate = neighbour_count(x, support)
    assert 0.95 * lattice < estimate < 1.15 * lattice, (estimate, lattice)


def test_a_cloud_in_one_cell_counts_every_particle_and_an_empty_frame_none():
    x = np.random.default_rng(0).uniform(0.0, 1e-3, (1000, 3))
    assert neighbour_count(x, 0.1) == 1000
    assert neighbour_count(np.zeros((0, 3)), 0.1) == 0.0


def test_a_stray_particle_far_out_leaves_the_estimate_of_the_bulk():
    """One particle a kilometre away: the dense grid would be huge, so the cells are hashed, and
    the bulk's estimate barely moves."""
    r = 0.01
    support, step = anisotropy_support(r, 5.0), spacing(r)
    g = np.arange(40) * step
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    stray = np.vstack([x, [[1000.0, 1000.0, 1000.0]]])
    assert abs(neighbour_count(stray, support) - neighbour_count(x, support)) < 1.0
