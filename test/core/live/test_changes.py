"""Road changes followed by the live map (hdmap_core/live/changes.py): bag2map's ``follow_map`` on
the settled map, only the changed places rebuilt; the history's documents and ids. The splice
itself is tested in test/core/updates/test_splice.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdmap_core.evaluation.zone import evaluate_zone
from hdmap_core.live.changes import (
    change_from_dict,
    change_polygon,
    change_to_dict,
    follow_live,
    follow_loaded,
    live_changes,
    new_changes,
)
from hdmap_core.pipeline.driver import PipelineConfig, build_map
from hdmap_core.simulation.changes import change_zone, parse_change
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import detect_changes
from hdmap_core.updates.evidence import fleet_evidence
from hdmap_core.updates.follow import FollowResult, follow_changes
from hdmap_core.updates.places import places_of
from hdmap_core.updates.splice import grow

N_BEFORE, N_AFTER = 14, 4
SIM = SimConfig(
    n_drives=N_BEFORE + N_AFTER, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0
)
CHANGE = f"shift:400-1100:1.5:fwd_lane2@{N_BEFORE}"


def test_polygon_history_document_and_new_changes():
    poly = change_polygon([(1, 0, 0), (2, 0, 0), (2, 1, 0)], 100.0)
    assert poly.shape[1] == 2
    assert poly[:, 0].min() == 100.0 and poly[:, 0].max() == 300.0 and poly[:, 1].max() == 200.0
    area = 0.5 * abs(np.dot(poly[:, 0], np.roll(poly[:, 1], 1)) - np.dot(poly[:, 1], np.roll(poly[:, 0], 1)))
    assert area == pytest.approx(35000.0)  # hull of the three cells: 3 squares + the half of one

    class _C:  # a DetectedChange's interface as new_changes uses it
        def __init__(self, i):
            self.id = i

    assert [c.id for c in new_changes({5: None}, [_C(5), _C(6)])] == [6]  # type: ignore[list-item]


@pytest.fixture(scope="module")
def moved_fleet():
    road = synthetic_highway("motorway", length_m=1500.0)
    fleet = simulate_fleet(road, config=SIM, seed=5, changes=[parse_change(CHANGE)])
    first = build_map(list(fleet.drives), config=PipelineConfig(), seed=0, workers=1).map
    return road, fleet, first


@pytest.mark.slow
def test_follow_live_finds_the_offline_change_and_rebuilds_only_its_region(moved_fleet):
    road, fleet, first = moved_fleet
    built = []

    def build(drives):
        built.append(list(drives))
        return build_map(list(drives), config=PipelineConfig(), seed=0, workers=1).map

    result = follow_live(first, fleet.drives, build=build)
    # the same change as the offline rule finds on the same map (same id: places and time)
    places = places_of(fleet.drives, cell_m=ChangeConfig().cell_m)
    offline = detect_changes(fleet_evidence(fleet.drives, first, places, config=ChangeConfig()), places)
    assert [c.id for c in result.changes] == [c.id for c in offline] and len(offline) == 1
    # one build, of the drives clipped to the rebuilt places (the changed ones and their tapers)
    # grown by the margin of 2 places; the map is the settled one outside the rebuilt places
    (region,) = built
    assert set(result.changes[0].keys) <= result.rebuilt
    margin = grow(places, result.rebuilt, 2)
    assert all(k in margin for d in region for k in places.keys(d.xy, d.yaw))
    every = {k for d in fleet.drives for k in places.keys(d.xy, d.yaw)}
    assert len(every & margin) < len(every)  # not the whole road
    # exactly bag2map's code: follow_changes with the settled map as its first build gives this map
    calls: list[int] = []

    def offline_build(drives):
        calls.append(len(drives))
        return (first if len(calls) == 1 else build(drives)), None

    offline_follow = follow_changes(fleet.drives, build=offline_build)
    assert calls[0] == len(fleet.drives) and len(calls) == 2
    assert [f.id for f in offline_follow.map.features] == [f.id for f in result.map.features]
    for a, b in zip(offline_follow.map.features, result.map.features):
        np.testing.assert_array_equal(a.points, b.points)
        assert (a.predecessors, a.successors) == (b.predecessors, b.successors)
    assert [(n.id, n.successors, n.features) for n in offline_follow.map.topology] == [
        (n.id, n.successors, n.features) for n in result.map.topology
    ]
    # the zone follows the road as it is now; the old pieces are retired with the change's time
    zones = [change_zone(road, parse_change(CHANGE))]
    gt_now = fleet.extra["gt_after"]
    before = evaluate_zone(first, gt_now, road, zones)
    now = evaluate_zone(result.map, gt_now, road, zones)
    assert now.ghost_share < before.ghost_share - 0.2
    assert now.recall > before.recall + 0.2
    assert result.retired and all(r.valid_to_ns == result.changes[0].time_ns for r in result.retired)
    # the announced change: its tiles, polygon and retired pieces, through a JSON round trip
    (c,) = live_changes(result, tile_size_m=256.0, map_version=first.version + 1, confirmed_ns=123)
    assert c.id == result.changes[0].id and c.map_version == first.version + 1
    assert set(c.retired_feature_ids) == {r.feature_id for r in result.retired}
    assert {(int(x // 256.0), int(y // 256.0)) for x, y in np.concatenate([r.points for r in c.retired])} <= set(
        c.tiles
    )
    back = change_from_dict(json.loads(json.dumps(change_to_dict(c))))
    assert back.id == c.id and back.places == c.places and back.tiles == c.tiles
    np.testing.assert_allclose(back.polygon, c.polygon)
    assert [r.feature_id for r in back.retired] == [r.feature_id for r in c.retired]


@pytest.mark.slow
def test_follow_loaded_on_two_workers_is_follow_live_on_one(moved_fleet):
    """The stitcher's worker process (drives loaded there, comparison and rebuild on every CPU, as
    bag2map) follows the change to the same map as one process."""
    _, fleet, first = moved_fleet

    def build(drives):
        return build_map(list(drives), config=PipelineConfig(), seed=0, workers=1).map

    one = follow_live(first, fleet.drives, build=build)
    two = follow_loaded(first, lambda: list(fleet.drives), pipeline_config=PipelineConfig(), workers=2)
    assert len(one.changes) == 1 and [c.id for c in two.changes] == [c.id for c in one.changes]
    assert [f.id for f in two.map.features] == [f.id for f in one.map.features]
    for a, b in zip(one.map.features, two.map.features):
        np.testing.assert_array_equal(a.points, b.points)


def test_no_change_keeps_the_map_and_builds_nothing():
    road = synthetic_highway("motorway", length_m=400.0)
    fleet = simulate_fleet(
        road, config=SimConfig(n_drives=4, snippet_length_min_m=300.0, snippet_length_max_m=400.0), seed=1
    )
    first = build_map(list(fleet.drives), config=PipelineConfig(), seed=0, workers=1).map

    def build(drives):
        raise AssertionError("nothing to rebuild")

    result = follow_live(first, fleet.drives, build=build)
    assert isinstance(result, FollowResult) and result.changes == () and result.map is first
    assert follow_live(first, [], build=build).map is first
