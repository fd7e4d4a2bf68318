"""Road changes (simulation/changes.py), the simulator's drives over a changing road, and the
changed zone scored apart (evaluation/zone.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.errors import ConfigError, GroundTruthError
from hdmap_core.evaluation.evaluate import hdmap_from_ground_truth
from hdmap_core.evaluation.zone import evaluate_zone
from hdmap_core.model import FeatureType
from hdmap_core.simulation.changes import (
    RoadChange,
    apply_change,
    change_zone,
    changes_from_dict,
    parse_change,
    road_as_of,
    zone_mask,
)
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway


@pytest.fixture(scope="module")
def road():
    return synthetic_highway("motorway", length_m=1500.0)


def _lateral(zone, pts):
    _, j = zone.tree.query(pts)
    t = zone.tangents[j]
    v = pts - zone.line[j]
    return t[:, 0] * v[:, 1] - t[:, 1] * v[:, 0]


def test_parse_change_reads_the_text_form_and_names_what_is_wrong():
    c = parse_change("shift:1000-2000:1.5:fwd_lane1@40")
    assert (c.kind, c.from_m, c.to_m, c.size, c.route_id, c.after_drive) == (
        "shift",
        1000.0,
        2000.0,
        1.5,
        "fwd_lane1",
        40,
    )
    assert parse_change(c.text()) == c
    assert parse_change("restripe:10-500@3").size is None
    assert parse_change("remove:10-500:fwd_lane2@3").route_id == "fwd_lane2"
    for bad in ("shift:1000-2000", "warp:0-500@1", "shift:500-100@1", "add:0-500@1", "shift:0-150@1"):
        with pytest.raises(ConfigError):
            parse_change(bad)


def test_shift_moves_lines_and_lanes_of_one_carriageway_but_not_borders(road):
    change = RoadChange("shift", 400.0, 1100.0, 1.5, "fwd_lane2")
    after = apply_change(road, change)
    zone = change_zone(road, change)
    moved_any = False
    for f, g in zip(road.features, after.features):
        assert f.id == g.id and f.type == g.type and len(f.points) == len(g.points)
        d = np.linalg.norm(g.points - f.points, axis=1)
        tang = np.gradient(f.points, axis=0)
        inside = zone_mask(zone, f.points, tang)
        full = zone_mask(_core(zone), f.points, tang)
        if f.type == FeatureType.ROAD_BORDER or not inside.any():
            assert d.max() == 0.0  # borders and the other carriageway stay
            continue
        moved_any = True
        assert d[~inside].max() == 0.0
        assert np.allclose(d[full], 1.5, atol=0.01)
        # to the right of the driving direction
        assert np.all(_lateral(zone, g.points[full]) < _lateral(zone, f.points[full]) - 1.4)
    assert moved_any
    lane = next(lid for lid in road.lanes if lid.startswith("fwd"))
    assert road.lanes[lane].centerline.shape == after.lanes[lane].centerline.shape


def _core(zone):
    """The zone less its tapers."""
    return type(zone)(zone.line, zone.s, zone.from_m + 100.0, zone.to_m - 100.0)


def test_restripe_and_remove_act_inside_the_zone_only(road):
    change = RoadChange("restripe", 400.0, 1100.0, None, "fwd_lane2")
    after = apply_change(road, change)
    zone = change_zone(road, change)

    inside_dashed = [
        f
        for f in after.features
        if f.type == FeatureType.DASHED and zone_mask(zone, f.points, np.gradient(f.points, axis=0))[1:-1].any()
    ]
    assert inside_dashed == []
    n_dashed_before = sum(len(f.points) for f in road.features if f.type == FeatureType.DASHED)
    n_dashed_after = sum(len(f.points) for f in after.features if f.type == FeatureType.DASHED)
    assert 0 < n_dashed_after < n_dashed_before
    ids = [f.id for f in after.features]
    assert len(ids) == len(set(ids))
    removed = apply_change(road, RoadChange("remove", 400.0, 1100.0, 2, "fwd_lane2"))
    assert sum(len(f.points) for f in removed.features) < sum(len(f.points) for f in road.features)
    with pytest.raises(GroundTruthError):
        apply_change(road, RoadChange("remove", 400.0, 1100.0, 9, "fwd_lane2"))
    with pytest.raises(GroundTruthError):
        apply_change(road, RoadChange("shift", 400.0, 1100.0, 1.0, "no_such_route"))


@pytest.mark.slow
def test_drives_after_a_change_see_the_changed_road_a_day_later(road):
    change = parse_change("shift:400-1100:1.5:fwd_lane2@6")
    cfg = SimConfig(n_drives=8, snippet_length_min_m=600.0, snippet_length_max_m=1400.0, direction_bias=1.0)
    plain = simulate_fleet(
        road,
        config=SimConfig(n_drives=6, snippet_length_min_m=600.0, snippet_length_max_m=1400.0, direction_bias=1.0),
        seed=3,
    )
    fleet = simulate_fleet(road, config=cfg, seed=3, changes=[change])
    for a, b in zip(plain.drives, fleet.drives[:6]):  # before the change: the same drives
        assert np.array_equal(a.xy, b.xy) and a.stamps_ns[0] == b.stamps_ns[0]
    (timed,) = fleet.extra["changes"]
    assert fleet.drives[5].stamps_ns[-1] < timed.time_ns < fleet.drives[6].stamps_ns[0]
    assert fleet.drives[6].start_ns - fleet.drives[5].start_ns > 86_000e9
    assert fleet.extra["gt_before"] is road
    assert road_as_of(road, [timed], timed.time_ns - 1) is road
    after = road_as_of(road, [timed], timed.time_ns)
    assert all(np.array_equal(f.points, g.points) for f, g in zip(after.features, fleet.extra["gt_after"].features))


def test_the_zone_scores_the_current_road_and_finds_ghosts_of_the_old(road):
    change = RoadChange("shift", 400.0, 1100.0, 1.5, "fwd_lane2", time_ns=5)
    after = apply_change(road, change)
    zone = change_zone(road, change)
    doc = {"changes": [{**change.to_dict(), "zone": zone.to_dict()}]}
    changes, zones = changes_from_dict(doc)
    assert changes == [change]
    new = evaluate_zone(hdmap_from_ground_truth(after), after, road, zones)
    old = evaluate_zone(hdmap_from_ground_truth(road), after, road, zones)
    assert new.n_cuts > 300
    assert new.recall > 0.99 and new.precision > 0.99 and new.mean_m < 0.01 and new.ghost_share == 0.0
    assert old.recall < 0.6 and old.ghost_share > 0.3 and old.old_recall > 0.99


def test_close_moves_the_edge_onto_the_divider_and_the_lane_into_its_neighbour(road):
    change = RoadChange("close", 400.0, 1100.0, None, "fwd_lane2")
    after = apply_change(road, change)
    zone = change_zone(road, change)
    core = _core(zone)
    by_id = {f.id: f for f in road.features}
    moved = [
        f
        for f in after.features
        if f.id in by_id
        and len(f.points) == len(by_id[f.id].points)
        and np.abs(f.points - by_id[f.id].points).max() > 0
    ]
    (edge,) = moved
    assert edge.type == FeatureType.SOLID
    full = zone_mask(core, edge.points, np.gradient(edge.points, axis=0))
    shift = _lateral(zone, edge.points[full]) - _lateral(zone, by_id[edge.id].points[full])
    assert np.allclose(shift, 3.5, atol=0.05)  # onto the divider, 3.5 m left
    # no dashed marking is left inside the zone on that side: the divider is gone
    for f in after.features:
        if f.type == FeatureType.DASHED:
            inside = zone_mask(core, f.points, np.gradient(f.points, axis=0))
            assert not (inside & (_lateral(zone, f.points) < -4.0)).any()
    closed = [lid for lid in road.lanes if np.abs(after.lanes[lid].centerline - road.lanes[lid].centerline).max() > 3.0]
    assert closed and all(lid.startswith("fwd") and lid.endswith(":3") for lid in closed)


def test_open_moves_the_edge_out_and_draws_a_divider(road):
    after = apply_change(road, RoadChange("open", 400.0, 1100.0, 2.5, "fwd_lane2"))
    assert len(after.features) == len(road.features) + 1
    new = after.features[-1]
    assert new.type == FeatureType.DASHED and new.id > max(f.id for f in road.features)
    with pytest.raises(ConfigError):
        parse_change("open:400-1100@1")


def test_open_keeps_the_moved_edge_within_the_road_border(road):
    """The synthetic motorway's hard shoulder is 2.5 m (edge line to road border): an opening of
    up to 2.5 m puts the moved edge on or inside the border, a wider one is refused, naming the
    largest SIZE there."""
    change = RoadChange("open", 400.0, 1100.0, 2.5, "fwd_lane2")
    after = apply_change(road, change)
    zone = change_zone(road, change)
    core = _core(zone)
    borders = [f for f in after.features if f.type == FeatureType.ROAD_BORDER]
    edge = min(
        (f for f in after.features if f.type == FeatureType.SOLID and zone_mask(core, f.points).any()),
        key=lambda f: np.median(_lateral(zone, f.points[zone_mask(core, f.points)])),
    )
    lat_edge = _lateral(zone, edge.points[zone_mask(core, edge.points)])
    lat_border = max(
        np.median(lat)
        for f in borders
        if (lat := _lateral(zone, f.points[zone_mask(core, f.points)])).size and np.median(lat) < 0
    )
    assert np.allclose(lat_edge, lat_border, atol=0.02)  # on the border, not beyond it
    for size in (2.6, 3.0):
        with pytest.raises(GroundTruthError, match=r"beyond the road border.*at most SIZE 2\.50 m"):
            apply_change(road, RoadChange("open", 400.0, 1100.0, size, "fwd_lane2"))


def test_open_adds_the_new_lane_linked_to_its_neighbour(road):
    change = RoadChange("open", 400.0, 1100.0, 2.0, "fwd_lane2")
    after = apply_change(road, change)
    zone = change_zone(road, change)
    (new,) = set(after.lanes) - set(road.lanes)
    lane = after.lanes[new]
    divider = after.features[-1]
    # midway between the new divider (the old edge) and the moved edge: 1 m right of the divider
    lat = _lateral(zone, lane.centerline)
    assert np.allclose(lat, np.median(_lateral(zone, divider.points)) - 1.0, atol=0.05)
    (first,), (last,) = lane.predecessors, lane.successors
    assert new in after.lanes[first].successors and new in after.lanes[last].predecessors
    assert first.endswith(":3") and last.endswith(":3") and lane.left is not None and lane.left.endswith(":3")
    # the drives do not use it: no lane has it as its neighbour, so the simulated drives stay as they were
    assert all(new not in (ln.left, ln.right) for ln in after.lanes.values())


def test_the_zone_lane_count_follows_the_road_s_lanes(road):
    """The road's lane count in the zone comes from its lane centerlines: one more lane where the
    shoulder opened, one fewer where a lane closed (its centerline runs on its neighbour's)."""
    from dataclasses import replace

    from hdmap_core.evaluation.zone import evaluate_zone_lanes
    from hdmap_core.lanes.model import LaneMap

    for kind, size, lanes in (("open", 2.0, 4.0), ("close", None, 2.0)):
        change = RoadChange(kind, 400.0, 1100.0, size, "fwd_lane2")
        after = apply_change(road, change)
        core = replace(change_zone(road, change), from_m=550.0, to_m=950.0)
        rep = evaluate_zone_lanes(LaneMap(), after, [core])
        assert rep.n_cuts > 50 and rep.mean_gt_lanes == pytest.approx(lanes), kind
        assert rep.count_accuracy == 0.0 and rep.mean_map_lanes == 0.0
    # the opened lane's split and merge are links of the zone; an empty map has none of them
    full = evaluate_zone_lanes(
        LaneMap(), apply_change(road, RoadChange("open", 400.0, 1100.0, 2.0, "fwd_lane2")), [change_zone(road, change)]
    )
    assert full.n_links >= 2 and full.links_ok == 0


def _lane(lid: int, centerline: np.ndarray, half_m: float, succ: tuple[int, ...] = ()):
    """A map lane piece along ``centerline`` with solid sides ``half_m`` to each side (no lane changes)."""
    from hdmap_core.geometry import turn_left, unit_tangents
    from hdmap_core.lanes.model import Boundary, Lane

    left = turn_left(unit_tangents(centerline))
    sides = [
        Boundary(10 * lid + k, 0, FeatureType.SOLID, centerline + sign * half_m * left, 0, 0)
        for k, sign in ((1, 1.0), (2, -1.0))
    ]
    lane = Lane(
        lid,
        centerline,
        np.full(len(centerline), 2 * half_m),
        sides[0].id,
        sides[1].id,
        0,
        0,
        FeatureType.SOLID,
        FeatureType.SOLID,
        successors=succ,
    )
    return lane, sides


def test_the_opened_lane_s_split_and_merge_are_probed_where_it_parts_and_joins(road):
    """The road links the opened lane to the right lane's pieces at its two ends, which run on past
    its start and began before its end: the split is probed at the opened lane's start, the merge
    at its end (probing at the right piece's end and the next piece's start looked for the lane
    before the joint after the one behind it). A map whose right lane is cut where the opened lane
    starts and ends, linked only by successors, has both; without the link, not."""
    from hdmap_core.evaluation.zone import evaluate_zone_lanes
    from hdmap_core.geometry import arc_length
    from hdmap_core.lanes.model import LaneMap

    change = RoadChange("open", 600.0, 1300.0, 2.5, "fwd_lane2")  # the opened lane: 700-1200 m
    after = apply_change(road, change)
    zone = change_zone(road, change)
    opened = after.lanes["opened"]
    (first,), (last,) = opened.predecessors, opened.successors
    right = np.concatenate([after.lanes[x].centerline for x in ("fwd:0:3", first, last)])
    right = right[np.r_[True, np.hypot(*np.diff(right, axis=0).T) > 1e-6]]
    s = arc_length(right)
    ends = [int(np.argmin(np.hypot(*(right - p).T))) for p in (opened.centerline[0], opened.centerline[-1])]
    assert 0 < ends[0] < ends[1] < len(right) - 1
    pieces = np.split(np.arange(len(right)), ends)
    r = [right[np.r_[p, p[-1] + 1] if p[-1] + 1 < len(right) else p] for p in pieces]
    assert s[ends[0]] - s[0] > 100.0 and s[-1] - s[ends[1]] > 100.0

    def lane_map(split: bool, merge: bool) -> LaneMap:
        parts = [
            _lane(1, r[0], 1.75, (2, 4) if split else (2,)),
            _lane(2, r[1], 1.75, (3,)),
            _lane(3, r[2], 1.75),
            _lane(4, opened.centerline, 1.25, (3,) if merge else ()),
        ]
        return LaneMap(tuple(p[0] for p in parts), tuple(b for p in parts for b in p[1]))

    full = evaluate_zone_lanes(lane_map(True, True), after, [zone])
    # the five links: the three lanes' piece joints in the zone, the split and the merge; the map
    # has the right lane's joint (inside its piece 2), the split and the merge, not the other lanes
    assert full.n_links == 5 and full.links_ok == 3
    assert evaluate_zone_lanes(lane_map(False, True), after, [zone]).links_ok == 2
    assert evaluate_zone_lanes(lane_map(True, False), after, [zone]).links_ok == 2
