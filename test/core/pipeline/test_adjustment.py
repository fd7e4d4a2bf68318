"""Tests of the network-wide lateral offset adjustment (hdmap_core.pipeline.adjustment).

The synthetic cases come from ``hdmap_core.simulation.chains``: a road with five lines, drives that
cover random intervals of it (chains of overlaps), each with a known correction curve
(bias + Gauss-Markov drift). "Common error" at a step is the mean, over the drives crossing it,
of (estimated - true) correction: exactly what shifts the fused lines of that step. The per-step
method (paper) leaves the mean true correction of those drives in the map; its expected size is
the local floor sqrt(sigma_bias^2 + sigma_drift^2) / sqrt(N) (times sqrt(2/pi) for a mean |.|).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from step_fleets import LANE_SHIFT_M, lane_ambiguous_fleet

from hdmap_core.errors import ConfigError
from hdmap_core.model import FeatureType
from hdmap_core.pipeline.adjustment import AdjustConfig, OffsetModel, adjust_offsets
from hdmap_core.simulation.chains import ChainSimConfig, simulate_step_observations
from hdmap_core.steps import StepObservations

from former_configs import former

# A short chain keeps every case around a second: 10 km road, 30 drives of 2-5 km.
SMALL = ChainSimConfig(road_length_m=10000.0, n_drives=30, drive_length_max_m=5000.0, step_spacing_m=25.0)


def _per_step_errors(obs, truth, model):
    """Per step with >= 2 drives: common error, local common offset, drive count, relative errors."""
    common, local, n_local, rel = [], [], [], []
    for o in obs:
        ids, first = np.unique(np.asarray(o.drive_ids), return_index=True)
        if ids.size < 2:
            continue
        s = np.asarray(o.drive_s_m)[first]
        true = np.array([truth.true_correction(d, x) for d, x in zip(ids, s)])
        est = np.array([model.offset(d, np.array([x]))[0] for d, x in zip(ids, s)])
        err = est - true
        common.append(err.mean())
        local.append(true.mean())
        n_local.append(ids.size)
        rel.append(err - err.mean())
    return np.array(common), np.array(local), np.array(n_local), np.concatenate(rel)


def _floor(cfg: ChainSimConfig, n_local: np.ndarray) -> float:
    """Expected mean |common offset| of N drives: the per-step method's floor."""
    sigma = np.hypot(cfg.bias_sigma_m, cfg.drift_sigma_m)
    return float(np.mean(sigma / np.sqrt(n_local)) * np.sqrt(2.0 / np.pi))


# --------------------------------------------------------------------------------------------
# Known answers
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_noise_free_bias_only_recovers_offsets_and_gauge():
    # Zero-mean true biases, no drift, no noise: relative offsets are exact, and the zero-mean
    # prior fixes the gauge exactly when the model has no drift either.
    sim = replace(SMALL, noise_sigma_m=0.0, drift_sigma_m=0.0, zero_mean_bias=True)
    obs, truth = simulate_step_observations(config=sim, seed=3)
    model = adjust_offsets(obs, config=former(AdjustConfig, drift_sigma_m=0.0))
    common, local, n_local, rel = _per_step_errors(obs, truth, model)
    floor = _floor(sim, n_local)
    assert np.abs(rel).max() < 1e-3
    assert np.abs(common).mean() < 0.01 * floor
    # The default model (with drift) lets the common mode wander a little with place, but the
    # relative offsets stay exact and the gauge is still far below the local floor.
    model = adjust_offsets(obs)
    common, _, _, rel = _per_step_errors(obs, truth, model)
    assert np.abs(rel).max() < 0.01
    assert np.abs(common).mean() < 0.3 * floor
    assert np.abs(local).mean() > 0.5 * floor  # the case is not trivially easy


