"""Tests of Sec. IV-C aggregation and the processed-stretch store (aggregation.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.model import FeatureType
from hdmap_core.pipeline.aggregation import (
    SINGLE_DRIVE_STD_M,
    AggregationConfig,
    ProcessedStore,
    aggregate_many,
    aggregate_step,
    gaussian_overlap,
    kde_maxima,
)

from former_configs import former


@pytest.mark.parametrize("factor", [0.5, 1.0, 6.0])
def test_kde_maximum_of_symmetric_cluster_is_its_centre(factor):
    centre = 2.37
    half = np.array([0.05, 0.12, 0.3, 0.31, 0.6])
    x = np.concatenate([centre - half, centre + half, [centre]])
    lab = np.zeros(len(x), dtype=np.int64)
    m = kde_maxima(x, lab, np.array([factor * x.std()]))
    assert m[0] == pytest.approx(centre, abs=1e-5)


def test_kde_maximum_is_the_mode_not_the_mean():
    # Eight samples at 0 +- 0.02, two outliers at 1.0: the mean moves, the mode stays.
    x = np.array([-0.02, -0.01, 0.0, 0.0, 0.01, 0.02, -0.015, 0.015, 1.0, 1.0])
    agg = aggregate_step(
        x,
        np.zeros(10, np.int64),
        np.full(10, 1),
        np.arange(10),
        config=former(AggregationConfig, kde_bandwidth_factor=0.3),
    )
    assert abs(agg.lateral_m[0]) < 0.02
    assert x.mean() > 0.19


def test_overlap_filter_drops_the_smaller_cluster():
    rng = np.random.default_rng(0)
    solid = rng.normal(1.75, 0.05, 12)
    dashed_misclassified = rng.normal(1.78, 0.05, 3)  # the same line seen as dashed by few drives
    other = rng.normal(-1.75, 0.05, 10)
    x = np.concatenate([solid, dashed_misclassified, other])
    labels = np.repeat([0, 1, 2], [12, 3, 10])
    types = np.repeat([FeatureType.SOLID, FeatureType.DASHED, FeatureType.DASHED], [12, 3, 10])
    drive = np.concatenate([np.arange(12), np.arange(3), np.arange(10)])
    cfg = former(AggregationConfig, kde_bandwidth_factor=1.0, overlap_threshold=0.5)
    agg = aggregate_step(x, labels, types, drive, config=cfg)
    np.testing.assert_array_equal(agg.kept_labels, [2, 0])
    np.testing.assert_array_equal(agg.types, [FeatureType.DASHED, FeatureType.SOLID])
    np.testing.assert_array_equal(agg.counts, [10, 12])
    off = aggregate_step(
        x, labels, types, drive, config=former(AggregationConfig, kde_bandwidth_factor=1.0, overlap_filter=False)
    )
    assert len(off.lateral_m) == 3


def _step(features):
    """One step from (position, type, drives) per feature; every drive's sample sits exactly on
    its feature, so each KDE maximum is the feature's position and each cluster's density the
    0.15 m minimum bandwidth normal (two such clusters d apart overlap 2 * Phi(-d / 0.3))."""
    labels = np.concatenate([np.full(n, c) for c, (_, _, n) in enumerate(features)])
    x = np.array([features[c][0] for c in labels])
    types = np.array([features[c][1] for c in labels])
    drive = np.concatenate([np.arange(n) for _, _, n in features])
    return x, labels, types, drive


_AGG = dict(kde_bandwidth_factor=1.0, kde_min_bandwidth_m=0.15, overlap_threshold=0.3)


def test_overlap_filter_border_beside_marking():
    # A dashed lane line at 0 (8 drives), the solid edge line at 3.50 m (10 drives) and a curb
    # 0.25 m beyond it (6 drives): overlap 2 * Phi(-0.25 / 0.3) = 0.40 > 0.3.
    x, labels, types, drive = _step(
        [(0.0, FeatureType.DASHED, 8), (3.50, FeatureType.SOLID, 10), (3.75, FeatureType.ROAD_BORDER, 6)]
    )
    paper = aggregate_step(x, labels, types, drive, config=former(AggregationConfig, **_AGG))
    np.testing.assert_array_equal(paper.kept_labels, [0, 1])  # the curb (fewer samples) dropped
    split = aggregate_step(
        x, labels, types, drive, config=former(AggregationConfig, overlap_border_marking=False, **_AGG)
    )
    np.testing.assert_array_equal(split.kept_labels, [0, 1, 2])
    np.testing.assert_allclose(split.lateral_m, [0.0, 3.50, 3.75], atol=1e-9)
    np.testing.assert_array_equal(split.types, [FeatureType.DASHED, FeatureType.SOLID, FeatureType.ROAD_BORDER])
    np.testing.assert_array_equal(split.counts, [8, 10, 6])


@pytest.mark.parametrize("copy_m", [3.52, 3.78])
def test_overlap_filter_by_class_still_drops_a_misclassified_copy(copy_m):
    # Plus a dashed copy of the edge line seen by 2 drives, beside the line (3.52 m) or beyond
    # the curb (3.78 m: the curb lies between them in position, the pair must still be compared;
    # overlap with the line 2 * Phi(-0.28 / 0.3) = 0.35 > 0.3).
    feats = [
        (0.0, FeatureType.DASHED, 8),
        (3.50, FeatureType.SOLID, 10),
        (3.75, FeatureType.ROAD_BORDER, 6),
        (copy_m, FeatureType.DASHED, 2),
    ]
    x, labels, types, drive = _step(feats)
    agg = aggregate_step(
        x, labels, types, drive, config=former(AggregationConfig, overlap_border_marking=False, **_AGG)
    )
    np.testing.assert_array_equal(agg.kept_labels, [0, 1, 2])
    np.testing.assert_array_equal(agg.counts, [8, 10, 6])


@pytest.mark.parametrize("first", [FeatureType.SOLID, FeatureType.DASHED])
def test_tie_between_solid_and_dashed_goes_by_the_lines_place(first):
    # Two drives saw the same line, one as solid, one as dashed (0.05 m apart: they overlap).
    # Outermost marking of its side (only a border beyond it) -> solid; a marking with markings
    # on both sides -> dashed. Without the option the tie goes by position order.
    second = FeatureType.DASHED if first == FeatureType.SOLID else FeatureType.SOLID
    cfg = former(AggregationConfig, tie_by_position=True, **_AGG)
    outer = [(0.0, FeatureType.DASHED, 3), (3.50, first, 1), (3.55, second, 1), (4.6, FeatureType.ROAD_BORDER, 3)]
    agg = aggregate_step(*_step(outer), config=cfg)
    np.testing.assert_array_equal(agg.types, [FeatureType.DASHED, FeatureType.SOLID, FeatureType.ROAD_BORDER])
    inner = [(0.0, FeatureType.SOLID, 3), (3.50, first, 1), (3.55, second, 1), (7.0, FeatureType.DASHED, 3)]
    agg = aggregate_step(*_step(inner), config=cfg)
    np.testing.assert_array_equal(agg.types, [FeatureType.SOLID, FeatureType.DASHED, FeatureType.DASHED])
    paper = aggregate_step(*_step(inner), config=former(AggregationConfig, **_AGG))
    np.testing.assert_array_equal(paper.types, [FeatureType.SOLID, first, FeatureType.DASHED])
    # a majority is not overruled: two drives say solid, one dashed, in the inner place
    major = [
        (0.0, FeatureType.SOLID, 3),
        (3.50, FeatureType.SOLID, 2),
        (3.55, FeatureType.DASHED, 1),
        (7.0, FeatureType.DASHED, 3),
    ]
    agg = aggregate_step(*_step(major), config=cfg)
    np.testing.assert_array_equal(agg.types, [FeatureType.SOLID, FeatureType.SOLID, FeatureType.DASHED])


def test_border_of_two_drives_on_a_line_stays_beside_it():
    # An edge line at 3.5 m (3 drives) with a border right on it (0.1 m over): seen as a border
    # by one drive it is the filter's misclassified copy and dropped; by two drives it stays
    # with border_beside_marking_drives 2 (a curb on the line), and is dropped without it.
    cfg = former(AggregationConfig, border_beside_marking_drives=2, **_AGG)
    one = [(0.0, FeatureType.DASHED, 3), (3.5, FeatureType.SOLID, 3), (3.6, FeatureType.ROAD_BORDER, 1)]
    two = [(0.0, FeatureType.DASHED, 3), (3.5, FeatureType.SOLID, 3), (3.6, FeatureType.ROAD_BORDER, 2)]
    np.testing.assert_array_equal(
        aggregate_step(*_step(one), config=cfg).types, [FeatureType.DASHED, FeatureType.SOLID]
    )
    agg = aggregate_step(*_step(two), config=cfg)
    np.testing.assert_array_equal(agg.types, [FeatureType.DASHED, FeatureType.SOLID, FeatureType.ROAD_BORDER])
    np.testing.assert_array_equal(agg.counts, [3, 3, 2])
    paper = aggregate_step(*_step(two), config=former(AggregationConfig, **_AGG))
    np.testing.assert_array_equal(paper.types, [FeatureType.DASHED, FeatureType.SOLID])


def test_mean_method_and_uncertainty():
    x = np.array([0.9, 1.1, 1.0, 1.0])
    agg = aggregate_step(
        x,
        np.zeros(4, np.int64),
        np.ones(4, np.int64),
        np.array([0, 1, 2, 3]),
        config=former(AggregationConfig, method="mean"),
    )
    assert agg.lateral_m[0] == pytest.approx(1.0)
    assert agg.std_m[0] == pytest.approx(x.std() / 2.0)
    assert agg.counts[0] == 4


def test_dropped_labels_ignored():
    agg = aggregate_step(
        np.array([5.0, 0.0, 0.1]),
        np.array([-1, 0, 0]),
        np.ones(3, np.int64),
        np.arange(3),
        config=former(AggregationConfig),
    )
    assert len(agg.lateral_m) == 1 and agg.lateral_m[0] == pytest.approx(0.05, abs=1e-6)


def test_processed_store_marks_merges_and_round_trips():
    store = ProcessedStore()
    s2 = store.with_marks({"a": np.array([10.0, 12.0, 14.0, 40.0]), "b": np.array([0.0])}, pad_m=1.0, merge_gap_m=6.0)
    assert store.intervals == {}  # the input store is not changed
    assert s2.intervals["a"] == [(9.0, 15.0), (39.0, 41.0)]
    np.testing.assert_array_equal(
        s2.contains("a", np.array([8.9, 9.0, 12.0, 15.0, 20.0, 40.5])), [False, True, True, True, False, True]
    )
    assert not s2.contains("zzz", np.array([1.0])).any()
    s3 = s2.with_marks({"a": np.array([16.0])}, pad_m=1.0, merge_gap_m=6.0)
    assert s3.intervals["a"][0] == (9.0, 17.0)
    # the new store shares the unmarked drives' lists, and the store before keeps its own
    assert s2.intervals["a"] == [(9.0, 15.0), (39.0, 41.0)] and s3.intervals["b"] == s2.intervals["b"]
    back = ProcessedStore.from_json(s3.to_json())
    assert back.intervals == s3.intervals
    with pytest.raises(ConfigError):
        ProcessedStore.from_json("{not json")


def test_config_checks():
    with pytest.raises(ConfigError):
        former(AggregationConfig, method="median")
    with pytest.raises(ConfigError):
        former(AggregationConfig, overlap_threshold=1.5)


@pytest.mark.parametrize(
    ("mu2", "s1", "s2"), [(0.5, 0.2, 0.2), (0.5, 0.2, 0.4), (1.0, 0.3, 0.1), (0.0, 0.2, 0.5), (3.0, 0.2, 0.3)]
)
def test_gaussian_overlap_equals_numeric_integral(mu2, s1, s2):
    grid = np.linspace(-6, 9, 200001)
    p = np.exp(-0.5 * (grid / s1) ** 2) / (s1 * np.sqrt(2 * np.pi))
    q = np.exp(-0.5 * ((grid - mu2) / s2) ** 2) / (s2 * np.sqrt(2 * np.pi))
    want = np.minimum(p, q).sum() * (grid[1] - grid[0])
    assert float(gaussian_overlap(0.0, s1, mu2, s2)) == pytest.approx(want, abs=1e-4)


def test_aggregate_many_equals_per_step():
    rng = np.random.default_rng(8)
    parts = []
    for step in range(5):
        centres = np.array([-5.25, -1.75, 1.75, 5.25]) + rng.normal(0, 0.1)
        for c, (mu, t) in enumerate(zip(centres, (1, 2, 2, 1))):
            n = int(rng.integers(3, 9))
            parts.append(
                (rng.normal(mu, 0.08, n), np.full(n, step), np.full(n, step * 10 + c), np.full(n, t), np.arange(n))
            )
    x, st, lab, ty, dr = (np.concatenate(v) for v in zip(*parts))
    cfg = former(AggregationConfig, kde_bandwidth_factor=1.0)
    many = aggregate_many(x, st, lab, ty, dr, config=cfg)
    for step in range(5):
        sel = st == step
        one = aggregate_step(x[sel], lab[sel], ty[sel], dr[sel], config=cfg)
        np.testing.assert_allclose(many.lateral_m[many.step == step], one.lateral_m, atol=1e-9)
        np.testing.assert_array_equal(many.counts[many.step == step], one.counts)


def test_common_error_of_corrected_drives_is_added_to_the_spread():
    """Four corrected drives agreeing within 0.1 m still carry the mean of their localization
    errors: lateral_std = sqrt(spread^2 + common^2 / n); one drive: sqrt(single^2 + common^2)."""
    x = np.array([0.9, 1.1, 1.0, 1.0])
    four = dict(labels=np.zeros(4, np.int64), types=np.ones(4, np.int64), drive=np.arange(4))
    cfg = former(AggregationConfig, method="mean", common_sigma_m=1.0)
    agg = aggregate_step(x, four["labels"], four["types"], four["drive"], config=cfg)
    assert agg.std_m[0] == pytest.approx(np.hypot(x.std() / 2.0, 1.0 / 2.0))
    one = aggregate_step(
        np.array([2.0]), np.zeros(1, np.int64), np.ones(1, np.int64), np.zeros(1, np.int64), config=cfg
    )
    assert one.std_m[0] == pytest.approx(np.hypot(SINGLE_DRIVE_STD_M, 1.0))
    with pytest.raises(ConfigError, match="common_sigma_m"):
        former(AggregationConfig, common_sigma_m=-0.1)


def test_distinct_drives_per_cluster_by_marks_and_by_unique():
    from hdmap_core.pipeline.aggregation import _distinct_drives  # noqa: PLC0415 - a private helper

    rng = np.random.default_rng(7)
    # dense pairs (marks) and sparse ones (few samples, many drives: the unique)
    for m, k, nd in [(5000, 40, 30), (200, 20, 5000)]:
        lab = np.concatenate([np.arange(k), rng.integers(0, k, m - k)])
        drive = rng.integers(0, nd, m)
        want = np.array([len(set(drive[lab == c].tolist())) for c in range(k)])
        got = _distinct_drives(lab, drive, k)
        np.testing.assert_array_equal(got, want)
        assert got.dtype == np.int64


def test_kde_maxima_the_same_in_runs_of_clusters(monkeypatch):
    from hdmap_core.pipeline import aggregation  # noqa: PLC0415

    rng = np.random.default_rng(11)
    k = 300
    labels = np.concatenate([np.arange(k), rng.integers(0, k, 20000)])
    x = labels * 0.7 + rng.normal(0.0, 0.2, len(labels))
    bw = rng.uniform(0.15, 0.4, k)
    whole = kde_maxima(x, labels, bw)
    for chunk in (1, 50, 997):
        monkeypatch.setattr(aggregation, "KDE_CHUNK_SAMPLES", chunk)
        np.testing.assert_array_equal(kde_maxima(x, labels, bw), whole)  # to the last bit
    # each maximum near its cluster's centre
    assert np.all(np.abs(whole - np.arange(k) * 0.7) < 0.2)
