"""Road changes followed by the live map (hdmap_core/live/changes.py): the offline change rule on
the settled map, only the changed region rebuilt; the history's documents and ids."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hdmap_core.evaluation.zone import evaluate_zone
from hdmap_core.live.changes import (
    LiveFollow,
    change_from_dict,
    change_polygon,
    change_to_dict,
    follow_live,
    live_changes,
    new_changes,
    splice,
)
from hdmap_core.model import FeatureType, HDMap, MapFeature
from hdmap_core.pipeline.driver import PipelineConfig, build_map
from hdmap_core.simulation.changes import change_zone, parse_change
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import detect_changes
from hdmap_core.updates.evidence import fleet_evidence
from hdmap_core.updates.places import Places, places_of

N_BEFORE, N_AFTER = 14, 4
SIM = SimConfig(
    n_drives=N_BEFORE + N_AFTER, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0
)
CHANGE = f"shift:400-1100:1.5:fwd_lane2@{N_BEFORE}"


def _feature(fid, xs, y, pred=(), succ=()):
    pts = np.stack([np.asarray(xs, dtype=float), np.full(len(xs), float(y))], axis=1)
    n = len(pts)
    return MapFeature(fid, FeatureType.SOLID, pts, np.full(n, 5, dtype=np.uint16), np.full(n, 0.1), pred, succ)


def test_splice_replaces_exactly_the_changed_places_and_keeps_the_links_of_kept_ends():
    places = Places(100.0, {(i, 0): 0.0 for i in range(4)})  # a road along +x, cells 0..3
    changed = {(1, 0, 0), (2, 0, 0)}  # x in [100, 300) driving along +x
    xs = np.arange(0.0, 400.0, 5.0)
    inlet = _feature(3, [-50.0, -5.0], 50.0, succ=(1,))  # ends where line 1 starts
    line = _feature(1, xs, 50.0, pred=(3,), succ=(4,))
    outlet = _feature(4, [400.0, 450.0], 50.0, pred=(1,))
    into = _feature(5, [-50.0, -5.0], 30.0, succ=(6,))  # ends where 6 starts, inside the zone
    inside = _feature(6, xs[(xs >= 150) & (xs < 250)], 30.0, pred=(5,))
    short = _feature(7, xs[:10], 20.0)
    consensus = HDMap(features=(inlet, line, outlet, into, inside, short), version=3)
    rebuilt = HDMap(features=(_feature(1, xs, 51.5, pred=(3,)),))  # the same line, moved, everywhere
    out = splice(consensus, rebuilt, places, changed)
    ids = [f.id for f in out.features]
    assert len(ids) == len(set(ids)) and 6 not in ids  # a feature wholly inside is gone
    by_y = lambda y: [f for f in out.features if np.allclose(f.points[:, 1], y)]  # noqa: E731
    old = sorted((f for f in by_y(50.0) if len(f.points) > 2), key=lambda f: f.points[0, 0])
    (new,) = by_y(51.5)
    assert [(f.points[0, 0], f.points[-1, 0]) for f in old] == [(0.0, 95.0), (300.0, 395.0)]
    assert (new.points[0, 0], new.points[-1, 0]) == (100.0, 295.0) and new.id > 7
    assert new.predecessors == () and new.successors == ()  # rebuilt pieces: no links
    # the piece that starts where line 1 started keeps its id and its predecessor; the piece that
    # ends where it ended has a new id, the successor and the outlet's predecessor link
    head, tail = old
    assert head.id == 1 and head.predecessors == (3,) and head.successors == ()
    assert tail.id > 7 and tail.predecessors == () and tail.successors == (4,)
    got = {f.id: f for f in out.features}
    assert got[4].predecessors == (tail.id,) and got[3].successors == (1,)
    assert got[5].successors == ()  # its successor's start was inside the changed places
    assert got[7].points.shape == short.points.shape and out.version == 3


def test_polygon_history_document_and_new_changes():
    poly = change_polygon([(1, 0, 0), (2, 0, 0), (2, 1, 0)], 100.0)
    assert poly.shape[1] == 2
    assert poly[:, 0].min() == 100.0 and poly[:, 0].max() == 300.0 and poly[:, 1].max() == 200.0
    area = 0.5 * abs(np.dot(poly[:, 0], np.roll(poly[:, 1], 1)) - np.dot(poly[:, 1], np.roll(poly[:, 0], 1)))
    assert area == pytest.approx(35000.0)  # hull of the three cells: 3 squares + the half of one

    class _C:  # a DetectedChange's interface as new_changes uses it
        def __init__(self, i):
            self.id = i

    assert [c.id for c in new_changes({5: None}, [_C(5), _C(6)])] == [6]


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
    # one build, of the drives clipped to the changed places grown by the margin
    (region,) = built
    ij = np.array([k[:2] for k in result.changes[0].keys])
    lo, hi = ij.min(axis=0) * 100.0 - 128.0, (ij.max(axis=0) + 1) * 100.0 + 128.0
    pts = np.concatenate([d.xy for d in region])
    assert (pts >= lo).all() and (pts < hi).all()
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


def test_no_change_keeps_the_map_and_builds_nothing():
    road = synthetic_highway("motorway", length_m=400.0)
    fleet = simulate_fleet(
        road, config=SimConfig(n_drives=4, snippet_length_min_m=300.0, snippet_length_max_m=400.0), seed=1
    )
    first = build_map(list(fleet.drives), config=PipelineConfig(), seed=0, workers=1).map

    def build(drives):
        raise AssertionError("nothing to rebuild")

    result = follow_live(first, fleet.drives, build=build)
    assert isinstance(result, LiveFollow) and result.changes == () and result.map is first
    assert follow_live(first, [], build=build).map is first
