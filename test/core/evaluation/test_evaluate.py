"""The evaluator (paper Sec. VII) on small synthetic roads with known answers and on a real map.

The synthetic road, driving direction +x, 200 m long (y in metres)::

    y = 7.5  ============================  road_border   (id 5)
    y = 7.0  ----------------------------  solid          (id 4)
               lane "B"   ->   centre 5.25
    y = 3.5  - - - - - - - - - - - - - - -  dashed         (id 3)
               lane "A"   ->   centre 1.75
    y = 0.0  ----------------------------  solid          (id 2)
    y = -0.5 ============================  road_border   (id 1)
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from hdmap_core.errors import ConfigError, NoUsableDataError
from hdmap_core.evaluation.config import EvalConfig
from hdmap_core.evaluation.evaluate import evaluate_map, hdmap_from_ground_truth
from hdmap_core.evaluation.plot import plot_evaluation
from hdmap_core.evaluation.summary import format_summary
from hdmap_core.groundtruth import GroundTruth, GTFeature, GTLane, GTRoute, load_ground_truth
from hdmap_core.model import Drive, FeatureType, HDMap, MapFeature

LENGTH_M = 200.0


def _line(y: float, x0: float = 0.0, x1: float = LENGTH_M, reverse: bool = False) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, 1.0)
    pts = np.stack([x, np.full_like(x, y)], axis=1)
    return pts[::-1].copy() if reverse else pts


@pytest.fixture
def road() -> GroundTruth:
    feats = (
        GTFeature(1, FeatureType.ROAD_BORDER, _line(-0.5)),
        GTFeature(2, FeatureType.SOLID, _line(0.0)),
        GTFeature(3, FeatureType.DASHED, _line(3.5)),
        GTFeature(4, FeatureType.SOLID, _line(7.0)),
        GTFeature(5, FeatureType.ROAD_BORDER, _line(7.5)),
    )
    lanes = {
        "A": GTLane("A", _line(1.75), left="B"),
        "B": GTLane("B", _line(5.25), right="A"),
    }
    routes = (GTRoute("rA", ("A",)), GTRoute("rB", ("B",)))
    return GroundTruth("two_lanes", feats, lanes, routes)


def _drive(drive_id: str, y: float, x0: float, x1: float, reverse: bool = False) -> Drive:
    xy = _line(y, x0, x1, reverse=reverse)
    yaw = np.full(len(xy), math.pi if reverse else 0.0)
    return Drive(drive_id, xy, yaw, np.arange(len(xy), dtype=np.int64) * 10**8)


def _with_features(hdmap: HDMap, features: list[MapFeature]) -> HDMap:
    return replace(hdmap, features=tuple(features))


# --------------------------------------------------------------------------------------------


def test_ground_truth_against_itself_is_perfect(road: GroundTruth) -> None:
    report = evaluate_map(hdmap_from_ground_truth(road), road)
    # Two lanes, one cross section: the second lane's cuts are de-duplicated away.
    assert report.n_cuts == report.n_reference_cuts == int(LENGTH_M / 2)
    assert report.reference_length_m == pytest.approx(LENGTH_M)
    ov = report.overall
    assert ov.n_gt_points == ov.n_map_points == ov.n_matched == 5 * report.n_cuts
    assert ov.mean_m == pytest.approx(0.0, abs=1e-9)
    assert ov.p95_m == pytest.approx(0.0, abs=1e-9)
    assert ov.recall == ov.precision == ov.coverage == 1.0
    assert report.type_accuracy == 1.0
    assert report.fragmentation_mean == 1.0 and report.n_gt_features == 5
    assert set(report.per_type) == {"solid", "dashed", "road_border"}
    for st in report.per_type.values():
        assert st.recall == st.precision == st.coverage == 1.0
    assert report.per_type["road_border"].n_gt_points == 2 * report.n_cuts
    assert report.per_type["dashed"].n_gt_points == report.n_cuts


@pytest.mark.parametrize("shift_m", [0.3, -0.3])
def test_sideways_shift_is_total_error_not_shape_error(road: GroundTruth, shift_m: float) -> None:
    report = evaluate_map(hdmap_from_ground_truth(road, lateral_shift_m=shift_m), road)
    assert report.overall.mean_m == pytest.approx(0.3, abs=0.02)
    assert report.overall.corrected_mean_m < 0.02
    assert report.mean_abs_offset_m == pytest.approx(0.3, abs=0.02)
    np.testing.assert_allclose(report.cuts.offset_m, shift_m, atol=1e-9)
    for st in report.per_type.values():
        assert st.mean_m == pytest.approx(0.3, abs=0.02)
        assert st.recall == 1.0 and st.precision == 1.0  # 0.3 m is inside the 1 m radius


def test_shift_beyond_recall_radius_keeps_errors_but_drops_recall(road: GroundTruth) -> None:
    report = evaluate_map(hdmap_from_ground_truth(road, lateral_shift_m=1.2), road)
    assert report.overall.mean_m == pytest.approx(1.2, abs=0.02)
    assert report.overall.recall == 0.0 and report.overall.precision == 0.0
    assert report.coverage == 1.0  # still inside the 2.5 m gate


def test_one_wrong_type_lowers_type_accuracy(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    wrong = [replace(f, type=FeatureType.SOLID) if f.id == 3 else f for f in perfect.features]
    report = evaluate_map(_with_features(perfect, wrong), road)
    assert report.type_accuracy == pytest.approx(4 / 5)
    assert report.per_type["dashed"].recall == 0.0
    assert report.per_type["dashed"].coverage == 0.0
    # The mislabelled line is 3.5 m from the nearest true solid line: outside the gate.
    assert report.per_type["solid"].precision == pytest.approx(2 / 3)
    assert report.overall.mean_m == pytest.approx(0.0, abs=1e-9)


def test_offset_corrected_type_accuracy_forgives_the_common_error_only(road: GroundTruth) -> None:
    """Each border lies 0.5 m outside its solid edge line. The whole map 0.35 m to the left (a
    fleet's common error): the right border (-0.5 -> -0.15) is now nearer the solid line at 0, the
    left solid line (7.0 -> 7.35) nearer the border at 7.5, so two of five lines count as the wrong
    type on raw positions; less each cut's offset (0.35 m) every type is right. A type really
    wrong (the dashed line as solid) stays wrong after the correction."""
    shifted = hdmap_from_ground_truth(road, lateral_shift_m=0.35)
    report = evaluate_map(shifted, road)
    assert report.type_accuracy == pytest.approx(3 / 5)
    assert report.type_accuracy_corrected == pytest.approx(1.0)
    assert evaluate_map(hdmap_from_ground_truth(road), road).type_accuracy_corrected == 1.0
    wrong = [replace(f, type=FeatureType.SOLID) if f.id == 3 else f for f in shifted.features]
    report = evaluate_map(_with_features(shifted, wrong), road)
    assert report.type_accuracy_corrected == pytest.approx(4 / 5)
    assert report.to_dict()["type_accuracy_corrected"] == pytest.approx(4 / 5)


def test_missing_half_of_the_features_lowers_recall(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    kept = [f for f in perfect.features if f.id in (1, 3)]  # one border, the dashed line
    report = evaluate_map(_with_features(perfect, kept), road)
    assert report.overall.recall == pytest.approx(2 / 5)
    assert report.overall.precision == 1.0
    assert report.per_type["solid"].coverage == 0.0
    assert report.per_type["road_border"].recall == pytest.approx(0.5)
    assert report.coverage == 1.0  # every cut still has a matched point


def test_map_of_half_the_road_length_covers_half(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    half = [
        replace(f, points=f.points[:101], drive_count=f.drive_count[:101], lateral_std=f.lateral_std[:101])
        for f in perfect.features
    ]
    report = evaluate_map(_with_features(perfect, half), road)
    assert report.coverage == pytest.approx(0.5, abs=0.011)
    assert report.overall.recall == pytest.approx(0.5, abs=0.011)
    assert report.evaluable_length_m == pytest.approx(LENGTH_M / 2, abs=2.0)
    assert not report.cuts.evaluable[report.cuts.center[:, 0] > 101].any()


@pytest.mark.slow
def test_empty_map_gives_zero_coverage_without_crash(road: GroundTruth, tmp_path: Path) -> None:
    report = evaluate_map(HDMap(), road)
    assert report.coverage == 0.0
    assert report.overall.recall == 0.0
    assert math.isnan(report.overall.mean_m) and math.isnan(report.overall.precision)
    assert report.n_evaluable_cuts == 0
    doc = json.loads(json.dumps(report.to_dict(include_cuts=True), allow_nan=False))
    assert doc["overall"]["mean_m"] is None and doc["coverage"] == 0.0
    assert "n/a" in format_summary(report)
    out = plot_evaluation(report, HDMap(), road, tmp_path / "empty.png")
    assert out.stat().st_size > 0


def test_opposite_direction_and_far_features_are_ignored(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    # The opposite carriageway's border just beyond ours (within the cut margin), and a line
    # beyond the margin: neither is part of this carriageway.
    extra = [
        MapFeature(100, FeatureType.ROAD_BORDER, _line(8.2, reverse=True), np.zeros(201, int), np.zeros(201)),
        MapFeature(101, FeatureType.SOLID, _line(9.0), np.zeros(201, int), np.zeros(201)),
    ]
    report = evaluate_map(_with_features(perfect, list(perfect.features) + extra), road)
    assert report.overall.precision == 1.0
    assert report.overall.n_map_points == 5 * report.n_cuts


def test_map_border_displaced_outwards_is_still_seen(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    moved = [replace(f, points=f.points + [0.0, 0.8]) if f.id == 5 else f for f in perfect.features]
    report = evaluate_map(_with_features(perfect, moved), road)
    assert report.per_type["road_border"].coverage == 1.0
    assert report.per_type["road_border"].mean_m == pytest.approx(0.4, abs=1e-6)  # (0 + 0.8) / 2


def test_malformed_map_features_are_skipped_and_named(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    bad_pts = _line(3.0)
    bad_pts[5] = np.nan
    bad = [
        MapFeature(900, FeatureType.SOLID, bad_pts, np.zeros(201, int), np.zeros(201)),
        MapFeature(901, FeatureType.SOLID, np.zeros((1, 2)), np.zeros(1, int), np.zeros(1)),
        replace(perfect.features[0], id=902, drive_count=np.zeros(3, int)),
    ]
    report = evaluate_map(_with_features(perfect, list(perfect.features[1:]) + bad), road)
    text = "\n".join(report.skipped)
    assert "900" in text and "non-finite" in text
    assert "901" in text and "902" in text
    assert report.overall.recall == 1.0  # 902 (a copy of feature 1 with bad counts) still evaluates


def test_floor_from_drive_trajectories(road: GroundTruth) -> None:
    drives = [_drive(f"a{i}", 1.75, 0.0, LENGTH_M) for i in range(4)]
    drives += [_drive(f"b{i}", 5.25, 0.0, 100.0) for i in range(9)]
    drives += [_drive("wrong_way", 3.0, 0.0, LENGTH_M, reverse=True)]
    sigma = 0.8
    report = evaluate_map(hdmap_from_ground_truth(road), road, drives=drives, sigma_loc_m=sigma)
    assert report.floor_source == "drives"
    x = report.cuts.center[:, 0]
    first, second = x < 99.0, x > 101.0
    np.testing.assert_allclose(report.cuts.drive_count[first], 13)
    np.testing.assert_allclose(report.cuts.drive_count[second], 4)
    np.testing.assert_allclose(report.cuts.floor_m[first], sigma / math.sqrt(13))
    np.testing.assert_allclose(report.cuts.floor_m[second], sigma / 2)
    assert report.floor_mean_m == pytest.approx(float(np.mean(report.cuts.floor_m)))
    assert report.sigma_loc_m == sigma


def test_fleet_density_against_the_papers_drives_per_place(road: GroundTruth) -> None:
    # 13 drives over the first 100 m, 4 beyond: with the paper's 5-25 range, about half the
    # reference cuts are in it and half below; the map plays no part (an empty map: same figures)
    drives = [_drive(f"a{i}", 1.75, 0.0, LENGTH_M) for i in range(4)]
    drives += [_drive(f"b{i}", 5.25, 0.0, 100.0) for i in range(9)]
    for hdmap in (hdmap_from_ground_truth(road), HDMap()):
        report = evaluate_map(hdmap, road, drives=drives)
        n = report.cuts.drive_count[report.cuts.n_gt > 0]
        assert report.density_share == pytest.approx(np.mean(n == 13))
        assert report.sparse_share == pytest.approx(np.mean(n == 4))
        assert 0.4 < report.density_share < 0.6
        assert report.density_share + report.sparse_share == pytest.approx(1.0)
        assert report.drive_count_median in (4.0, 8.5, 13.0)
    assert "at 5-25 drives" in format_summary(report)
    wide = evaluate_map(hdmap_from_ground_truth(road), road, drives=drives, config=EvalConfig(density_drives=(1, 30)))
    assert wide.density_share == pytest.approx(1.0) and wide.sparse_share == 0.0
    # without drives there is no density (the map's drive counts are not the fleet's)
    bare = evaluate_map(hdmap_from_ground_truth(road), road)
    assert math.isnan(bare.density_share) and "fleet density" not in format_summary(bare)


def test_coverage_over_the_driven_cuts(road: GroundTruth) -> None:
    """Drives only over the first 100 m of the 200 m road: half the reference is driven. A map of
    the whole road covers all of it; a map of the undriven half only has 50 % coverage overall and
    none over the driven cuts; a map of the driven half only is complete where the fleet drove."""
    drives = [_drive(f"b{i}", 5.25, 0.0, 100.0) for i in range(3)]
    drives += [_drive("wrong_way", 3.0, 0.0, LENGTH_M, reverse=True)]  # the other direction counts for nothing

    def part(lo: float, hi: float) -> HDMap:
        full = hdmap_from_ground_truth(road)
        feats = []
        for f in full.features:
            keep = (f.points[:, 0] >= lo) & (f.points[:, 0] <= hi)
            feats.append(
                replace(f, points=f.points[keep], drive_count=f.drive_count[keep], lateral_std=f.lateral_std[keep])
            )
        return _with_features(full, feats)

    whole = evaluate_map(hdmap_from_ground_truth(road), road, drives=drives)
    assert whole.driven_share == pytest.approx(0.5, abs=0.02)
    assert whole.coverage == 1.0 and whole.coverage_driven == 1.0
    undriven = evaluate_map(part(102.0, LENGTH_M), road, drives=drives)
    assert undriven.coverage == pytest.approx(0.5, abs=0.03) and undriven.coverage_driven == 0.0
    driven = evaluate_map(part(0.0, 100.0), road, drives=drives)
    assert driven.coverage == pytest.approx(0.5, abs=0.03) and driven.coverage_driven == pytest.approx(1.0, abs=0.02)
    assert "coverage over them" in format_summary(driven)
    assert driven.to_dict()["coverage_driven"] == pytest.approx(driven.coverage_driven)
    bare = evaluate_map(hdmap_from_ground_truth(road), road)  # no drives: unknown
    assert (
        math.isnan(bare.driven_share)
        and math.isnan(bare.coverage_driven)
        and "driven reference" not in format_summary(bare)
    )


def test_realized_floor_is_the_mean_error_of_the_crossing_drives(road: GroundTruth) -> None:
    drives = [_drive(f"a{i}", 1.75, 0.0, LENGTH_M) for i in range(4)]
    drives += [_drive(f"b{i}", 5.25, 0.0, 100.0) for i in range(2)]
    drives += [_drive("wrong_way", 3.0, 0.0, LENGTH_M, reverse=True)]
    errors = {"a0": -0.4, "a1": -0.2, "a2": 0.0, "a3": -0.2, "b0": 0.9, "b1": 0.9, "wrong_way": 5.0}
    report = evaluate_map(hdmap_from_ground_truth(road), road, drives=drives, sigma_loc_m=1.0, drive_errors=errors)
    x = report.cuts.center[:, 0]
    first, second = x < 99.0, x > 101.0
    # first 100 m: the a and b drives (mean of -0.8 and 1.8 over 6 = 1/6), beyond: the a drives
    # (-0.2); the wrong-way drive crosses no cut in its direction
    expected = (np.count_nonzero(first) * (1.0 / 6.0) + np.count_nonzero(second) * 0.2) / (
        np.count_nonzero(first) + np.count_nonzero(second)
    )
    assert report.fleet_floor_mean_m == pytest.approx(expected, abs=0.01)
    assert "realized floor" in format_summary(report)
    assert math.isnan(evaluate_map(hdmap_from_ground_truth(road), road, drives=drives).fleet_floor_mean_m)


def _seen_all(gt: GroundTruth, count: int = 1) -> dict[int, np.ndarray]:
    return {f.id: np.full(len(f.points), count) for f in gt.features}


def test_recall_over_observed_points_ignores_what_no_drive_saw(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    without_outer_border = _with_features(perfect, [f for f in perfect.features if f.id != 5])
    seen = {**_seen_all(road, 3), 5: np.zeros(len(road.features[4].points))}
    report = evaluate_map(without_outer_border, road, seen_counts=seen)
    assert report.overall.recall == pytest.approx(4 / 5)  # unchanged by the seen counts
    assert report.observed_share == pytest.approx(4 / 5)
    assert report.recall_observed == 1.0
    assert report.n_observed == 4 * report.n_cuts
    text = format_summary(report)
    assert "observed GT points" in text and "80.0%" in text and "100.0%" in text
    doc = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert doc["observed_share"] == pytest.approx(0.8) and doc["recall_observed"] == 1.0


def test_observed_and_missed_stretches_of_one_line(road: GroundTruth) -> None:
    # The outer solid line (id 4) seen up to x = 100 only; the map has the dashed line (id 3)
    # up to x = 150 only and no outer border. Cuts are at x = 1, 3, ..., 199, on GT vertices; a
    # vertex belongs to the segment starting there, so the cut at x = 101 (segment 101-102) is
    # not observed and the one at x = 99 (segment 99-100) is.
    perfect = hdmap_from_ground_truth(road)
    feats = []
    for f in perfect.features:
        keep = {1: 201, 2: 201, 3: 151, 4: 101, 5: 0}[f.id]
        if keep:
            feats.append(
                replace(f, points=f.points[:keep], drive_count=f.drive_count[:keep], lateral_std=f.lateral_std[:keep])
            )
    seen = _seen_all(road)
    seen[4] = (np.arange(201) <= 100).astype(int)
    report = evaluate_map(_with_features(perfect, feats), road, seen_counts=seen)
    assert report.n_cuts == 100
    # observed: 3 full features + 50 cuts of line 4 (x = 1 ... 99) + all of border 5
    assert report.n_observed == 4 * 100 + 50
    assert report.observed_share == pytest.approx(450 / 500)
    # hits: 200 (ids 1, 2) + 75 (dashed, x <= 149) + 50 (line 4); border 5 missed everywhere
    assert report.overall.recall == pytest.approx(325 / 500)
    assert report.recall_observed == pytest.approx(325 / 450)
    # by seen count: line 4's 50 unseen cuts (none mapped) in "0", the other 450 points in "1"
    # (ids 1, 2: 200 hits; dashed 3: 75; line 4 seen half: 50; border 5: 0)
    by = {label: (share, rec) for label, share, rec in report.recall_by_seen}
    assert by["0"] == pytest.approx((50 / 500, 0.0))
    assert by["1"] == pytest.approx((450 / 500, 325 / 450))
    assert math.isnan(by["2"][1]) and by["2"][0] == 0.0 and by[">=3"][0] == 0.0
    assert "GT points by drives that saw them" in format_summary(report)


def test_recall_by_seen_count_buckets(road: GroundTruth) -> None:
    # every feature seen by a different number of drives; the map lacks the outer border (id 5)
    perfect = hdmap_from_ground_truth(road)
    seen = {f.id: np.full(len(f.points), {1: 0, 2: 1, 3: 2, 4: 3, 5: 7}[f.id]) for f in road.features}
    report = evaluate_map(_with_features(perfect, [f for f in perfect.features if f.id != 5]), road, seen_counts=seen)
    by = {label: (share, rec) for label, share, rec in report.recall_by_seen}
    assert [label for label, _, _ in report.recall_by_seen] == ["0", "1", "2", ">=3"]
    assert by["0"] == pytest.approx((0.2, 1.0)) and by["1"] == pytest.approx((0.2, 1.0))
    assert by["2"] == pytest.approx((0.2, 1.0))
    assert by[">=3"] == pytest.approx((0.4, 0.5))  # line 4 hit, border 5 (seen by 7) missed
    doc = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert doc["recall_by_seen"][3] == [">=3", pytest.approx(0.4), pytest.approx(0.5)]
    assert evaluate_map(perfect, road).recall_by_seen == ()


def test_a_point_is_observed_when_either_end_of_its_segment_was_seen(road: GroundTruth) -> None:
    # The inner solid line with a vertex every 10 m; only the vertex at x = 50 was seen: the
    # segments 40-50 and 50-60 are observed, i.e. the cuts at x = 41, 43, ..., 59.
    coarse = _line(0.0)[::10]
    gt = replace(road, features=tuple(replace(f, points=coarse) if f.id == 2 else f for f in road.features))
    seen = _seen_all(gt)
    seen[2] = (np.arange(len(coarse)) == 5).astype(int)
    report = evaluate_map(hdmap_from_ground_truth(gt), gt, seen_counts=seen)
    assert report.n_observed == 4 * 100 + 10
    assert report.observed_share == pytest.approx(410 / 500)
    assert report.recall_observed == 1.0 and report.overall.recall == 1.0


def test_missing_or_mismatched_seen_counts_are_left_out_and_named(road: GroundTruth) -> None:
    seen = _seen_all(road, 2)
    del seen[1]
    seen[2] = np.zeros(7, dtype=int)
    seen[3] = np.zeros(201, dtype=int)  # a line no drive saw, but the map has it
    seen[4] = ["many"] * 201  # not numbers: left out like a wrong length
    seen[6] = np.ones(3)  # no such feature: ignored
    report = evaluate_map(hdmap_from_ground_truth(road), road, seen_counts=seen)
    text = "\n".join(report.skipped)
    assert "feature 1: no seen counts" in text and "feature 2: 7 seen counts for 201 points" in text
    assert "feature 4: seen counts that are not numbers" in text
    assert report.observed_share == pytest.approx(1 / 2)  # of ids 3 and 5
    assert report.recall_observed == 1.0 and report.n_observed == 100
    plain = evaluate_map(hdmap_from_ground_truth(road), road)
    assert math.isnan(plain.observed_share) and math.isnan(plain.recall_observed) and plain.n_observed == 0
    assert "observed GT points" not in format_summary(plain)
    assert json.loads(json.dumps(plain.to_dict(), allow_nan=False))["recall_observed"] is None


@pytest.mark.slow
def test_simulated_seen_counts_bound_a_map_of_the_drives_own_detections() -> None:
    # The noise-free detections of a few drives, taken as the map: everything the fleet observed
    # is in it, except at the open ends of the detected pieces (a segment with one seen end).
    # The opposite median barrier is reported in the seeing drive's direction, while the cuts of
    # its own carriageway count only lines running their way: so each detection is also put in
    # reversed (6 short drives leave stretches of a barrier seen from the other side only).
    from hdmap_core.simulation.fleet import SimConfig, simulate_fleet
    from hdmap_core.simulation.synthetic import synthetic_highway

    gt = synthetic_highway("motorway", length_m=1500.0)
    cfg = SimConfig.noise_free(
        n_drives=6,
        snippet_length_min_m=400.0,
        snippet_length_max_m=800.0,
        visibility_next_marking=0.7,
        visibility_far_marking=0.25,
        visibility_border=0.6,
    )
    fleet = simulate_fleet(gt, config=cfg, seed=2)
    lines = [(x.type, p) for d in fleet.drives for x in d.detections for p in (x.points, x.points[::-1])]
    feats = [MapFeature(i, t, p, np.ones(len(p), int), np.zeros(len(p))) for i, (t, p) in enumerate(lines)]
    report = evaluate_map(HDMap(features=tuple(feats)), gt, seen_counts=fleet.seen_count)
    assert 0.3 < report.observed_share < 0.9
    assert report.overall.recall < 0.9 * report.recall_observed
    assert report.recall_observed > 0.98
    assert report.overall.recall == pytest.approx(report.observed_share * report.recall_observed, abs=1e-12)


def test_floor_from_map_drive_counts_and_default_sigma(road: GroundTruth) -> None:
    report = evaluate_map(hdmap_from_ground_truth(road, drive_count=9), road)
    assert report.floor_source == "map"
    assert report.floor_mean_m == pytest.approx(EvalConfig().default_sigma_loc_m / 3)
    none = evaluate_map(hdmap_from_ground_truth(road), road)
    assert none.floor_source == "none" and math.isnan(none.floor_mean_m)


def test_fragmentation_counts_map_pieces_per_gt_feature(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    pieces = []
    for f in perfect.features:
        if f.id == 3:  # the dashed line in three pieces
            for k, (a, b) in enumerate([(0, 70), (70, 140), (140, 201)]):
                pieces.append(
                    replace(
                        f,
                        id=300 + k,
                        points=f.points[a : b + (b < 201)],
                        drive_count=f.drive_count[a : b + (b < 201)],
                        lateral_std=f.lateral_std[a : b + (b < 201)],
                    )
                )
        else:
            pieces.append(f)
    report = evaluate_map(_with_features(perfect, pieces), road)
    assert report.fragmentation_max == 3
    assert report.fragmentation_mean == pytest.approx((4 * 1 + 3) / 5)


@pytest.mark.slow
def test_report_outputs(road: GroundTruth, tmp_path: Path) -> None:
    hdmap = hdmap_from_ground_truth(road, lateral_shift_m=0.3, drive_count=5)
    report = evaluate_map(hdmap, road)
    doc = json.loads(json.dumps(report.to_dict(include_cuts=True), allow_nan=False))
    assert doc["overall"]["mean_m"] == pytest.approx(0.3, abs=0.02)
    assert set(doc["per_type"]) == {"solid", "dashed", "road_border"}
    assert len(doc["cuts"]["station_m"]) == report.n_cuts
    assert "cuts" not in report.to_dict()
    text = format_summary(report)
    for word in ("solid", "dashed", "road_border", "coverage", "type accuracy", "fragmentation", "floor"):
        assert word in text
    png = plot_evaluation(report, hdmap, road, tmp_path / "eval.png")
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_no_highway_lane_is_a_clear_error(road: GroundTruth) -> None:
    town = replace(road, lanes={k: replace(v, highway=False) for k, v in road.lanes.items()})
    with pytest.raises(NoUsableDataError, match="highway"):
        evaluate_map(hdmap_from_ground_truth(town), town)
    report = evaluate_map(hdmap_from_ground_truth(town), town, config=EvalConfig(highway_only=False))
    assert report.coverage == 1.0


@pytest.mark.parametrize(
    "kwargs",
    [
        {"step_m": 0.0},
        {"gate_m": -1.0},
        {"recall_radius_m": 3.0},
        {"max_feature_angle_deg": 95.0},
        {"border_margin_m": float("nan")},
        {"density_drives": (5, 2)},
        {"density_drives": (-1, 5)},
    ],
)
def test_bad_config_is_rejected(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        EvalConfig(**kwargs)


def test_bad_arguments_are_rejected(road: GroundTruth) -> None:
    with pytest.raises(ConfigError, match="sigma_loc_m"):
        evaluate_map(HDMap(), road, sigma_loc_m=0.0)
    with pytest.raises(Exception, match="HDMap"):
        evaluate_map(road, road)  # type: ignore[arg-type]


def test_inputs_are_not_mutated(road: GroundTruth) -> None:
    hdmap = hdmap_from_ground_truth(road, lateral_shift_m=0.3)
    before = [f.points.copy() for f in hdmap.features]
    gt_before = [f.points.copy() for f in road.features]
    evaluate_map(hdmap, road)
    for f, p in zip(hdmap.features, before):
        np.testing.assert_array_equal(f.points, p)
    for f, p in zip(road.features, gt_before):
        np.testing.assert_array_equal(f.points, p)


# --------------------------------------------------------------------------------------------
# A real map


def _shared_map(name: str) -> GroundTruth:
    """A real map shipped in the repository's ``data/maps``."""
    from hdmap_core.simulation.fleet import maps_dirs

    paths = [d / f"{name}.gt.json" for d in maps_dirs() if (d / f"{name}.gt.json").is_file()]
    assert paths, f"{name}.gt.json not found: data/maps ships with the repository"
    return load_ground_truth(paths[0])


@pytest.fixture(scope="module")
def e6mini() -> GroundTruth:
    return _shared_map("esmini_e6mini")


@pytest.mark.slow
def test_real_map_against_itself_and_shifted(e6mini: GroundTruth, tmp_path: Path) -> None:
    same = evaluate_map(hdmap_from_ground_truth(e6mini), e6mini)
    assert same.overall.mean_m == pytest.approx(0.0, abs=1e-6)
    assert same.overall.recall == same.overall.precision == 1.0
    assert same.coverage > 0.99
    assert same.type_accuracy == 1.0 and same.fragmentation_mean == 1.0
    # Both carriageways of the 1.46 km motorway, each cross section once.
    assert same.reference_length_m == pytest.approx(2 * 1460, rel=0.02)
    shifted_map = hdmap_from_ground_truth(e6mini, lateral_shift_m=0.3)
    shifted = evaluate_map(shifted_map, e6mini)
    assert shifted.overall.mean_m == pytest.approx(0.3, abs=0.02)
    assert shifted.overall.corrected_mean_m < 0.02
    assert plot_evaluation(shifted, shifted_map, e6mini, tmp_path / "e6.png").stat().st_size > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["carla_town04", "carla_town06"])