@pytest.mark.slow
def test_noise_free_drift_is_followed_by_the_curve():
    sim = replace(SMALL, noise_sigma_m=0.0)
    obs, truth = simulate_step_observations(config=sim, seed=1)
    _, _, _, rel_curve = _per_step_errors(obs, truth, adjust_offsets(obs))
    _, _, _, rel_const = _per_step_errors(
        obs, truth, adjust_offsets(obs, config=former(AdjustConfig, drift_sigma_m=0.0))
    )
    rms_curve, rms_const = np.sqrt(np.mean(rel_curve**2)), np.sqrt(np.mean(rel_const**2))
    # A constant per drive cannot follow the 0.3 m drift; 200 m knots follow most of it (what is
    # left is the Gauss-Markov roughness between knots).
    assert rms_const > 0.2
    assert rms_curve < 0.35 * rms_const


@pytest.mark.slow
def test_noisy_absolute_error_below_local_floor():
    # The main claim: tying every place to the whole chain of drives brings the common offset
    # below what the N drives at that place can give. Three fixed seeds, full-size chain.
    sim = ChainSimConfig()
    ours, local_floor, per_step = [], [], []
    for seed in (0, 1, 2):
        obs, truth = simulate_step_observations(config=sim, seed=seed)
        common, local, n_local, _ = _per_step_errors(obs, truth, adjust_offsets(obs))
        ours.append(np.abs(common).mean())
        local_floor.append(_floor(sim, n_local))
        per_step.append(np.abs(local).mean())
    print(
        f"mean |common error|: adjusted {np.round(ours, 3)}, floor {np.round(local_floor, 3)}, "
        f"per-step {np.round(per_step, 3)}"
    )
    assert np.mean(ours) < 0.75 * np.mean(local_floor)
    assert np.mean(ours) < 0.75 * np.mean(per_step)
    assert max(ours) < max(local_floor)


@pytest.mark.slow
@pytest.mark.parametrize("burst_m", [0.0, 100.0])
def test_wrong_labels_are_resisted_by_the_robust_loss(burst_m):
    sim = replace(SMALL, wrong_label_fraction=0.05, wrong_label_burst_m=burst_m)
    obs, truth = simulate_step_observations(config=sim, seed=5)
    clean_obs, _ = simulate_step_observations(config=replace(sim, wrong_label_fraction=0.0), seed=5)
    rms = {}
    variants = {
        # no robustness at all: plain least squares on the given labels
        "linear": former(AdjustConfig, loss="linear", coarse_reject_m=0.0, reassociate_rounds=0),
        # robust loss (+ coarse stage) on the given labels
        "huber_labels": former(AdjustConfig, reassociate_rounds=0),
        "cauchy_labels": former(AdjustConfig, loss="cauchy", reassociate_rounds=0),
        # default: re-association (global EM) as well
        "default": former(AdjustConfig),
    }
    for name, cfg in variants.items():
        model = adjust_offsets(obs, config=cfg)
        common, _, n_local, rel = _per_step_errors(obs, truth, model)
        rms[name] = float(np.sqrt(np.mean(rel**2)))
        if name != "linear":
            assert np.abs(common).mean() < _floor(sim, n_local)
            handled = model.stats["downweighted_fraction"] + model.stats["relabelled_fraction"]
            assert 0.02 < handled < 0.15
    _, _, _, rel_clean = _per_step_errors(clean_obs, truth, adjust_offsets(clean_obs))
    rms_clean = float(np.sqrt(np.mean(rel_clean**2)))
    print(f"relative rms: {rms}, clean {rms_clean:.3f}")
    for name in ("huber_labels", "cauchy_labels", "default"):
        assert rms[name] < 0.5 * rms["linear"]
        assert rms[name] < 1.3 * rms_clean


