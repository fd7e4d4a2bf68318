"""Tests of the matrix-free reduced normal equations (hdmap_core.pipeline.adjustment_schur).

The operator must be the explicit Schur complement (``adjustment.reduced_normal`` plus the prior)
entry for entry, and the adjustment solved with it (``AdjustConfig.max_pair_fill`` 0) must give the explicit
solve's offsets within the CG tolerance.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from hdmap_core.pipeline import adjustment as adj
from hdmap_core.pipeline import adjustment_assoc as assoc
from hdmap_core.pipeline.adjustment import AdjustConfig, adjust_offsets
from hdmap_core.pipeline.adjustment_schur import SchurNormal, SchurSolver, pair_fill
from hdmap_core.simulation.chains import ChainSimConfig, simulate_step_observations

SMALL = ChainSimConfig(road_length_m=6000.0, n_drives=24, drive_length_max_m=4000.0, step_spacing_m=25.0)


def _system(seed: int = 0, drift: bool = True):
    """A synthetic fit's pieces with uneven weights (some 0, as coarse-rejected samples)."""
    obs, _ = simulate_step_observations(config=SMALL, seed=seed)
    pool = assoc.gather(obs, {})
    samples = assoc.select(pool, pool.label)
    cfg = AdjustConfig() if drift else adj.coarse_config(AdjustConfig())
    lay = adj.knot_layout(samples, cfg)
    a = adj.design_matrix(samples, lay, cfg)
    prior = adj.prior_matrix(lay, cfg)
    rng = np.random.default_rng(seed)
    info = cfg.noise_sigma_m**-2 * rng.uniform(0.2, 1.0, samples.s_m.size)
    info[rng.random(samples.s_m.size) < 0.05] = 0.0
    return samples, a, prior, info


@pytest.mark.parametrize("drift", [True, False])
def test_operator_is_the_explicit_schur_complement(drift):
    samples, a, prior, info = _system(drift=drift)
    h, rhs = adj.reduced_normal(a, samples.cluster, samples.n_clusters, info, samples.lateral_m)
    h = (h + prior).toarray()
    op = SchurNormal(a, samples.cluster, samples.n_clusters, info, samples.lateral_m, prior, samples.drive)
    assert op.shape == h.shape
    np.testing.assert_allclose(op.rhs, rhs, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(op.toarray(), h, rtol=1e-10, atol=1e-6 * np.abs(h).max())
    v = np.random.default_rng(1).normal(size=h.shape[1])
    np.testing.assert_allclose(op @ v, h @ v, rtol=1e-9, atol=1e-9 * np.abs(h @ v).max())
    # the preconditioner: H's entries within each drive, nothing across drives
    lay = adj.knot_layout(samples, AdjustConfig() if drift else adj.coarse_config(AdjustConfig()))
    owner = np.repeat(np.arange(lay.col0.size), 1 + lay.n_knots)
    same = owner[:, None] == owner[None, :]
    np.testing.assert_allclose(op.drive_blocks().toarray(), np.where(same, h, 0.0), atol=1e-6 * np.abs(h).max())
    assert np.abs(np.where(same, 0.0, h)).max() > 0  # the drives are coupled: the test is not trivial


def test_solver_matches_a_direct_solve():
    samples, a, prior, info = _system(seed=3)
    op = SchurNormal(a, samples.cluster, samples.n_clusters, info, samples.lateral_m, prior, samples.drive)
    want = np.linalg.solve(op.toarray(), op.rhs)
    solver = SchurSolver()
    got = solver.solve(op, op.rhs, np.zeros(op.shape[0]))
    np.testing.assert_allclose(got, want, atol=1e-7)
    assert solver.unconverged == 0 and solver.iterations > 0
    # warm start at the solution: (almost) nothing left to do
    before = solver.iterations
    solver.solve(op, op.rhs, got)
    assert solver.iterations - before <= 2


def test_pair_fill_counts_the_pairs_of_unknowns_that_share_a_cluster(monkeypatch):
    import hdmap_core.pipeline.adjustment_schur as schur  # noqa: PLC0415

    # two clusters: the first touches columns {0, 1, 3}, the second {1, 2}: pairs 3^2 + 2^2 less
    # the one they share, (1, 1)
    a = sp.csr_matrix(np.array([[1.0, 0.5, 0, 0], [0, 1.0, 0, 0.5], [0, 0.3, 0.7, 0], [0, 0, 1.0, 0]]))
    assert pair_fill(a, np.array([0, 0, 1, 1]), 2) == 3**2 + 2**2 - 1
    assert pair_fill(a, np.array([0, 0, 0, 0]), 1) == 4**2
    samples, a, _, _ = _system()
    b = (abs(a).T @ sp.csr_matrix((np.ones(a.shape[0]), samples.cluster, np.arange(a.shape[0] + 1)))).tocsr()
    want = (b @ b.T).nnz
    monkeypatch.setattr(schur, "PAIR_COUNT_ROWS", 7)  # many slabs: the same count
    assert pair_fill(a, samples.cluster, samples.n_clusters) == want
    assert want > pair_fill(a, samples.cluster, samples.n_clusters, stop_above=want // 10) > want // 10


def test_matrix_free_adjustment_equals_the_explicit_one(monkeypatch):
    """The whole adjustment (association, robust IRLS, std) with the operator from the start."""
    sim = replace(SMALL, wrong_label_fraction=0.05)
    obs, _ = simulate_step_observations(config=sim, seed=5)
    explicit = adjust_offsets(obs)
    monkeypatch.setattr(AdjustConfig, "max_pair_fill", 0)
    free = adjust_offsets(obs)
    assert "matrix_free" not in explicit.stats
    assert free.stats["matrix_free"] is True and free.stats["cg_unconverged"] == 0
    assert free.stats["cg_coarse_unknowns"] > 0  # deflated by the coarse space
    assert explicit.stats["iterations"] > 1  # IRLS re-weighted: the operator was rebuilt
    for key in ("n_samples_used", "lane_shifts", "iterations", "relabelled_fraction"):
        assert free.stats[key] == explicit.stats[key], key
    assert sorted(free.drives) == sorted(explicit.drives) and explicit.drives
    for d, cur in explicit.drives.items():
        other = free.drives[d]
        assert other.k0 == cur.k0
        np.testing.assert_allclose(other.bias_m, cur.bias_m, atol=1e-7)
        np.testing.assert_allclose(other.drift_m, cur.drift_m, atol=1e-7)
        np.testing.assert_allclose(other.var_bias, cur.var_bias, rtol=1e-6)
        np.testing.assert_allclose(other.var_drift, cur.var_drift, rtol=1e-6)