def test_large_real_maps_shifted(name: str) -> None:
    gt = _shared_map(name)
    report = evaluate_map(hdmap_from_ground_truth(gt, lateral_shift_m=0.3), gt)
    assert report.overall.mean_m == pytest.approx(0.3, abs=0.02)
    assert report.overall.corrected_mean_m < 0.02
    assert report.coverage > 0.99
    print(f"{name}: evaluated in {report.runtime_s:.2f} s")  # a figure, not a timed assertion


def test_bad_ground_truth_parts_are_left_out_and_named(road: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(road)
    dashed = road.features[2].points.copy()
    dashed[50] = np.nan
    centre = road.lanes["A"].centerline.copy()
    centre[10] = np.inf
    bad = replace(
        road,
        features=road.features[:2]
        + (replace(road.features[2], points=dashed),)
        + road.features[3:]
        + (GTFeature(99, FeatureType.SOLID, np.full((3, 2), np.nan)),),
        lanes={**road.lanes, "A": replace(road.lanes["A"], centerline=centre)},
        routes=road.routes + (GTRoute("ghost", ("A", "no_such_lane")),),
    )
    report = evaluate_map(perfect, bad)
    text = "\n".join(report.skipped)
    assert "feature 3: 1 non-finite" in text and "feature 99" in text
    assert "lane A: 1 non-finite" in text and "route ghost" in text
    assert report.overall.recall == 1.0 and report.overall.mean_m == pytest.approx(0.0, abs=1e-9)
    assert report.n_reference_cuts == int(LENGTH_M / 2)


@pytest.mark.slow
def test_synthetic_highway_with_ramps_each_cross_section_once() -> None:
    synthetic = pytest.importorskip("hdmap_core.simulation.synthetic")
    length_m = 3000.0
    gt = synthetic.synthetic_highway("motorway_ramps", length_m=length_m)
    report = evaluate_map(hdmap_from_ground_truth(gt), gt)
    assert report.coverage == 1.0 and report.overall.recall == 1.0 and report.overall.precision == 1.0
    assert report.type_accuracy == 1.0 and report.fragmentation_mean == 1.0
    # Two carriageways of 3 lanes (6 routes' worth of lanes) plus the ramps' own stretches beyond
    # the gore: far less than the lane length, a little more than twice the road length.
    lane_km = sum(
        np.linalg.norm(np.diff(ln.centerline, axis=0), axis=1).sum() for ln in gt.lanes.values() if ln.highway
    )
    assert 2 * length_m * 0.98 < report.reference_length_m < 2 * length_m * 1.5 < lane_km


# --------------------------------------------------------------------------------------------
# Splits and merges


@pytest.fixture(scope="module")
def ramps() -> GroundTruth:
    synthetic = pytest.importorskip("hdmap_core.simulation.synthetic")
    return synthetic.synthetic_highway("motorway_ramps", length_m=3000.0)


def _unlinked(hdmap: HDMap) -> HDMap:
    return _with_features(hdmap, [replace(f, successors=(), predecessors=()) for f in hdmap.features])


@pytest.mark.slow
def test_ground_truth_map_has_every_split_and_merge(ramps: GroundTruth) -> None:
    report = evaluate_map(hdmap_from_ground_truth(ramps), ramps)
    # Per carriageway one interchange: the deceleration lane's dashed line starts on the edge line
    # (split), at the exit gore it ends where two solid lines start (split); the entry mirrors it.
    assert (report.gt_splits, report.gt_merges) == (4, 4)
    assert (report.found_splits, report.found_merges) == (4, 4)
    assert report.missing_branch_points == ()
    assert all(b.evaluable for b in report.branch_points)
    # The lane graph has one lane split (exit) and one lane merge (entry) per carriageway.
    assert (report.gt_lane_splits, report.gt_lane_merges) == (2, 2)
    doc = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert (doc["gt_splits"], doc["found_merges"], doc["missing_branch_points"]) == (4, 4, [])
    assert "splits 4/4, merges 4/4" in format_summary(report)
    shifted = evaluate_map(hdmap_from_ground_truth(ramps, lateral_shift_m=0.3), ramps)
    assert (shifted.found_splits, shifted.found_merges) == (4, 4)


@pytest.mark.slow
def test_splits_without_links_are_missing(ramps: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(ramps)
    report = evaluate_map(_unlinked(perfect), ramps)
    assert (report.gt_splits, report.gt_merges) == (4, 4)
    # Where a branch starts on the edge line's interior the geometry still connects them (a link
    # cannot express it); at the gores, where lines end and start, only links do.
    assert (report.found_splits, report.found_merges) == (2, 2)
    missing = report.missing_branch_points
    assert len(missing) == 4 and all("not connected" in b.reason for b in missing)
    # Every feature pulled back from its ends by ~12 m as well, where a branch starting on the
    # edge line has left it by > 0.1 m: nothing is connected any more.
    cut = slice(15, -15)
    trimmed = [
        replace(f, points=f.points[cut], drive_count=f.drive_count[cut], lateral_std=f.lateral_std[cut])
        for f in _unlinked(perfect).features
    ]
    none = evaluate_map(_with_features(perfect, trimmed), ramps)
    assert (none.gt_splits, none.gt_merges, none.found_splits, none.found_merges) == (4, 4, 0, 0)
    text = format_summary(none)
    assert "splits 0/4, merges 0/4" in text and "missing split at" in text


@pytest.mark.slow
def test_unmapped_branch_is_named(ramps: GroundTruth) -> None:
    perfect = hdmap_from_ground_truth(ramps)
    # Leave out the ramps' inner solid lines (the features that start at the exit gores and end
    # at the entry gores): those splits/merges lose a branch; the others stay found.
    gore = {i for b in evaluate_map(perfect, ramps).branch_points if len(b.gt_features) == 3 for i in b.gt_features}
    ramp_inner = {f.id for f in ramps.features if f.id in gore and f.type == FeatureType.SOLID and len(f.points) < 500}
    kept = [f for f in perfect.features if f.id not in ramp_inner]
    report = evaluate_map(_with_features(perfect, kept), ramps)
    assert (report.found_splits, report.found_merges) == (2, 2)
    assert all("not mapped" in b.reason for b in report.missing_branch_points)


@pytest.mark.slow
def test_real_map_branch_points_against_itself(e6mini: GroundTruth) -> None:
    # e6mini is a plain 3 + 3 motorway: no lane or feature splits; the figure is 0 of 0.
    report = evaluate_map(hdmap_from_ground_truth(e6mini), e6mini)
    assert (report.gt_splits, report.gt_merges, report.found_splits, report.found_merges) == (0, 0, 0, 0)
    assert (report.gt_lane_splits, report.gt_lane_merges) == (0, 0)


@pytest.mark.slow
def test_town04_ground_truth_map_finds_what_is_evaluable() -> None:
    gt = _shared_map("carla_town04")
    report = evaluate_map(hdmap_from_ground_truth(gt), gt)
    assert report.found_splits == report.gt_splits and report.found_merges == report.gt_merges
    assert report.gt_lane_splits > 0  # the lane graph branches; the markings stop at junctions
    # the markings' branch points: each is found or named not evaluable (none is simply missed)
    assert report.branch_points
    assert all(b.found or b.reason.startswith("not evaluable") for b in report.branch_points)


def test_lateral_std_calibration_counts_the_points_within_their_one_sigma(road: GroundTruth) -> None:
    """Shifted 0.3 m: a map claiming 0.5 m has every point within it (z 0.6), one claiming 0.1 m
    none (z 3); a map with lateral_std 0 (hdmap_from_ground_truth) gives no figure."""
    shifted = hdmap_from_ground_truth(road, lateral_shift_m=0.3)
    none = evaluate_map(shifted, road)
    assert none.n_std_points == 0 and math.isnan(none.std_within_share)
    for std, within, z in ((0.5, 1.0, 0.6), (0.1, 0.0, 3.0)):
        feats = [replace(f, lateral_std=np.full(len(f.points), std)) for f in shifted.features]
        report = evaluate_map(_with_features(shifted, feats), road)
        assert report.n_std_points == report.overall.n_matched > 0
        assert report.std_within_share == within
        assert report.std_z_rms == pytest.approx(z, rel=0.02)
        assert "lateral_std as 1-sigma" in format_summary(report)
    # two of the five features claim 0.5 m, three 0.1 m: two fifths of the points lie within
    feats = [
        replace(f, lateral_std=np.full(len(f.points), 0.5 if i % 2 else 0.1)) for i, f in enumerate(shifted.features)
    ]
    assert len(feats) == 5
    assert evaluate_map(_with_features(shifted, feats), road).std_within_share == pytest.approx(0.4, abs=0.01)
