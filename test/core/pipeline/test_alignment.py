"""Tests of the Sec. IV-B EM offset estimation (alignment.py)."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
from sklearn.metrics import silhouette_samples

from hdmap_core.errors import ConfigError
from hdmap_core.model import FeatureType
from hdmap_core.pipeline.alignment import (
    AlignmentConfig,
    align_step,
    align_steps_gap,
    cluster_type,
    kmeans_1d_all_k,
    recheck_offsets,
    register_drives,
    silhouette_samples_1d,
    solve_offsets,
    step_silhouette,
)

from former_configs import former, former_replace

LINES = np.array([-5.25, -1.75, 1.75, 5.25])
LINE_TYPES = np.array([FeatureType.SOLID, FeatureType.DASHED, FeatureType.DASHED, FeatureType.SOLID])


def _step(offsets, *, lines=LINES, types=LINE_TYPES, noise=0.0, seed=0):
    """Samples of drives each seeing every line, drive d shifted by offsets[d]."""
    rng = np.random.default_rng(seed)
    offsets = np.asarray(offsets, float)
    lat = (lines[None, :] + offsets[:, None]).ravel() + rng.normal(0, noise, len(offsets) * len(lines))
    drive = np.repeat(np.arange(len(offsets)), len(lines))
    return lat, np.tile(types, len(offsets)), drive


def _sse(x, bounds):
    return sum(((x[a:b] - x[a:b].mean()) ** 2).sum() for a, b in zip(bounds[:-1], bounds[1:]))


def test_kmeans_dp_is_optimal():
    rng = np.random.default_rng(5)
    x = np.sort(rng.normal(0, 1, 11) + np.repeat([0, 4, 9], [4, 4, 3]))
    parts = kmeans_1d_all_k(x, 4)
    assert len(parts) == 4  # k = 1..4
    for k, b in enumerate(parts, start=1):
        assert len(b) == k + 1
        best = min(_sse(x, (0, *c, len(x))) for c in itertools.combinations(range(1, len(x)), k - 1))
        assert _sse(x, b) == pytest.approx(best)


def test_silhouette_matches_sklearn():
    rng = np.random.default_rng(2)
    x = rng.normal(0, 1, 30)
    lab = rng.integers(0, 3, 30)
    np.testing.assert_allclose(silhouette_samples_1d(x, lab), silhouette_samples(x[:, None], lab), atol=1e-12)


def test_cluster_type_picks_k_by_silhouette_and_gap():
    x = np.array([0.0, 0.1, -0.1, 3.5, 3.6, 3.4, 7.0, 7.1])
    for method in ("silhouette", "gap"):
        lab = cluster_type(x, method=method, k_max=6, single_cluster_silhouette=0.5, gap_split_m=1.0)
        np.testing.assert_array_equal(lab, [0, 0, 0, 1, 1, 1, 2, 2])
    single = cluster_type(
        np.array([0.0, 0.05, 0.1, 0.15, 0.2]),
        method="silhouette",
        k_max=4,
        single_cluster_silhouette=0.7,
        gap_split_m=1.0,
    )
    assert np.all(single == 0)


@pytest.mark.parametrize("solver", ["lm", "closed_form"])
def test_offsets_recovered_exactly_noise_free(solver):
    # 5 drives each seeing 3 lines, shifted by known amounts.
    shifts = np.array([0.6, -0.9, 0.25, 1.1, -0.4])
    lat, types, drive = _step(shifts, lines=np.array([-5.25, -1.75, 1.75]), types=np.array([3, 2, 2]))
    cfg = former(AlignmentConfig, solver=solver, ridge=1e-9, min_cluster_separation_m=2.0)
    res = align_step(lat, types, drive, config=cfg)
    assert res.valid
    assert res.silhouette > 0.99
    # Correction = -shift up to the common gauge (drift removal fixes the mean).
    corr = res.offsets_m
    np.testing.assert_allclose(corr - corr.mean(), -(shifts - shifts.mean()), atol=1e-5)
    # Corrected samples collapse onto the lines (shifted by the mean shift).
    x = lat + corr[drive]
    for c in np.unique(res.labels):
        assert np.ptp(x[res.labels == c]) < 1e-4


def test_robust_loss_resists_one_bad_sample():
    shifts = np.array([0.5, -0.5, 0.3, -0.3, 0.0, 0.2])
    lat, types, drive = _step(shifts, noise=0.02, seed=1)
    lat = lat.copy()
    lat[0] += 0.8  # drive 0 sees one line 0.8 m off
    plain = align_step(lat, types, drive, config=former(AlignmentConfig, solver="closed_form"))
    robust = align_step(
        lat, types, drive, config=former(AlignmentConfig, solver="closed_form", robust_loss=True, huber_delta_m=0.1)
    )
    err_plain = abs((plain.offsets_m - plain.offsets_m.mean())[0] + (shifts[0] - shifts.mean()))
    err_robust = abs((robust.offsets_m - robust.offsets_m.mean())[0] + (shifts[0] - shifts.mean()))
    assert err_robust < 0.5 * err_plain


@pytest.mark.parametrize("seed", range(5))
def test_silhouette_gate_rejects_pure_noise(seed):
    # 3 drives x 40 samples of one type, no lines at all: a Gaussian blob of noise.
    rng = np.random.default_rng(seed)
    lat = rng.normal(0.0, 2.0, 120)
    res = align_step(
        lat, np.full(120, 2), np.repeat(np.arange(3), 40), config=former(AlignmentConfig, solver="closed_form")
    )
    assert res.silhouette < 0.67
    assert not res.valid


def test_prior_offsets_and_gap_clustering():
    shifts = np.array([0.7, -0.8, 0.4, -0.3])
    lat, types, drive = _step(shifts, noise=0.01)
    prior = -shifts + 0.05  # previous step's offsets, nearly right
    cfg = former(AlignmentConfig, clustering="auto", solver="closed_form", prior_weight=1.0, remove_drift=False)
    res = align_step(lat, types, drive, config=cfg, prior=prior)
    assert res.valid
    np.testing.assert_allclose(res.offsets_m, -shifts, atol=0.08)


def test_no_offsets_when_estimation_off():
    lat, types, drive = _step([0.3, -0.3, 0.1])
    res = align_step(lat, types, drive, config=former(AlignmentConfig, estimate_offsets=False))
    np.testing.assert_array_equal(res.offsets_m, 0.0)


def test_solve_offsets_ignores_dropped_samples():
    lat, types, drive = _step([0.2, -0.2])
    labels = np.tile([0, 1, 2, 3], 2)
    labels[0] = -1
    o = solve_offsets(lat, labels, types, drive, 2, config=former(AlignmentConfig, solver="closed_form", ridge=1e-9))
    assert o[0] - o[1] == pytest.approx(-0.4, abs=1e-6)


def test_config_checks():
    with pytest.raises(ConfigError):
        former(AlignmentConfig, clustering="dbscan")
    with pytest.raises(ConfigError):
        former(AlignmentConfig, solver="adam")


def test_fast_silhouette_equals_sklearn_per_type():
    rng = np.random.default_rng(4)
    x = np.concatenate(
        [rng.normal(0, 0.2, 10), rng.normal(3.5, 0.3, 8), rng.normal(1.0, 0.2, 7), rng.normal(9, 0.2, 5)]
    )
    types = np.repeat([1, 1, 2, 2], [10, 8, 7, 5])
    labels = np.repeat([0, 1, 2, 3], [10, 8, 7, 5])
    want = np.concatenate(
        [silhouette_samples(x[:18, None], labels[:18]), silhouette_samples(x[18:, None], labels[18:])]
    )
    assert step_silhouette(x, labels, types) == pytest.approx(want.mean())
    # A type with a single cluster does not count.
    x2 = np.concatenate([x, [20.0, 20.1]])
    assert step_silhouette(x2, np.concatenate([labels, [4, 4]]), np.concatenate([types, [3, 3]])) == pytest.approx(
        want.mean()
    )


def _road_step(errors, *, seed=0, noise=0.03):
    """A step of a 3-lane road: drive d sees every line shifted by errors[d] (+ noise)."""
    rng = np.random.default_rng(seed)
    lines = np.array([-6.5, -5.25, -1.75, 1.75, 5.25, 6.5])
    ltypes = np.array([3, 1, 2, 2, 1, 3])
    lat, types, drive = [], [], []
    for d, e in enumerate(errors):
        lat.append(lines + e + rng.normal(0, noise, len(lines)))
        types.append(ltypes)
        drive.append(np.full(len(lines), d))
    return np.concatenate(lat), np.concatenate(types), np.concatenate(drive)


def test_register_drives_without_prior_recovers_large_errors():
    errors = np.array([0.0, 1.9, -2.2, 0.7, -1.2, 2.6])  # several beyond half a lane (1.75 m)
    lat, types, drive = _road_step(errors)
    o = register_drives(lat, types, drive, len(errors), max_offset_m=5.0, gap_m=1.0)
    np.testing.assert_allclose(o - o[0], -(errors - errors[0]), atol=0.15)


def test_recheck_moves_a_lane_locked_drive_back():
    errors = np.array([0.3, -0.4, 0.1, 0.5, -0.2, 0.0, 0.2])
    lat, types, drive = _road_step(errors, seed=3)
    good = -errors
    locked = good.copy()
    locked[2] += 3.5  # drive 2 tracked one lane off: its dashed lines sit on the others' dashed
    o = recheck_offsets(lat, types, drive, locked, max_offset_m=5.0, gap_m=1.0)
    np.testing.assert_allclose(o, good, atol=0.1)
    # Drives in the right place stay exactly where they are.
    np.testing.assert_array_equal(np.delete(o, 2), np.delete(locked, 2))


def test_tracked_step_with_prior_and_new_drive():
    errors = np.array([0.3, -0.4, 0.1, 0.5, -0.2, 1.8])
    lat, types, drive = _road_step(errors, seed=5)
    prior = -errors.copy()
    prior[5] = np.nan  # a drive that just joined
    cfg = former(AlignmentConfig, clustering="auto", solver="closed_form", prior_weight=1.0, remove_drift=False)
    res = align_step(lat, types, drive, config=cfg, prior=prior)
    assert res.valid
    np.testing.assert_allclose(res.offsets_m, -errors, atol=0.08)


def test_lone_clusters_accepted_only_when_asked_and_tight():
    # Two drives on a ramp, each seeing one solid and one border: no type has two clusters.
    lat = np.array([-1.8, 1.7, -1.75, 1.75])
    types = np.array([1, 3, 1, 3])
    drive = np.array([0, 0, 1, 1])
    paper = align_step(lat, types, drive, config=former(AlignmentConfig, solver="closed_form"))
    assert paper.silhouette == -1.0 and not paper.valid
    lone = align_step(
        lat, types, drive, config=former(AlignmentConfig, solver="closed_form", lone_cluster_max_std_m=0.3)
    )
    assert lone.valid
    wide = np.array([-2.6, 1.7, -1.0, 1.75])  # the solid samples disagree by 1.6 m
    res = align_step(
        wide, types, drive, config=former(AlignmentConfig, estimate_offsets=False, lone_cluster_max_std_m=0.3)
    )
    assert not res.valid


def test_one_drive_alone_accepted_when_asked():
    # One drive seeing two dashed lines, two solids and a border: every cluster is a singleton,
    # so the silhouette is 0 and the paper's gate rejects the step; lone_cluster_max_std_m
    # accepts it (nothing to align, every cluster tight).
    lat = np.array([-5.2, -1.75, 1.75, 5.2, 6.3])
    types = np.array([1, 2, 2, 1, 3])
    drive = np.zeros(5, dtype=np.int64)
    gap = former(AlignmentConfig, clustering="gap", solver="closed_form")
    paper = align_step(lat, types, drive, config=gap)
    assert paper.silhouette == 0.0 and not paper.valid
    lone = align_step(lat, types, drive, config=former_replace(gap, lone_cluster_max_std_m=0.3))
    assert lone.valid
    assert len(np.unique(lone.labels[lone.labels >= 0])) == 5
    # Two drives half a lane apart: singleton clusters too, but the silhouette decides as before.
    two = align_step(
        np.r_[lat, lat + 1.75],
        np.r_[types, types],
        np.r_[drive, drive + 1],
        config=former_replace(gap, estimate_offsets=False, lone_cluster_max_std_m=0.3),
    )
    assert two.silhouette < 0.67 and not two.valid


# Sparse-step rule: two drives on a 3-lane road (borders, solids, two dashed lines).
_SPARSE_LINES = np.array([-6.5, -5.25, -1.75, 1.75, 5.25, 6.5])
_SPARSE_TYPES = np.array([3, 1, 2, 2, 1, 3])
_SPARSE = former(
    AlignmentConfig, clustering="gap", solver="closed_form", sparse_step_max_drives=2, sparse_step_max_std_m=0.3
)


def _two_drive_step(seen0, seen1, *, shift=0.4, err=None):
    """Drive 0 sees lines ``seen0`` where they are, drive 1 lines ``seen1`` shifted by ``shift``
    plus a per-line error ``err`` (indexed like the lines)."""
    err = np.zeros(len(_SPARSE_LINES)) if err is None else np.asarray(err, float)
    lat = np.r_[_SPARSE_LINES[seen0], _SPARSE_LINES[seen1] + shift + err[seen1]]
    types = np.r_[_SPARSE_TYPES[seen0], _SPARSE_TYPES[seen1]]
    drive = np.r_[np.zeros(len(seen0), np.int64), np.ones(len(seen1), np.int64)]
    return lat, types, drive


def test_sparse_step_with_lines_one_drive_misses_accepted_only_with_the_rule():
    # Both see the two dashed lines; drive 0 also the left solid and border, drive 1 the right
    # ones: four singletons (silhouette 0) pull the mean below 0.67 though every cluster is tight.
    err = [0, 0, 0.05, -0.05, 0, 0]
    lat, types, drive = _two_drive_step([0, 1, 2, 3], [2, 3, 4, 5], err=err)
    paper = align_step(lat, types, drive, config=replace(_SPARSE, sparse_step_max_drives=0))
    assert paper.silhouette < 0.67 and not paper.valid
    res = align_step(lat, types, drive, config=_SPARSE)
    assert res.valid and res.silhouette == pytest.approx(paper.silhouette)
    # The offsets come from the shared lines: drive 1 is moved back onto drive 0.
    assert res.offsets_m[1] - res.offsets_m[0] == pytest.approx(-0.4, abs=1e-3)
    assert len(np.unique(res.labels)) == 6 and np.all(res.labels >= 0)
    # A third drive makes the step no longer sparse (limit 2 drives), a limit of 3 covers it.
    lat3 = np.r_[lat, _SPARSE_LINES[[2, 3]] - 0.2]
    types3, drive3 = np.r_[types, _SPARSE_TYPES[[2, 3]]], np.r_[drive, [2, 2]]
    assert not align_step(lat3, types3, drive3, config=_SPARSE).valid
    assert align_step(lat3, types3, drive3, config=replace(_SPARSE, sparse_step_max_drives=3)).valid


def test_sparse_step_of_singletons_and_one_shared_cluster_accepted_with_the_option():
    """Two drives (carla_town06_30_s2, x 360 m, final pass, samples already shifted): both see
    the border 0.2 m apart; drive 0 sees a solid line at -6.3 m, drive 1 dashed lines at -2.9
    and 7.5 m; at 0.5 m and 4.1 m they disagree on the type (solid/dashed side by side, dropped
    as type clashes). Every type with two clusters holds only singletons, so the silhouette
    without singletons is undefined (-1) and the sparse-step rule rejected the step: 40 such
    steps in a row left 80 m of road unmapped. With ``sparse_singletons_accept`` it is judged like
    a lone-cluster step (every cluster tight) when some cluster is shared by both drives."""
    lat = np.array([-7.69, -7.47, -6.33, -2.94, 0.43, 0.54, 4.08, 4.12, 7.52])
    B, S, D = int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID), int(FeatureType.DASHED)
    types = np.array([B, B, S, D, S, D, D, S, D])
    drive = np.array([1, 0, 0, 1, 1, 0, 1, 0, 1])
    cfg = former(
        AlignmentConfig,
        clustering="gap",
        estimate_offsets=False,
        sparse_step_max_drives=3,
        sparse_step_max_std_m=0.3,
        sparse_type_clash_m=1.0,
        lone_cluster_max_std_m=0.3,
    )
    old = align_step(lat, types, drive, config=cfg)
    assert not old.valid and old.silhouette == pytest.approx(0.0)
    res = align_step(lat, types, drive, config=former_replace(cfg, sparse_singletons_accept=True))
    assert res.valid
    assert np.all(res.labels[[4, 5, 6, 7]] == -1)  # the clashing pairs stay dropped
    assert res.labels[0] == res.labels[1] >= 0 and np.all(res.labels[[2, 3, 8]] >= 0)
    # No cluster shared by the two drives (the border seen by drive 0 only): nothing ties them,
    # the step stays rejected.
    lone = np.ones(len(lat), dtype=bool)
    lone[0] = False
    assert not align_step(
        lat[lone], types[lone], drive[lone], config=former_replace(cfg, sparse_singletons_accept=True)
    ).valid
    # A loose shared cluster (border 0.8 m apart) is no agreement either.
    far = lat.copy()
    far[0] = -8.27
    assert not align_step(far, types, drive, config=former_replace(cfg, sparse_singletons_accept=True)).valid


def test_type_clash_kept_as_a_line_of_unknown_type_with_the_option():
    """The step above: the two drives place lines at 0.5 m and 4.1 m within 0.11 m but disagree
    on solid/dashed. Dropping both samples left a hole in both lines wherever one drive
    misclassified a stretch; with ``sparse_type_clash_keep`` each pair becomes one cluster of
    type UNKNOWN (its type is decided along the polyline), everything else unchanged."""
    lat = np.array([-7.69, -7.47, -6.33, -2.94, 0.43, 0.54, 4.08, 4.12, 7.52])
    B, S, D, U = (int(t) for t in (FeatureType.ROAD_BORDER, FeatureType.SOLID, FeatureType.DASHED, FeatureType.UNKNOWN))
    types = np.array([B, B, S, D, S, D, D, S, D])
    drive = np.array([1, 0, 0, 1, 1, 0, 1, 0, 1])
    cfg = former(
        AlignmentConfig,
        clustering="gap",
        estimate_offsets=False,
        sparse_step_max_drives=3,
        sparse_step_max_std_m=0.3,
        sparse_type_clash_m=1.0,
        lone_cluster_max_std_m=0.3,
        sparse_singletons_accept=True,
    )
    old = align_step(lat, types, drive, config=cfg)
    assert old.types is None
    res = align_step(lat, types, drive, config=former_replace(cfg, sparse_type_clash_keep=True))
    assert res.valid == old.valid and res.silhouette == old.silhouette
    kept = res.labels >= 0
    assert np.array_equal(res.labels[old.labels >= 0], old.labels[old.labels >= 0])
    assert (
        res.labels[4] == res.labels[5] >= 0 and res.labels[6] == res.labels[7] >= 0 and res.labels[4] != res.labels[6]
    )
    assert not set(res.labels[[4, 6]].tolist()) & set(old.labels[old.labels >= 0].tolist())  # clusters of their own
    assert np.array_equal(res.types[[4, 5, 6, 7]], [U, U, U, U])
    assert np.array_equal(np.delete(res.types, [4, 5, 6, 7]), np.delete(types, [4, 5, 6, 7])) and kept.all()
    # A third drive agreeing with drive 1 (solid at 0.35 m): the solid line has two drives,
    # drive 0's dashed sample there is a dropped singleton of no unknown line; the other pair
    # is still kept as unknown.
    lat3, types3, drive3 = np.r_[lat, 0.35], np.r_[types, S], np.r_[drive, 2]
    res3 = align_step(lat3, types3, drive3, config=former_replace(cfg, sparse_type_clash_keep=True))
    assert res3.valid
    assert res3.labels[5] == -1 and res3.labels[4] == res3.labels[9] >= 0
    assert res3.types[4] == S and res3.types[6] == res3.types[7] == U
    # A marking against a border is a clash too (drive 0 reports the line at 4.1 m as a border):
    # kept as unknown, its type decided along the polyline (never a border there).
    types4 = types.copy()
    types4[7] = B
    res4 = align_step(lat, types4, drive, config=former_replace(cfg, sparse_type_clash_keep=True))
    assert res4.labels[6] == res4.labels[7] >= 0 and np.all(res4.types[[4, 5, 6, 7]] == U)
    # Only the default preset's final pass keeps clashes (the first pass feeds the adjustment).
    from hdmap_core.pipeline import presets

    default = presets.preset("default")
    assert default.final_alignment.sparse_type_clash_keep and not default.alignment.sparse_type_clash_keep
    assert not former(AlignmentConfig).sparse_type_clash_keep
    for name in ("paper", "naive"):
        p = presets.preset(name)
        assert not p.alignment.sparse_type_clash_keep
        assert p.final_pass is None


def test_four_drive_step_judged_by_the_sparse_rule_clash_drop_only_up_to_three():
    """Four drives (carla_town06_30_s1, x -86 m, final pass, samples shifted): every line is
    tight (pairs within 0.2 m), but drive 0 takes the second line for solid, drive 3 the fourth,
    and drive 1 alone sees the right edge line: five singletons pull the silhouette to 0.64 and
    the step was rejected (50 m of a road with 4 drives unmapped). Judged by the sparse-step
    rule (sparse_step_max_drives 4) it is accepted. The type-clash drop, limited to steps of <= 3
    drives (sparse_type_clash_max_drives), keeps the clashing singletons here; without the limit
    they are dropped."""
    B, S, D = int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID), int(FeatureType.DASHED)
    lat = np.array([-7.55, -6.46, -6.38, -6.28, -2.95, -2.84, -2.78, 0.50, 0.69, 0.70, 4.08, 4.09, 7.50])
    types = np.array([B, S, S, S, D, D, S, D, D, D, S, D, S])
    drive = np.array([0, 2, 0, 3, 2, 3, 0, 3, 2, 0, 3, 1, 1])
    cfg = former(
        AlignmentConfig,
        clustering="gap",
        estimate_offsets=False,
        sparse_step_max_drives=3,
        sparse_step_max_std_m=0.3,
        sparse_type_clash_m=1.0,
        lone_cluster_max_std_m=0.3,
        sparse_singletons_accept=True,
    )
    old = align_step(lat, types, drive, config=cfg)
    assert not old.valid and 0.6 < old.silhouette < 0.67
    four = former_replace(cfg, sparse_step_max_drives=4, sparse_type_clash_max_drives=3)
    res = align_step(lat, types, drive, config=four)
    assert res.valid and np.all(res.labels >= 0)
    dropped = align_step(lat, types, drive, config=former_replace(four, sparse_type_clash_max_drives=0))
    assert dropped.labels[6] == -1 and dropped.labels[10] == -1 and dropped.labels[11] == -1


def test_sparse_step_rule_rejects_loose_clusters():
    # Same layout, but the drives disagree on the dashed lines by 0.7 m in opposite directions:
    # no offset makes both pairs tight (std 0.35 m), though they are far apart (silhouette > 0.67).
    lat, types, drive = _two_drive_step([0, 1, 2, 3], [2, 3, 4, 5], shift=0.0, err=[0, 0, 0.7, -0.7, 0, 0])
    res = align_step(lat, types, drive, config=_SPARSE)
    assert not res.valid
    assert len(np.unique(res.labels)) == 6  # each dashed pair is one cluster
    assert step_silhouette(lat + res.offsets_m[drive], res.labels, types, skip_singletons=True) >= 0.67
    # The std limit is what rejects it: a limit above 0.35 m accepts the step.
    assert align_step(lat, types, drive, config=replace(_SPARSE, sparse_step_max_std_m=0.4)).valid


def test_sparse_step_drops_a_type_clashing_singleton():
    # Both see all four lane lines, but drive 0 takes the left solid for dashed: a dashed and a
    # solid singleton 0.1 m apart.
    lat, types, drive = _two_drive_step([1, 2, 3, 4], [1, 2, 3, 4], shift=0.0)
    types = types.copy()
    types[0] = 2
    lat = lat.copy()
    lat[0] += 0.1
    keep = align_step(lat, types, drive, config=_SPARSE)
    assert keep.labels[0] >= 0 and keep.labels[4] >= 0
    res = align_step(lat, types, drive, config=former_replace(_SPARSE, sparse_type_clash_m=1.0))
    assert res.labels[0] == -1 and res.labels[4] == -1  # both singletons of the clash dropped
    assert np.all(res.labels[[1, 2, 3, 5, 6, 7]] >= 0) and res.valid
    # A singleton with no other type within 1 m stays: a border 1.25 m beside the solid.
    lat2, types2, drive2 = _two_drive_step([0, 1, 2, 3, 4], [1, 2, 3, 4], shift=0.0)
    res2 = align_step(lat2, types2, drive2, config=former_replace(_SPARSE, sparse_type_clash_m=1.0))
    assert res2.labels[0] >= 0 and res2.valid
    # One drive's own samples of two types close together are no clash (a line beside a border).
    lat4, types4, drive4 = _two_drive_step([0, 1, 2, 3], [1, 2, 3, 4], shift=0.0)
    lat4, types4, drive4 = np.r_[lat4, 6.0], np.r_[types4, 3], np.r_[drive4, 1]
    res4 = align_step(lat4, types4, drive4, config=former_replace(_SPARSE, sparse_type_clash_m=1.0))
    assert res4.labels[-2] >= 0 and res4.labels[-1] >= 0  # drive 1's solid at 5.25, border at 6.0
    assert res4.valid
    # ... but the same border seen by drive 0 clashes with drive 1's solid.
    res5 = align_step(lat4, types4, np.r_[drive4[:-1], 0], config=former_replace(_SPARSE, sparse_type_clash_m=1.0))
    assert res5.labels[-2] == -1 and res5.labels[-1] == -1
    # Steps with more drives than the limit keep their singletons.
    lat3 = np.r_[lat, _SPARSE_LINES[[2, 3]]]
    res3 = align_step(
        lat3, np.r_[types, 2, 2], np.r_[drive, 2, 2], config=former_replace(_SPARSE, sparse_type_clash_m=1.0)
    )
    assert res3.labels[0] >= 0 and res3.labels[4] >= 0


def test_sparse_step_config_checks():
    with pytest.raises(ConfigError):
        former(AlignmentConfig, sparse_step_max_drives=-1)
    with pytest.raises(ConfigError):
        former(AlignmentConfig, sparse_step_max_std_m=0.0)
    # The paper preset stays faithful; the default preset uses the rule in both passes, in the
    # final pass for steps of up to 4 drives (type-clash drop up to 3, as in the first pass).
    from hdmap_core.pipeline import presets

    assert presets.preset("paper").alignment.sparse_step_max_drives == 0
    default = presets.preset("default")
    assert default.alignment.sparse_step_max_drives == 3
    assert default.final_alignment.sparse_step_max_drives == 4
    assert default.final_alignment.sparse_type_clash_max_drives == default.alignment.sparse_step_max_drives


def _gap_final_config(**kw):
    return former(
        AlignmentConfig,
        clustering="gap",
        estimate_offsets=False,
        lone_cluster_max_std_m=0.3,
        sparse_step_max_drives=4,
        sparse_step_max_std_m=0.3,
        **kw,
    )


def test_align_steps_gap_equals_align_step_and_leaves_special_steps_out():
    rng = np.random.default_rng(11)
    cfg = _gap_final_config()
    steps, kinds = [], []
    for q in range(40):
        kind = q % 4
        if kind == 0:  # many drives, tight: valid
            lat, ty, dr = _step(rng.normal(0, 0.05, 8), noise=0.03, seed=q)
        elif kind == 1:  # many drives, noise: mostly rejected by the gate
            lat = rng.uniform(-6, 6, 40)
            ty, dr = rng.choice(LINE_TYPES, 40), rng.integers(0, 8, 40)
        elif kind == 2:  # sparse: left to align_step
            lat, ty, dr = _step(rng.normal(0, 0.05, 3), noise=0.03, seed=q)
        else:  # one cluster per type: silhouette undefined, left to align_step
            lat, ty, dr = _step(np.zeros(6), lines=LINES[:2], types=LINE_TYPES[:2], noise=0.02, seed=q)
        steps.append((lat, ty, dr + 100 * q))  # pivot-wide drive codes
        kinds.append(kind)
    ptr = np.concatenate([[0], np.cumsum([len(s[0]) for s in steps])])
    lat, ty, dr = (np.concatenate(v) for v in zip(*steps))
    out = align_steps_gap(lat, ty, dr, ptr, np.arange(len(steps)), config=cfg)
    assert set(out) == {q for q, k in enumerate(kinds) if k in (0, 1)}
    for q, al in out.items():
        x, t, d = steps[q]
        _, local = np.unique(d, return_inverse=True)
        ref = align_step(x, t, local, config=cfg)
        np.testing.assert_array_equal(al.labels, ref.labels)
        assert al.silhouette == pytest.approx(ref.silhouette, abs=1e-9)
        assert al.valid == ref.valid
        assert al.valid or kinds[q] == 1
        np.testing.assert_array_equal(al.offsets_m, np.zeros(len(np.unique(d))))
    assert not all(al.valid for al in out.values())  # the gate rejects noise here too


def test_align_steps_gap_needs_a_fixed_offset_config():
    with pytest.raises(ConfigError):
        align_steps_gap(
            np.zeros(2),
            np.zeros(2, int),
            np.zeros(2, int),
            np.array([0, 2]),
            np.array([0]),
            config=former(AlignmentConfig, clustering="gap"),
        )


def test_robust_loss_changes_nothing_without_outliers():
    # residuals within the Huber threshold: the weights stay 1, the robust solve is the plain one
    lat, ty, dr = _step([0.3, -0.2, 0.1], noise=0.02)
    labels = np.tile(np.arange(4), 3)
    plain = solve_offsets(lat, labels, ty, dr, 3, config=former(AlignmentConfig, solver="closed_form"))
    robust = solve_offsets(
        lat, labels, ty, dr, 3, config=former(AlignmentConfig, solver="closed_form", robust_loss=True)
    )
    np.testing.assert_allclose(robust, plain, atol=1e-12)


def test_sparse_step_of_two_drives_sharing_no_line_accepted_when_apart():
    """Two drives (carla_town04_30_s3, x 180-250 m, final pass, samples shifted) in different
    lanes: drive 1 sees the border and three lines on the right, drive 0 two lines on the left,
    none seen by both. Every cluster is a singleton and none is shared, so the step was rejected
    (35 steps in a row, 70 m unmapped) although each drive alone would pass the one-drive rule.
    With ``sparse_disjoint_apart_m`` it is accepted when no two samples of different drives lie
    closer than that (different lines, not one line the drives placed apart)."""
    B, S, D = int(FeatureType.ROAD_BORDER), int(FeatureType.SOLID), int(FeatureType.DASHED)
    lat = np.array([-9.05, -5.42, -1.97, 1.48, 4.99, 8.71])
    types = np.array([B, S, D, D, D, S])
    drive = np.array([1, 1, 1, 1, 0, 0])
    cfg = former(
        AlignmentConfig,
        clustering="gap",
        estimate_offsets=False,
        sparse_step_max_drives=4,
        sparse_step_max_std_m=0.3,
        sparse_type_clash_m=1.0,
        sparse_type_clash_max_drives=3,
        lone_cluster_max_std_m=0.3,
        sparse_singletons_accept=True,
    )
    assert former(AlignmentConfig).sparse_disjoint_apart_m == 0.0
    assert not align_step(lat, types, drive, config=cfg).valid
    on = former_replace(cfg, sparse_disjoint_apart_m=2.0)
    res = align_step(lat, types, drive, config=on)
    assert res.valid and np.all(res.labels >= 0) and len(np.unique(res.labels)) == 6
    # Each drive alone passes the one-drive rule either way.
    for d in (0, 1):
        assert align_step(lat[drive == d], types[drive == d], drive[drive == d] * 0, config=cfg).valid
    # The two drives disagree on the type of the one line both see (dropped as a clash): the
    # rest, 2+ m apart between the drives, is accepted (x -276 m: drive 0 border, dashed, solid,
    # dashed; drive 1 solid and the clashing solid).
    lat2 = np.array([-8.38, -4.87, -1.49, -1.37, 2.27, 5.57])
    types2 = np.array([B, S, D, S, S, D])
    drive2 = np.array([0, 1, 0, 1, 0, 0])
    assert not align_step(lat2, types2, drive2, config=cfg).valid
    res2 = align_step(lat2, types2, drive2, config=on)
    assert res2.valid and np.all(res2.labels[[2, 3]] == -1) and np.all(res2.labels[[0, 1, 4, 5]] >= 0)
    # Drive 0's line 1.5 m from drive 1's: one line placed apart (or a contradiction), rejected.
    near = lat.copy()
    near[4] = 2.98
    assert not align_step(near, types, drive, config=on).valid
    # A loose cluster (std > 0.3 m) is not accepted by the rule either.
    loose = np.r_[lat, 4.99 + 0.9]
    assert not align_step(loose, np.r_[types, D], np.r_[drive, 0], config=on).valid
    # Only the default preset's final pass uses the rule.
    from hdmap_core.pipeline import presets

    default = presets.preset("default")
    assert default.final_alignment.sparse_disjoint_apart_m == 2.0
    assert default.alignment.sparse_disjoint_apart_m == 0.0
    for name in ("paper", "naive"):
        p = presets.preset(name)
        assert p.alignment.sparse_disjoint_apart_m == 0.0
        assert p.final_pass is None


@pytest.mark.parametrize("n_drives, n_clusters", [(300, 8), (40, 3), (4, 6)])
def test_closed_form_solves_the_normal_equations(n_drives, n_clusters):
    # the rank-K (Woodbury) solve where K < D, the D x D one else: both the minimiser, i.e. the
    # solution of the full Hessian's system
    from hdmap_core.pipeline.alignment import _closed_form  # noqa: PLC0415 - a private helper

    rng = np.random.default_rng(n_drives)
    m_samples = 6 * n_drives
    drive = np.concatenate([np.arange(n_drives), rng.integers(0, n_drives, m_samples - n_drives)])
    labels = rng.integers(0, n_clusters, m_samples)
    x = labels * 3.5 + rng.normal(0.0, 0.2, n_drives)[drive] + rng.normal(0.0, 0.05, m_samples)
    w = rng.uniform(0.3, 1.0, m_samples)
    has_prior = rng.random(n_drives) < 0.7
    reg_w = 1e-4 + np.where(has_prior, 1.0, 0.0)
    reg_t = np.where(has_prior, rng.normal(0.0, 0.2, n_drives), 0.0)
    got = _closed_form(x, labels, drive, n_drives, w, reg_w, reg_t)
    # the Hessian/2 and gradient/2 of the documented cost, built sample by sample
    n_c = np.bincount(labels, minlength=n_clusters).astype(float)
    m = np.zeros((n_clusters, n_drives))
    xm = np.zeros((n_clusters, n_drives))
    np.add.at(m, (labels, drive), w)
    np.add.at(xm, (labels, drive), w * x)
    h = np.diag(reg_w).astype(float)
    g = np.zeros(n_drives)
    for c in range(n_clusters):
        wc = m[c].sum()
        h += (np.diag(m[c]) - np.outer(m[c], m[c]) / wc) / n_c[c]
        g += (xm[c] - xm[c].sum() * m[c] / wc) / n_c[c]
    np.testing.assert_allclose(got, np.linalg.solve(h, reg_w * reg_t - g), rtol=0, atol=1e-10)
