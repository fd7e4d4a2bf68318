"""The offset adjustment over observations split into parts (hdmap_core.pipeline.adjustment_dist)
must be the one solve (``adjust_offsets``) up to the order of floating-point sums: explicit and
matrix-free, with lane shifts, thinned dense steps and uneven parts; and every part's share must
count (dropping one moves the offsets)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from step_fleets import lane_ambiguous_fleet

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