def test_lane_shifted_stretch_is_rejected_by_the_coarse_stage():
    # Equally spaced lines: a drive associated one lane off is self-consistent (all its samples
    # agree with an offset of 3.5 m), so a per-sample robust loss cannot see it; the curve would
    # follow it. Here one drive is a lane off for 400 m of its length.
    sim = replace(SMALL, line_offsets_m=(-5.25, -1.75, 1.75, 5.25), line_types=(2, 2, 2, 2))
    obs, truth = simulate_step_observations(config=sim, seed=7)
    victim = truth.drive_ids[int(np.argmax([g[-1] - g[0] for g in truth.grid_s_m]))]  # the longest drive
    s_lo = truth.grid_s_m[truth.drive_ids.index(victim)][0] + 1000.0
    shifted = []
    for o in obs:
        hit = (np.asarray(o.drive_ids) == victim) & (o.drive_s_m >= s_lo) & (o.drive_s_m < s_lo + 400.0)
        if hit.any():
            cl = o.cluster.copy()
            cl[hit] = np.where(cl[hit] < 3, cl[hit] + 1, -1)
            o = replace(o, cluster=cl)
        shifted.append(o)
    s = np.linspace(s_lo + 50.0, s_lo + 350.0, 7)
    true = truth.true_correction(victim, s)
    plain = former(AdjustConfig, coarse_reject_m=0.0, reassociate_rounds=0)
    err_plain = np.abs(adjust_offsets(shifted, config=plain).offset(victim, s) - true)
    model = adjust_offsets(shifted, config=former(AdjustConfig, reassociate_rounds=0))
    err = np.abs(model.offset(victim, s) - true)
    err_default = np.abs(adjust_offsets(shifted).offset(victim, s) - true)
    assert err_default.max() < 0.5
    print(f"lane-shifted stretch: error without coarse stage {err_plain.round(2)}, with {err.round(2)}")
    assert err_plain.max() > 1.0
    assert err.max() < 0.5  # no data there: the curve bridges 400 m of drift
    assert 0.0 < model.stats["coarse_rejected_fraction"] < 0.02


def test_drive_with_large_bias_is_not_left_a_lane_off():
    # Dashed lines 3.5 m apart, rarely seen borders outside. One drive gets 2.5 m of extra bias:
    # by raw position most of its dashed samples are nearer the neighbouring line (a whole-drive
    # lane ambiguity); its border samples and the far dashed line disagree. The default
    # adjustment (re-association, shift search) must end on the right lane.
    moved, truth, victim = lane_ambiguous_fleet(SMALL)
    g = truth.grid_s_m[truth.drive_ids.index(victim)]
    s = np.linspace(g[0] + 100.0, g[-1] - 100.0, 9)
    true = truth.true_correction(victim, s) - LANE_SHIFT_M
    model = adjust_offsets(moved)
    err = np.abs(model.offset(victim, s) - true)
    print(f"large-bias drive: error {err.round(2)}, lane shifts {model.stats['lane_shifts']}")
    assert err.max() < 0.5


def test_schur_elimination_matches_explicit_least_squares():
    # Small case solved densely with the cluster positions as explicit unknowns and the priors
    # written out as whitened rows: the eliminated sparse solution must be the same.
    sim = replace(
        SMALL,
        road_length_m=2000.0,
        n_drives=5,
        drive_length_min_m=800.0,
        drive_length_max_m=1500.0,
        step_spacing_m=50.0,
    )
    obs, _ = simulate_step_observations(config=sim, seed=2)
    cfg = former(AdjustConfig, loss="linear", knot_spacing_m=150.0, compute_std=True)
    model = adjust_offsets(obs, config=cfg)
    ids = list(model.drives)
    col = {}
    p = 0
    for d in ids:
        col[d] = p
        p += 1 + model.drives[d].drift_m.size
    width = p + sum(np.unique(o.cluster).size for o in obs)  # bound on the cluster unknowns
    rows, rhs = [], []
    n_x = 0
    for o in obs:
        for c in np.unique(o.cluster):
            members = np.flatnonzero(o.cluster == c)
            members = [i for i in members if o.drive_ids[i] in col]
            if len({o.drive_ids[i] for i in members}) < 2:
                continue
            for i in members:
                d = o.drive_ids[i]
                cur = model.drives[d]
                row = np.zeros(width)
                u = o.drive_s_m[i] / cfg.knot_spacing_m - cur.k0
                k = int(np.clip(np.floor(u), 0, cur.drift_m.size - 2))
                t = u - k
                row[col[d]] = 1.0
                row[col[d] + 1 + k] += 1.0 - t
                row[col[d] + 2 + k] += t
                row[p + n_x] = -1.0
                rows.append(row / cfg.noise_sigma_m)
                rhs.append(-o.lateral_m[i] / cfg.noise_sigma_m)
            n_x += 1
    phi = np.exp(-cfg.knot_spacing_m / cfg.correlation_length_m)
    for d in ids:
        c0, nk = col[d], model.drives[d].drift_m.size
        row = np.zeros(width)
        row[c0] = 1.0 / cfg.bias_sigma_m
        rows.append(row)
        row = np.zeros(width)
        row[c0 + 1] = 1.0 / cfg.drift_sigma_m
        rows.append(row)
        for k in range(nk - 1):
            row = np.zeros(width)
            scale = 1.0 / (cfg.drift_sigma_m * np.sqrt(1 - phi**2))
            row[c0 + 2 + k] = scale
            row[c0 + 1 + k] = -phi * scale
            rows.append(row)
        rhs += [0.0] * (nk + 1)
    jac = np.array(rows)[:, : p + n_x]
    sol, *_ = np.linalg.lstsq(jac, np.array(rhs), rcond=None)
    cov = np.linalg.inv(jac.T @ jac)[:p, :p]
    for d in ids:
        cur, c0 = model.drives[d], col[d]
        np.testing.assert_allclose(cur.bias_m, sol[c0], atol=1e-8)
        np.testing.assert_allclose(cur.drift_m, sol[c0 + 1 : c0 + 1 + cur.drift_m.size], atol=1e-8)
        np.testing.assert_allclose(cur.var_bias, cov[c0, c0], rtol=1e-6)
        np.testing.assert_allclose(cur.var_drift, np.diag(cov)[c0 + 1 : c0 + 1 + cur.drift_m.size], rtol=1e-6)
        # std at a knot = sqrt(var(b) + var(g_k) + 2 cov(b, g_k))
        s_knot = (cur.k0 + 1) * cfg.knot_spacing_m
        want = np.sqrt(cov[c0, c0] + cov[c0 + 2, c0 + 2] + 2 * cov[c0, c0 + 2])
        np.testing.assert_allclose(model.std(d, np.array([s_knot])), [want], rtol=1e-6)


