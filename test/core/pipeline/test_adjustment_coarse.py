"""Tests of the matrix-free solve's coarse space (hdmap_core.pipeline.adjustment_coarse).

``Z`` must hold one bias column per connected group of drives and hats over the knots that sum to
1 at every placed knot; the deflated conjugate gradients must give the direct solve of H x = rhs,
in fewer iterations than the per-drive blocks alone on a long chain of drives.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from hdmap_core.pipeline import adjustment as adj
from hdmap_core.pipeline import adjustment_assoc as assoc
from hdmap_core.pipeline.adjustment import AdjustConfig
from hdmap_core.pipeline.adjustment_coarse import Deflation, coarse_basis, drive_links, place_sums
from hdmap_core.pipeline.adjustment_schur import SchurNormal, SchurSolver
from hdmap_core.simulation.chains import ChainSimConfig, simulate_step_observations

LONG = ChainSimConfig(road_length_m=12000.0, n_drives=40, drive_length_max_m=3000.0, step_spacing_m=25.0)


def _fit(obs, cfg=None):
    cfg = cfg or AdjustConfig()
    pool = assoc.gather(obs, {})
    samples = assoc.select(pool, pool.label)
    lay = adj.knot_layout(samples, cfg)
    a = adj.design_matrix(samples, lay, cfg)
    op = SchurNormal(
        a,
        samples.cluster,
        samples.n_clusters,
        np.full(samples.s_m.size, cfg.noise_sigma_m**-2),
        samples.lateral_m,
        adj.prior_matrix(lay, cfg),
        samples.drive,
    )
    z = coarse_basis(lay.col0, lay.n_knots, place_sums(a, samples.xy), drive_links(samples.drive, samples.cluster))
    return samples, lay, op, z


def _two_roads(seed=0):
    """Two chains of drives that share no cluster (the second 5 km to the side, its own drives)."""
    cfg = replace(LONG, road_length_m=4000.0, n_drives=12)
    one, _ = simulate_step_observations(config=cfg, seed=seed)
    two, _ = simulate_step_observations(config=cfg, seed=seed + 1)
    two = [
        replace(
            o,
            pivot_id="b" + o.pivot_id,
            drive_ids=tuple("b" + d for d in o.drive_ids),
            midpoint=o.midpoint + [0.0, 5000.0],
        )
        for o in two
    ]
    return one + two


def test_basis_has_a_bias_column_per_group_and_hats_that_sum_to_one():
    samples, lay, _, z = _fit(_two_roads())
    z = z.toarray()
    bias_cols = z[lay.col0]
    # every drive's bias in exactly one column, and the drives of the two roads in different ones
    assert np.all((bias_cols > 0).sum(axis=1) == 1)
    group = np.argmax(bias_cols, axis=1)
    road_b = np.array([d.startswith("b") for d in samples.drive_ids])
    assert len(set(group[road_b])) == 1 and len(set(group[~road_b])) == 1 and group[road_b][0] != group[~road_b][0]
    knots = np.setdiff1d(np.arange(lay.n_unknowns), lay.col0)
    placed = z[knots].sum(axis=1) > 0
    assert placed.mean() > 0.9
    np.testing.assert_allclose(z[knots][placed].sum(axis=1), 1.0, atol=1e-12)
    # no knot column serves both roads
    hats = z[:, np.flatnonzero(bias_cols.sum(axis=0) == 0)]
    owner = np.repeat(road_b, 1 + lay.n_knots)
    assert not np.any((hats[owner] > 0).any(axis=0) & (hats[~owner] > 0).any(axis=0))


def test_drive_links_connect_the_drives_of_a_cluster():
    links = drive_links(np.array([3, 1, 1, 2, 0, 4]), np.array([0, 0, 0, 0, 1, 1]))
    assert sorted(map(tuple, links.tolist())) == [(0, 4), (1, 2), (2, 3)]
    assert drive_links(np.zeros(0, dtype=int), np.zeros(0, dtype=int)).shape == (0, 2)


def test_place_sums_weight_the_knots_by_the_design_matrix():
    a = sp.csr_matrix(np.array([[1.0, 0.25, 0.75], [1.0, 1.0, 0.0]]))
    sums = place_sums(a, np.array([[0.0, 10.0], [4.0, np.nan]]))  # the second sample has no place
    np.testing.assert_allclose(sums, [[1.0, 0.0, 10.0], [0.25, 0.0, 2.5], [0.75, 0.0, 7.5]])


def test_deflated_solve_is_the_direct_solve_in_fewer_iterations():
    obs, _ = simulate_step_observations(config=LONG, seed=2)
    _, _, op, z = _fit(obs)
    want = np.linalg.solve(op.toarray(), op.rhs)
    plain, deflated = SchurSolver(), SchurSolver(z)
    np.testing.assert_allclose(plain.solve(op, op.rhs, np.zeros(op.shape[0])), want, atol=1e-7)
    got = deflated.solve(op, op.rhs, np.zeros(op.shape[0]))
    np.testing.assert_allclose(got, want, atol=1e-7)
    assert deflated.unconverged == 0 and 0 < deflated.iterations < plain.iterations
    # the coarse space alone: H x = rhs restricted to it is solved exactly
    defl = Deflation(op, z)
    y = defl.solution(np.zeros(op.shape[0]), op.rhs)
    np.testing.assert_allclose(z.T @ (op @ y), z.T @ op.rhs, rtol=1e-8, atol=1e-8 * np.abs(z.T @ op.rhs).max())


def test_without_knots_the_biases_are_placed():
    cfg = adj.coarse_config(AdjustConfig())
    samples, lay, op, z = _fit(_two_roads(), cfg)
    dense = z.toarray()
    assert dense.shape[0] == lay.n_unknowns and dense.shape[1] > 2  # the groups' columns and hats over the drives
    np.testing.assert_allclose(dense.sum(axis=1), 2.0)  # its group's column + hats summing to 1
    want = np.linalg.solve(op.toarray(), op.rhs)
    np.testing.assert_allclose(SchurSolver(z).solve(op, op.rhs, np.zeros(op.shape[0])), want, atol=1e-7)
