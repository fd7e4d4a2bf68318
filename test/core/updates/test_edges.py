"""Lane closed / opened: the edge line's move (``updates.edges``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap_core.evaluation.zone import evaluate_zone, evaluate_zone_lanes
from hdmap_core.lanes.derive import derive_lanes
from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature
from hdmap_core.pipeline.driver import PipelineConfig, build_map
from hdmap_core.simulation.changes import change_zone, parse_change
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.edges import (
    MIN_EDGE_MOVE_M,
    EdgeEvidence,
    detect_edge_changes,
    edge_evidence,
    merge_changes,
    solid_lines,
)
from hdmap_core.updates.follow import follow_changes
from hdmap_core.updates.places import Places, places_of

PLACES = Places(100.0, {(i, 0): 0.0 for i in range(0, 6)})


def _rows(key, before, after, t0=0):
    vals = [*before, *after]
    return [EdgeEvidence(f"d{t0 + i:02d}", (t0 + i) * 10**9, key, float(v), 10) for i, v in enumerate(vals)]


def test_an_edge_line_that_moved_a_lane_is_a_lane_change_and_grows_into_the_taper():
    rng = np.random.default_rng(1)
    ev = [
        *_rows((2, 0, 0), rng.normal(0, 0.05, 8), [3.4, 3.6]),
        *_rows((3, 0, 0), rng.normal(0, 0.05, 8), [1.4, np.nan]),  # the taper: one drive, half the move
        *_rows((4, 0, 0), rng.normal(0, 0.05, 8), [0.02, 0.01]),  # the road after the zone
    ]
    (c,) = detect_edge_changes(ev, PLACES)
    assert c.kinds == ("lane_closed",)
    assert {p.key for p in c.places} == {(2, 0, 0), (3, 0, 0)}
    assert [p.extended for p in c.places] == [False, True]
    assert c.time_ns == 8 * 10**9 and c.drives_after == ("d08", "d09")
    # an opened shoulder moves it right
    (o,) = detect_edge_changes(_rows((2, 0, 0), rng.normal(0, 0.05, 8), [-2.0, -2.1]), PLACES)
    assert o.kinds == ("lane_opened",)
    # no change: one drive off, a move under the smallest, drives that disagree
    assert detect_edge_changes(_rows((2, 0, 0), rng.normal(0, 0.05, 8), [3.5]), PLACES) == []
    assert detect_edge_changes(_rows((2, 0, 0), rng.normal(0, 0.05, 8), [1.2, 1.3]), PLACES) == []
    assert detect_edge_changes(_rows((2, 0, 0), rng.normal(0, 0.05, 8), [3.5, 0.0, 3.5]), PLACES) == []


def test_a_drive_that_saw_the_old_edge_turned_divider_supports_a_measured_opening_only():
    rng = np.random.default_rng(2)
    before = rng.normal(0, 0.05, 8)
    rows = _rows((2, 0, 0), before, [-2.0, -MIN_EDGE_MOVE_M])
    seen_only = EdgeEvidence(rows[-1].drive_id, rows[-1].time_ns, rows[-1].key, -MIN_EDGE_MOVE_M, 12, measured=False)
    # one drive measured the move, the next lane's drive saw the old edge line turned dashed
    (o,) = detect_edge_changes([*rows[:-1], seen_only], PLACES)
    assert o.kinds == ("lane_opened",) and len(o.drives_after) == 2
    # two drives that only saw a divider where the edge was (a misread type) confirm nothing
    first = EdgeEvidence(rows[-2].drive_id, rows[-2].time_ns, rows[-2].key, -MIN_EDGE_MOVE_M, 12, measured=False)
    assert detect_edge_changes([*rows[:-2], first, seen_only], PLACES) == []


def _change(cid, kind, keys, effect):
    places = tuple(PlaceChange(k, kind, 10, 5, effect, 9.0, ("b1",), ("a1", "a2")) for k in keys)
    return DetectedChange(cid, 10, (kind,), places, ("a1", "a2"), 0.9)


def test_an_edge_that_moved_with_the_markings_is_their_shift_not_a_lane_change():
    # the markings moved 3 m right (displacement +3), the edge 2.6 m right (move -2.6): a shift
    shift = _change(1, "geometry", [(2, 0, 0), (3, 0, 0)], 3.0)
    opened = _change(2, "lane_opened", [(3, 0, 0)], -2.6)
    assert merge_changes([shift], [opened], PLACES) == [shift]
    # the edge moved a lane beyond the markings' shift (0.5 m right, the edge 2.6 m): a lane opened
    small = _change(1, "geometry", [(2, 0, 0), (3, 0, 0)], 0.5)
    (merged,) = merge_changes([small], [opened], PLACES)
    assert merged.kinds == ("geometry", "lane_opened")
    # no shift touching it: the lane change stands on its own
    assert merge_changes([], [opened], PLACES) == [opened]


def _line(y: float, ftype: FeatureType, x0: float = 0.0, x1: float = 400.0) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, 2.0)
    return np.stack([x, np.full_like(x, y)], axis=1)


def test_edge_evidence_of_the_next_lane_reads_the_old_edge_turned_divider():
    """A drive in the next lane (the map's edge 5.25 m right of it) after a shoulder opened sees a
    dashed line where the map has its solid edge and not the moved edge (the sensor's far band)."""
    edge = MapFeature(
        id=1,
        type=FeatureType.SOLID,
        points=_line(-5.25, FeatureType.SOLID),
        drive_count=np.ones(201, dtype=np.int64),
        lateral_std=np.zeros(201),
    )
    hdmap = HDMap(features=(edge,))
    xy = _line(0.0, FeatureType.SOLID, 0.0, 300.0)
    drive_points = {
        "divider": Detection(FeatureType.DASHED, _line(-5.25, FeatureType.DASHED, 0.0, 330.0)),
        "solid": Detection(FeatureType.SOLID, _line(1.75, FeatureType.SOLID, 0.0, 330.0)),
    }
    stamps = np.arange(len(xy), dtype=np.int64) * 10**8
    drive = Drive("d", xy, np.zeros(len(xy)), stamps, tuple(drive_points.values()))
    places = places_of([drive], cell_m=100.0)
    anchors = dict.fromkeys(places.keys(xy, drive.yaw), 0.0)
    ev = [e for e in edge_evidence(drive, solid_lines(hdmap), places, anchors) if np.isfinite(e.move_m)]
    assert ev and all(e.move_m == -MIN_EDGE_MOVE_M and not e.measured for e in ev)
    # the same drive seeing the edge solid still: no move
    drive = replace(drive, detections=(Detection(FeatureType.SOLID, _line(-5.25, FeatureType.SOLID, 0.0, 330.0)),))
    ev = [e for e in edge_evidence(drive, solid_lines(hdmap), places, anchors) if np.isfinite(e.move_m)]
    assert ev and all(abs(e.move_m) < 0.01 and e.measured for e in ev)


N_BEFORE, N_AFTER = 14, 4
SIM = SimConfig(
    n_drives=N_BEFORE + N_AFTER, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0
)
CLOSE = f"close:400-1100:fwd_lane2@{N_BEFORE}"


def _build(drives):
    r = build_map(list(drives), config=PipelineConfig(), seed=0, workers=1)
    return r.map, r.report


@pytest.mark.slow
def test_a_closed_lane_is_found_and_the_lanes_follow():
    road = synthetic_highway("motorway", length_m=1500.0)
    fleet = simulate_fleet(road, config=SIM, seed=5, changes=[parse_change(CLOSE)])
    result = follow_changes(fleet.drives, build=_build)
    assert any("lane_closed" in c.kinds for c in result.changes)
    zones = [change_zone(road, parse_change(CLOSE))]
    gt_now = fleet.extra["gt_after"]
    before = evaluate_zone_lanes(derive_lanes(result.first_map), gt_now, zones)
    after = evaluate_zone_lanes(derive_lanes(result.map), gt_now, zones)
    assert after.count_accuracy > before.count_accuracy + 0.3
    assert abs(after.mean_map_lanes - after.mean_gt_lanes) < abs(before.mean_map_lanes - before.mean_gt_lanes)
    z = evaluate_zone(result.map, gt_now, road, zones)
    assert z.ghost_share < evaluate_zone(result.first_map, gt_now, road, zones).ghost_share
    # the map outside the rebuilt places is the first map's: every feature that does not enter them is kept as is
    places = places_of(fleet.drives, cell_m=ChangeConfig().cell_m)
    assert result.rebuilt
    kept = {id(f) for f in result.map.features}
    for f in result.first_map.features:
        yaw = np.arctan2(*np.gradient(f.points, axis=0)[:, ::-1].T)
        if not set(places.keys(f.points, yaw)) & result.rebuilt:
            assert id(f) in kept