# --------------------------------------------------------------------------------------------
# Model object
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_model():
    obs, truth = simulate_step_observations(config=SMALL, seed=0)
    return obs, truth, adjust_offsets(obs)


def test_json_round_trip(small_model):
    _, _, model = small_model
    back = OffsetModel.from_dict(json.loads(json.dumps(model.to_dict())))
    s = np.linspace(-500.0, 6000.0, 50)
    for d in model.drives:
        np.testing.assert_allclose(back.offset(d, s), model.offset(d, s), atol=1e-12)
        np.testing.assert_allclose(back.std(d, s), model.std(d, s), atol=1e-12)
    assert back.stats["n_samples_used"] == model.stats["n_samples_used"]


def test_from_dict_rejects_malformed():
    with pytest.raises(ConfigError, match="offset model"):
        OffsetModel.from_dict({"format": "something else"})
    with pytest.raises(ConfigError, match="malformed"):
        OffsetModel.from_dict({"format": "hdmap.offset_model", "drives": {"a": {"k0": 1}}})


def test_unknown_drive_and_extrapolation(small_model):
    _, truth, model = small_model
    prior = np.hypot(model.bias_sigma_m, model.drift_sigma_m)
    np.testing.assert_array_equal(model.offset("no such drive", np.array([0.0, 10.0])), [0.0, 0.0])
    np.testing.assert_allclose(model.std("no such drive", np.array([5.0])), [prior])
    d = truth.drive_ids[0]
    cur = model.drives[d]
    s_end = (cur.k0 + cur.drift_m.size - 1) * model.knot_spacing_m
    far = np.array([s_end, s_end + 1000.0, s_end + 1e6])
    o = model.offset(d, far)
    # beyond the last knot the drift decays towards 0 (Gauss-Markov prediction), the bias stays
    np.testing.assert_allclose(o[1] - cur.bias_m, (o[0] - cur.bias_m) * np.exp(-1.0), rtol=1e-9)
    np.testing.assert_allclose(o[2], cur.bias_m, atol=1e-9)
    sd = model.std(d, far)
    assert sd[0] < sd[1] < sd[2] <= prior
    inside = np.linspace(cur.k0 * model.knot_spacing_m, s_end, 40)
    assert np.all(model.std(d, inside) < 0.5 * prior)


