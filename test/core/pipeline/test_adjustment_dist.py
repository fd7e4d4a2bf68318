"""The offset adjustment over observations split into parts (hdmap_core.pipeline.adjustment_dist)
must be the one solve (``adjust_offsets``) up to the order of floating-point sums: explicit and
matrix-free, with lane shifts, thinned dense steps and uneven parts; and every part's share must
count (dropping one moves the offsets)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from step_fleets import lane_ambiguous_fleet

from hdmap_core.errors import ConfigError
from hdmap_core.pipeline.adjustment import AdjustConfig, OffsetModel, adjust_offsets
from hdmap_core.pipeline.adjustment_dist import AdjustPart, adjust_parts, local_call
from hdmap_core.simulation.chains import ChainSimConfig, simulate_step_observations

SMALL = ChainSimConfig(road_length_m=6000.0, n_drives=40, drive_length_max_m=4000.0, step_spacing_m=25.0)
CFG = AdjustConfig(compute_std=False)


def _lane_ambiguous_fleet():
    """One drive a lane off by raw position: re-association and the lane-shift search have work."""
    return lane_ambiguous_fleet(SMALL)[0]


def _parts(obs, cuts):
    bounds = [0, *cuts, len(obs)]
    return [AdjustPart(obs[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def _max_diff(a: OffsetModel, b: OffsetModel) -> float:
    assert sorted(a.drives) == sorted(b.drives) and a.drives
    s = np.linspace(0.0, 6000.0, 61)
    return max(float(np.abs(a.offset(d, s) - b.offset(d, s)).max()) for d in a.drives)


@pytest.mark.parametrize("matrix_free", [False, True])
def test_parts_give_the_one_solve(monkeypatch, matrix_free):
    obs = _lane_ambiguous_fleet()
    explicit = adjust_offsets(obs, config=CFG)
    if matrix_free:
        monkeypatch.setattr(AdjustConfig, "max_pair_fill", 0)
    one = adjust_offsets(obs, config=CFG) if matrix_free else explicit
    # uneven parts, one of them a single step: the steps' global numbers, the drives' order and
    # the lane-shift search's picks must be the fleet's
    n = len(obs)
    parts = _parts(obs, [n // 5, n // 5 + 1, n // 2, (4 * n) // 5])
    got = adjust_parts(local_call(parts), len(parts), CFG)
    assert _max_diff(one, got) < 1e-7
    assert _max_diff(explicit, got) < 1e-7  # matrix-free (deflated CG) or not: the explicit one solve
    for key in ("n_samples_used", "lane_shifts", "n_clusters", "n_unknowns", "iterations", "relabelled_fraction"):
        assert got.stats[key] == pytest.approx(one.stats[key], rel=1e-9), key
    assert one.stats["lane_shifts"] > 0  # the shift search was exercised
    assert got.stats.get("matrix_free", False) == matrix_free == one.stats.get("matrix_free", False)
    if matrix_free:  # the parts' coarse space is the one process's
        assert got.stats["cg_coarse_unknowns"] == one.stats["cg_coarse_unknowns"] > 0
    # dense steps were thinned (seen by more than THIN_DRIVES drives): by their global number
    assert one.stats["n_samples_used"] < sum(np.count_nonzero(np.asarray(o.cluster) >= 0) for o in obs)


def test_every_part_counts():
    """Drop one part's share of the normal equations: the offsets move (so the test above would
    catch a part left out of the sums)."""
    obs, _ = simulate_step_observations(config=SMALL, seed=2)
    parts = _parts(obs, [len(obs) // 3, (2 * len(obs)) // 3])
    one = adjust_offsets(obs, config=CFG)
    assert _max_diff(one, adjust_parts(local_call(parts), 3, CFG)) < 1e-7
    inner = local_call(_parts(obs, [len(obs) // 3, (2 * len(obs)) // 3]))

    def dropping(method, args):
        out = inner(method, args)
        if method == "normal":  # the middle part's H_b and rhs_b lost
            h, r = out[1]
            out[1] = (h * 0.0, r * 0.0)
        return out

    assert _max_diff(one, adjust_parts(dropping, 3, CFG)) > 1e-3


def test_no_usable_observation_gives_an_empty_model():
    obs, _ = simulate_step_observations(config=SMALL, seed=2)
    empty = [replace(o, cluster=np.full(len(o.drive_ids), -1)) for o in obs[:3]]
    model = adjust_parts(local_call(_parts(empty, [1])), 2, replace(CFG, reassociate_rounds=0))
    assert model.drives == {} and model.stats["n_drives"] == 0


def _two_roads():
    """Two fleets that share no drive (two carriageways), their steps interleaved at random as
    two processes' pivots interleave in the one pivot order: (observations, road of each step)."""
    a = _lane_ambiguous_fleet()
    b = [
        replace(o, pivot_id="B" + o.pivot_id, drive_ids=tuple("B" + d for d in o.drive_ids))
        for o in simulate_step_observations(config=replace(SMALL, n_drives=25), seed=5)[0]
    ]
    road = np.random.default_rng(1).permutation(np.r_[np.zeros(len(a), int), np.ones(len(b), int)])
    queues = [iter(a), iter(b)]
    return [next(queues[r]) for r in road], road


@pytest.mark.parametrize("compute_std", [False, True])
def test_parts_that_share_no_drive_give_the_one_solve_to_the_last_bit(compute_std):
    """The whole-fleet build's pivot shares: parts of interleaved steps, given their numbers."""
    obs, road = _two_roads()
    cfg = replace(CFG, compute_std=compute_std, iterations=8)
    one = adjust_offsets(obs, config=cfg)
    steps = [np.flatnonzero(road == r) for r in (1, 0)]  # the parts in any order
    got = adjust_parts(local_call([AdjustPart([obs[i] for i in s]) for s in steps]), 2, cfg, steps=steps)
    assert list(got.drives) == list(one.drives)  # the one solve's drive order
    assert one.stats["lane_shifts"] > 0 and one.stats["iterations"] > 2  # re-weighting happened
    assert got.stats["std_computed"] == compute_std
    for d, want in one.drives.items():
        have = got.drives[d]
        assert (have.k0, have.bias_m) == (want.k0, want.bias_m)
        np.testing.assert_array_equal(have.drift_m, want.drift_m)
        np.testing.assert_array_equal([have.var_bias], [want.var_bias])  # nan without the std
        np.testing.assert_array_equal(have.var_drift, want.var_drift)


def test_parts_with_step_numbers_must_not_share_a_drive():
    obs = _lane_ambiguous_fleet()
    n = len(obs)
    steps = [np.arange(0, n, 2), np.arange(1, n, 2)]
    with pytest.raises(ConfigError, match="must not share a drive"):
        adjust_parts(local_call([AdjustPart([obs[i] for i in s]) for s in steps]), 2, CFG, steps=steps)
