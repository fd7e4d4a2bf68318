"""Change detection and map updating (hdmap_core/updates): a changed road is found with its change
point and the map follows it; a badly localised drive is not a change."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.evaluation.zone import evaluate_zone
from hdmap_core.model import Detection
from hdmap_core.parallel import SpareWork
from hdmap_core.pipeline.driver import PipelineConfig, build_map
from hdmap_core.simulation.changes import change_zone, parse_change
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import change_point, detect_changes
from hdmap_core.updates.edges import fleet_edge_evidence
from hdmap_core.updates.evidence import fleet_evidence
from hdmap_core.updates.follow import (
    cut_before_changes,
    drive_comparisons,
    fleet_comparison,
    follow_changes,
    own_side,
    unwrapped,
)
from hdmap_core.updates.places import places_of

N_BEFORE, N_AFTER = 14, 4
SIM = SimConfig(
    n_drives=N_BEFORE + N_AFTER, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0
)
CHANGE = f"shift:400-1100:1.5:fwd_lane2@{N_BEFORE}"


def _build(drives):
    r = build_map(list(drives), config=PipelineConfig(), seed=0, workers=1)
    return r.map, r.report


def _detect(drives, hdmap):
    places = places_of(drives, cell_m=ChangeConfig().cell_m)
    return detect_changes(fleet_evidence(drives, hdmap, places, config=ChangeConfig()), places), places


def _moved_left(drive, metres):
    left = np.stack([-np.sin(drive.yaw), np.cos(drive.yaw)], axis=1)
    mean_left = left.mean(axis=0) / np.linalg.norm(left.mean(axis=0))
    dets = tuple(Detection(d.type, d.points + metres * mean_left) for d in drive.detections)
    return type(drive)(drive.drive_id, drive.xy + metres * left, drive.yaw, drive.stamps_ns, dets, drive.vehicle_id)


@pytest.fixture(scope="module")
def road():
    return synthetic_highway("motorway", length_m=1500.0)


def test_change_point_needs_consistent_drives_after_and_a_clear_step():
    rng = np.random.default_rng(0)
    before = rng.normal(0.0, 0.05, 12)
    kw = {"min_effect": 0.5, "floor": 0.1, "z_min": 5.0, "min_before": 3, "min_after": 2}
    found = change_point(np.concatenate([before, [1.4, 1.5, 1.45]]), **kw)
    assert found is not None and found[0] == 12 and 1.3 < found[1] < 1.6
    assert change_point(before, **kw) is None
    assert change_point(np.concatenate([before, [1.5]]), **kw) is None  # one drive is no change
    assert change_point(np.concatenate([before, [1.5, 0.02, 1.4]]), **kw) is None  # not every one after
    assert change_point(np.concatenate([before, [0.3, 0.3]]), **kw) is None  # too small


@pytest.mark.slow
def test_a_shifted_road_is_found_and_a_badly_localised_drive_is_not(road):
    fleet = simulate_fleet(road, config=SIM, seed=5, changes=[parse_change(CHANGE)])
    drives = fleet.drives
    hdmap, _ = _build(drives)
    changes, places = _detect(drives, hdmap)
    assert len(changes) == 1
    (c,) = changes
    assert "geometry" in c.kinds  # a shift also moves lines out of sight of the map's: other kinds too
    assert drives[N_BEFORE - 1].start_ns < c.time_ns <= drives[N_BEFORE].start_ns
    assert set(c.drives_after) <= {d.drive_id for d in drives[N_BEFORE:]}
    zone = change_zone(road, parse_change(CHANGE))
    geometric = [p for p in c.places if p.kind == "geometry"]
    assert len(geometric) >= 3
    assert all(0.7 < p.effect < 2.0 for p in geometric)
    # the confirmed places lie on the zone's carriageway
    centers = np.array([[(p.key[0] + 0.5) * 100.0, (p.key[1] + 0.5) * 100.0] for p in c.places])
    assert np.min(np.linalg.norm(centers[:, None, :] - zone.piece()[None], axis=2), axis=1).max() < 80.0

    # The same fleet on the unchanged road, its last drives 2 m off everywhere: no change.
    plain = simulate_fleet(road, config=SIM, seed=5)
    bad = [*plain.drives[:N_BEFORE], *(_moved_left(d, 2.0) for d in plain.drives[N_BEFORE:])]
    bad_map, _ = _build(bad)
    found, places = _detect(bad, bad_map)
    assert found == []
    # the places' change tests on two processes: the serial changes, to the last bit
    shifted_places = places_of(drives, cell_m=ChangeConfig().cell_m)
    evidence = fleet_evidence(drives, hdmap, shifted_places, config=ChangeConfig())
    assert repr(detect_changes(evidence, shifted_places, workers=2)) == repr(changes)
    # ... though moving those drives 2 m moved their markings' offset against the map by 2 m:
    # their displacement against the borders did not move.
    moved_ev = fleet_evidence(bad[N_BEFORE:], bad_map, places, config=ChangeConfig())
    as_is_ev = fleet_evidence(plain.drives[N_BEFORE:], bad_map, places, config=ChangeConfig())
    as_is = {(e.drive_id, e.key): e for e in as_is_ev}
    pairs = [(e, as_is[(e.drive_id, e.key)]) for e in moved_ev if (e.drive_id, e.key) in as_is]
    pairs = [(a, b) for a, b in pairs if np.isfinite(a.displacement_m) and np.isfinite(b.displacement_m)]
    assert len(pairs) >= 10
    assert np.median([abs(a.offset_m - b.offset_m) for a, b in pairs]) > 1.8
    assert np.median([abs(a.displacement_m - b.displacement_m) for a, b in pairs]) < 0.2


@pytest.mark.slow
def test_the_map_follows_the_change_and_keeps_what_it_replaced(road):
    fleet = simulate_fleet(road, config=SIM, seed=5, changes=[parse_change(CHANGE)])
    result = follow_changes(fleet.drives, build=_build)
    assert len(result.changes) == 1
    zones = [change_zone(road, parse_change(CHANGE))]
    gt_now = fleet.extra["gt_after"]
    first = evaluate_zone(result.first_map, gt_now, road, zones)
    now = evaluate_zone(result.map, gt_now, road, zones)
    assert now.ghost_share < first.ghost_share - 0.2
    assert now.recall > first.recall + 0.2
    assert result.map.version == result.first_map.version + 1
    assert result.retired and all(r.valid_to_ns == result.changes[0].time_ns for r in result.retired)
    # drives before the change lost their part in the changed places, the others are whole
    places = places_of(fleet.drives, cell_m=ChangeConfig().cell_m)
    cut = cut_before_changes(fleet.drives, places, result.changes)
    after_ids = {d.drive_id for d in fleet.drives[N_BEFORE:]}
    assert after_ids <= {d.drive_id for d in cut}
    assert any("/" in d.drive_id for d in cut)


def test_no_change_leaves_the_map_as_built():
    calls = []

    def build(drives):
        calls.append(len(drives))
        return _empty_map(), None

    road = synthetic_highway("motorway", length_m=400.0)
    fleet = simulate_fleet(
        road, config=SimConfig(n_drives=2, snippet_length_min_m=200.0, snippet_length_max_m=300.0), seed=1
    )
    result = follow_changes(fleet.drives, build=build)
    assert result.changes == () and result.map is result.first_map and calls == [2]


def _empty_map():
    from hdmap_core.model import HDMap

    return HDMap()


def test_the_drives_compared_on_two_processes_give_the_serial_records(road):
    fleet = simulate_fleet(road, config=SIM, seed=5, changes=[parse_change("close:400-1100:fwd_lane2@14")])
    drives = fleet.drives
    hdmap, _ = _build(drives)
    places = places_of(drives, cell_m=ChangeConfig().cell_m)
    evidence = fleet_evidence(drives, hdmap, places, config=ChangeConfig())
    edges = fleet_edge_evidence(drives, hdmap, places, evidence, config=ChangeConfig())
    assert evidence and edges
    for workers in (2, 3):
        par_evidence, par_edges = fleet_comparison(drives, hdmap, places, config=ChangeConfig(), workers=workers)
        # repr: every field, NaN included, to the last bit of each float
        assert [repr(e) for e in par_evidence] == [repr(e) for e in evidence]
        assert [repr(e) for e in par_edges] == [repr(e) for e in edges]
    # the drives' own sides made ahead (every drive's in a spare process, or every other drive's)
    with SpareWork(lambda i: own_side(drives[i], ChangeConfig()), len(drives)) as spare:
        ahead = {drives[i].drive_id: side for i, side in spare.take(wait=True).items()}
    assert len(ahead) == len(drives)
    some = {d.drive_id: ahead[d.drive_id] for d in drives[::2]}
    for sides, workers in ((ahead, 1), (some, 2)):
        records = drive_comparisons(drives, hdmap, places, config=ChangeConfig(), workers=workers, sides=sides)
        got_evidence, got_edges = unwrapped(records, ChangeConfig())
        assert [repr(e) for e in got_evidence] == [repr(e) for e in evidence]
        assert [repr(e) for e in got_edges] == [repr(e) for e in edges]
    # made with other cuts: not used
    other = ChangeConfig(cut_step_m=2.0)
    stale = {d.drive_id: own_side(d, other) for d in drives}
    records = drive_comparisons(drives, hdmap, places, config=ChangeConfig(), sides=stale)
    assert [repr(e) for e in unwrapped(records, ChangeConfig())[0]] == [repr(e) for e in evidence]


def test_a_map_seen_as_detections_gives_the_drive_side_of_those_detections(road):
    # border_shift sees the rebuilt map from each drive: its lines indexed once must give the very
    # arrays drive_side makes of the drive with the map's features as its own detections
    from dataclasses import replace

    from hdmap_core.updates.evidence import drive_side, map_lines, side_of_lines

    fleet = simulate_fleet(road, config=SIM, seed=3)
    hdmap, _ = _build(fleet.drives[:6])
    dets = tuple(Detection(f.type, np.asarray(f.points, dtype=float)) for f in hdmap.features if len(f.points) >= 2)
    lines = map_lines(hdmap)
    for drive in fleet.drives[6:10]:
        want = drive_side(replace(drive, detections=dets), ChangeConfig())
        got = side_of_lines(drive, lines, ChangeConfig())
        assert len(want.d_cut) > 2 * len(want.center)  # several of the map's lines on each cut
        for name in ("center", "tangent", "yaw", "d_cut", "d_s", "d_t"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