def test_offset_shape_follows_input(small_model):
    _, truth, model = small_model
    s = np.full((3, 4), 1000.0)
    assert model.offset(truth.drive_ids[1], s).shape == (3, 4)
    assert model.std(truth.drive_ids[1], s).shape == (3, 4)


@pytest.mark.slow
def test_std_is_roughly_calibrated():
    # Over several seeds, the common error divided by the posterior std of a drive crossing the
    # step is of order 1 (not 0.1, not 10): the std is a usable lateral uncertainty.
    z = []
    for seed in range(4):
        obs, truth = simulate_step_observations(config=SMALL, seed=10 + seed)
        model = adjust_offsets(obs)
        for o in obs[::10]:
            d, s = o.drive_ids[0], np.array([o.drive_s_m[0]])
            z.append((model.offset(d, s)[0] - truth.true_correction(d, s)[0]) / model.std(d, s)[0])
    rms_z = float(np.sqrt(np.mean(np.square(z))))
    print(f"error / posterior std: rms {rms_z:.2f} over {len(z)} steps")
    assert 0.4 < rms_z < 2.0


# --------------------------------------------------------------------------------------------
# Bad input and settings
# --------------------------------------------------------------------------------------------


def _step(idx, ids, s, lat, cl):
    return StepObservations(
        pivot_id="p",
        index=idx,
        midpoint=np.zeros(2),
        heading=0.0,
        drive_ids=tuple(ids),
        drive_s_m=np.asarray(s, float),
        lateral_m=np.asarray(lat, float),
        types=np.ones(len(ids), dtype=np.int64),
        cluster=np.asarray(cl),
    )


def test_bad_steps_are_skipped_and_named(small_model):
    obs, _, good = small_model
    bad = [
        _step(9001, ["a", "b"], [1.0], [0.0, 1.0], [0, 0]),  # length mismatch
        _step(9002, ["a", "b"], [1.0, 2.0], [0.0, 1.0], [0.0, 0.0]),  # float labels
    ]
    nan_step = _step(9003, [obs[0].drive_ids[0], obs[0].drive_ids[-1]], [np.nan, 5.0], [0.0, np.inf], [0, 0])
    model = adjust_offsets(list(obs) + bad + [nan_step])
    assert model.stats["n_steps_skipped"] == 2
    assert any("9001" in p and "lengths differ" in p for p in model.stats["problems"])
    assert any("9002" in p and "integer" in p for p in model.stats["problems"])
    assert model.stats["n_nonfinite_dropped"] == 2
    for d in good.drives:
        np.testing.assert_allclose(model.offset(d, np.array([1000.0])), good.offset(d, np.array([1000.0])))


def test_feature_type_members_are_accepted_as_types(small_model):
    obs, _, a = small_model
    as_enum = [replace(o, types=np.array([FeatureType(int(x)) for x in o.types], dtype=object)) for o in obs]
    b = adjust_offsets(as_enum)
    assert b.stats["n_steps_skipped"] == 0
    d = next(iter(a.drives))
    np.testing.assert_allclose(b.offset(d, np.array([1000.0])), a.offset(d, np.array([1000.0])))


def test_nothing_usable_gives_an_empty_model():
    lonely = [
        _step(0, ["a", "b"], [1.0, 2.0], [0.0, 3.0], [0, 1]),  # each cluster has one drive
        _step(1, ["a", "b"], [3.0, 4.0], [0.0, 0.1], [-1, -1]),  # outliers only
    ]
    for obs in ([], lonely):
        model = adjust_offsets(obs)
        assert model.drives == {}
        assert model.stats["n_samples_used"] == 0
        np.testing.assert_array_equal(model.offset("a", np.array([1.0])), [0.0])


def test_inputs_are_not_mutated():
    obs, _ = simulate_step_observations(config=SMALL, seed=4)
    before = [(o.drive_s_m.copy(), o.lateral_m.copy(), o.cluster.copy()) for o in obs]
    adjust_offsets(obs, config=former(AdjustConfig, loss="cauchy"))
    for o, (s, lat, cl) in zip(obs, before):
        np.testing.assert_array_equal(o.drive_s_m, s)
        np.testing.assert_array_equal(o.lateral_m, lat)
        np.testing.assert_array_equal(o.cluster, cl)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"knot_spacing_m": 0.0},
        {"bias_sigma_m": -1.0},
        {"drift_sigma_m": -0.1},
        {"noise_sigma_m": float("nan")},
        {"loss": "tukey"},
        {"iterations": 0},
    ],
)
def test_config_rejects_bad_values(kwargs):
    with pytest.raises(ConfigError, match=next(iter(kwargs)) if "loss" not in kwargs else "loss"):
        former(AdjustConfig, **kwargs)


def test_std_skipped_above_limit(small_model):
    obs, truth, _ = small_model
    model = adjust_offsets(obs, config=former(AdjustConfig, std_max_unknowns=10))
    assert model.stats["std_computed"] is False
    d = truth.drive_ids[0]
    assert np.isnan(model.std(d, np.array([1000.0]))).all()
    assert np.isfinite(model.offset(d, np.array([1000.0]))).all()
    json.dumps(model.to_dict())  # NaN variances are written as null


def test_dense_steps_are_thinned_for_the_fit():
    from hdmap_core.pipeline import adjustment_assoc as assoc

    def step(idx, n):
        ids = [f"d{i}" for i in range(n)]
        return _step(idx, ids, np.full(n, 10.0 * idx), np.zeros(n), np.zeros(n, dtype=np.int64))

    # steps 0-3 seen by 3 drives, steps 4-9 by 8: with thin_drives=4 the dense ones are used
    # every ceil(8 / 4) = 2nd step
    obs = [step(i, 3) for i in range(4)] + [step(i, 8) for i in range(4, 10)]
    pool = assoc.gather(obs, {})
    used = np.unique(pool.step[assoc.select(pool, pool.label, thin_drives=4).pool_index])
    np.testing.assert_array_equal(used, [0, 1, 2, 3, 4, 6, 8])
    every = np.unique(pool.step[assoc.select(pool, pool.label).pool_index])
    np.testing.assert_array_equal(every, np.arange(10))


def test_lane_shift_search_in_chunks_is_the_one_chunk_result(monkeypatch):
    """The shift search scores its samples in chunks (bounded memory): the same model, bit for bit."""
    import hdmap_core.pipeline.adjustment_assoc as assoc  # noqa: PLC0415

    sim = replace(SMALL, line_offsets_m=(-3.5, 0.0, 3.5), line_types=(2, 2, 2))
    obs, _ = simulate_step_observations(config=sim, seed=8)
    monkeypatch.setattr(assoc, "SHIFT_CHUNK_SAMPLES", 10**9)
    one = adjust_offsets(obs)
    monkeypatch.setattr(assoc, "SHIFT_CHUNK_SAMPLES", 37)
    chunked = adjust_offsets(obs)
    assert one.stats["n_samples_used"] > 37 * 10  # many chunks
    assert sorted(one.drives) == sorted(chunked.drives) and one.drives
    for d, cur in one.drives.items():
        other = chunked.drives[d]
        assert cur.k0 == other.k0 and cur.bias_m == other.bias_m and np.array_equal(cur.drift_m, other.drift_m)


def test_nearest_centre_lookup_in_chunks_is_the_one_chunk_result(monkeypatch):
    """The re-association looks its samples up in chunks (bounded memory): the same labels."""
    import hdmap_core.pipeline.adjustment_assoc as assoc  # noqa: PLC0415

    obs, _ = simulate_step_observations(config=SMALL, seed=4)
    pool = assoc.gather(obs, {})
    cen = assoc.centres(pool, pool.label, pool.lateral_m)
    assert cen is not None
    v = pool.lateral_m + np.random.default_rng(0).normal(0.0, 0.5, pool.s_m.size)
    one = assoc.nearest(cen, pool.step, pool.ftype, v)
    monkeypatch.setattr(assoc, "NEAREST_CHUNK_SAMPLES", 1000)
    chunked = assoc.nearest(cen, pool.step, pool.ftype, v)
    assert pool.s_m.size > 10 * 1000  # many chunks
    assert (one[0] != pool.label).any() and (one[0] == pool.label).any()  # the noise moved some
    np.testing.assert_array_equal(one[0], chunked[0])
    np.testing.assert_array_equal(one[1], chunked[1])
