"""The map as it was before a change (hdmap_core/updates/before.py): where the consensus of every
drive has taken the new road, the drives are compared with the map of the drives before."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.evaluation.zone import evaluate_zone
from hdmap_core.model import Drive
from hdmap_core.pipeline.driver import PipelineConfig, build_map
from hdmap_core.simulation.changes import change_zone, parse_change
from hdmap_core.simulation.config import SimConfig
from hdmap_core.simulation.fleet import simulate_fleet
from hdmap_core.simulation.synthetic import synthetic_highway
from hdmap_core.updates.before import as_before, consensus_step, moved_consensus, with_neighbours
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import detect_changes
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.follow import (
    clip_to_places,
    cut_before_changes,
    drive_comparisons,
    drives_near_changes,
    fleet_comparison,
    follow_map,
    recompared,
    unwrapped,
)
from hdmap_core.updates.places import places_of
from hdmap_core.updates.splice import grow, splice

KW = {"min_effect": 0.5, "min_before": 3, "min_after": 2}


def test_a_step_split_between_the_drives_before_and_after_is_found():
    rng = np.random.default_rng(1)
    # the consensus of both took a line between: the drives before read +0.2, those after -0.2
    # (a 3 m move on 3.5 m lanes merged with the neighbour's old line), below the smallest shift
    before, after = 0.2 + rng.normal(0, 0.04, 11), -0.2 + rng.normal(0, 0.04, 10)
    assert consensus_step(np.concatenate([before, after]), **KW) == 11
    # a share that fell: the map took the new type, the drives after agree with it
    shares = np.concatenate([[0.3, 0.0, 0.44, 0.25, 0.31, 0.5, 0.28, 0.3, 0.35], [0.0, 0.05, 0.0, 0.16, 0.0]])
    # the earliest such step: the last drive before may fall on its after side (one in 4 may)
    assert consensus_step(shares, min_effect=0.3, min_before=3, min_after=3) == 8
    assert consensus_step(shares[:9], min_effect=0.3, min_before=3, min_after=3) is None


def test_no_step_in_scatter_nor_one_of_a_few_drives_or_without_half_the_drives_before():
    rng = np.random.default_rng(2)
    assert consensus_step(rng.normal(0, 0.1, 30), **KW) is None
    # one drive in 4 after may miss the line; two in four do not make a step
    mixed = np.concatenate([np.zeros(10), [-0.4, 0.0, -0.4, 0.0]])
    assert consensus_step(mixed, **KW) is None
    # a step after 3 of 12 drives: the map of 3 drives is a poorer consensus than the first map
    early = np.concatenate([np.full(3, 0.4), np.zeros(9)])
    assert consensus_step(early, **KW) is None
    # the earliest step, not the strongest: a step found late keeps drives of the new road before
    # (the larger step at 12), nor later than the first drive that shows it
    late = np.concatenate([np.zeros(10), [0.3, 0.3, 0.8, 0.8, 0.8, 0.8]])
    assert consensus_step(late, **KW) <= 10


def _ev(drive: str, t: int, key, displacement: float) -> PlaceEvidence:
    return PlaceEvidence(drive, t, key, 10, 0.0, 0.0, True, displacement, 20, 0, 0, 0, 0, 0, 0)


def test_candidate_places_take_their_group_s_median_time_and_their_neighbours():
    road = [
        Drive(f"d{i}", np.c_[np.arange(0.0, 700.0, 5.0), np.zeros(140)], np.zeros(140), np.arange(140) + i * 1000)
        for i in range(3)
    ]
    places = places_of(road, cell_m=100.0)
    keys = sorted({k for d in road for k in places.keys(d.xy, d.yaw)})
    assert len(keys) == 7
    evidence = []
    for i in range(12):
        for j, key in enumerate(keys):
            moved = 2 <= j <= 4 and i >= 6 + 2 * (j == 4)  # a step at drive 6, at drive 8 in the last place
            evidence.append(_ev(f"d{i}", i * 1000, key, -0.3 if moved else 0.0))
    found = moved_consensus(evidence, ChangeConfig())
    # (the last place's at drive 7: one drive in 4 after a step may not show it)
    assert found == {keys[2]: 6000, keys[3]: 6000, keys[4]: 7000}
    assert moved_consensus(evidence, ChangeConfig(), skip={keys[2]}) == {keys[3]: 6000, keys[4]: 7000}
    grown = with_neighbours(found, places)
    assert grown == {keys[1]: 6000, keys[2]: 6000, keys[3]: 6000, keys[4]: 6000, keys[5]: 6000}
    # two touching places are no group: a step there is the drives' scatter
    assert with_neighbours({keys[2]: 6000, keys[3]: 6000}, places) == {}
    assert with_neighbours({keys[0]: 1000, keys[2]: 6000, keys[3]: 6000, keys[4]: 7000}, places) == grown


def test_the_drives_cut_to_the_road_as_it_was():
    xy = np.c_[np.arange(0.0, 500.0, 2.0), np.zeros(250)]
    old = Drive("old", xy, np.zeros(250), np.arange(250, dtype=np.int64))
    new = Drive("new", xy, np.zeros(250), 10_000 + np.arange(250, dtype=np.int64))
    places = places_of([old], cell_m=100.0)
    key = places.keys(xy[100:101], np.zeros(1))[0]
    times = {key: 5_000}
    before = cut_before_changes([old, new], places, (), times=times, before=True)
    after = cut_before_changes([old, new], places, (), times=times)
    assert [d.drive_id for d in before] == ["old", "new/0", "new/1"]  # the new drive loses the place
    assert [d.drive_id for d in after] == ["old/0", "old/1", "new"]  # the old one there
    for d in (*before, *after):
        assert d.drive_id in ("old", "new") or key not in places.keys(d.xy, d.yaw)


@pytest.mark.parametrize("value", [np.nan])
def test_a_series_without_values_gives_no_candidate(value):
    key = (0, 0, 0)
    evidence = [_ev(f"d{i}", i, key, value) for i in range(12)]
    assert moved_consensus(evidence, ChangeConfig()) == {}


@pytest.mark.slow
def test_a_change_the_consensus_has_taken_is_confirmed_against_the_road_as_it_was():
    # 12 drives on the road as it was, 14 after a 3 m shift: the map of every drive holds the moved
    # lines blended with the old ones (3 m on 3.5 m lanes), and the drives against it show no change
    road = synthetic_highway("motorway", length_m=1500.0)
    change = parse_change("shift:400-1100:3.0:fwd_lane2@12")
    sim = SimConfig(n_drives=26, snippet_length_min_m=1300.0, snippet_length_max_m=1500.0, direction_bias=1.0)
    fleet = simulate_fleet(road, config=sim, seed=5, changes=[change])
    drives = fleet.drives

    def build(ds):
        return build_map(list(ds), config=PipelineConfig(), seed=0, workers=1).map

    first = build(drives)
    places = places_of(drives, cell_m=ChangeConfig().cell_m)
    evidence, _ = fleet_comparison(drives, first, places, config=ChangeConfig())
    assert detect_changes(evidence, places) == []
    assert moved_consensus(evidence, ChangeConfig())  # where the consensus moved
    result = follow_map(first, drives, build=build)
    assert len(result.changes) == 1
    (c,) = result.changes
    assert "geometry" in c.kinds and c.time_ns == drives[12].start_ns
    assert set(c.drives_after) <= {d.drive_id for d in drives[12:]}
    zones = [change_zone(road, change)]
    now = fleet.extra["gt_after"]
    plain, followed = evaluate_zone(first, now, road, zones), evaluate_zone(result.map, now, road, zones)
    assert followed.recall > plain.recall + 0.05 and followed.precision > plain.precision + 0.1


@pytest.mark.slow
def test_only_the_drives_near_the_road_as_it_was_are_compared_again():
    # the fleet above with drives of 300-800 m: some pass the moved place, some (5 of 26) stay clear of it
    road = synthetic_highway("motorway", length_m=1500.0)
    change = parse_change("shift:400-1100:3.0:fwd_lane2@12")
    sim = SimConfig(n_drives=26, snippet_length_min_m=300.0, snippet_length_max_m=800.0, direction_bias=1.0)
    drives = simulate_fleet(road, config=sim, seed=5, changes=[change]).drives

    def build(ds):
        return build_map(list(ds), config=PipelineConfig(), seed=0, workers=1).map

    config = ChangeConfig()
    first = build(drives)
    places = places_of(drives, cell_m=config.cell_m)
    records = drive_comparisons(drives, first, places, config=config)
    evidence, _ = unwrapped(records, config)
    taken = with_neighbours(moved_consensus(evidence, config), places)
    assert taken
    pieces = clip_to_places(
        cut_before_changes(drives, places, (), times=taken, before=True), places, grow(places, taken, 2)
    )
    reference = splice(first, as_before(first, build(pieces), pieces, places, set(taken)), places, set(taken))
    again = drives_near_changes(drives, first, reference, config.view_m + 1.0)
    assert 0 < len(again) < len(drives)  # some drives keep their first records
    partial = recompared(records, drives, first, reference, places, config=config)
    full = drive_comparisons(drives, reference, places, config=config)
    # repr: every field, NaN included, to the last bit of each float; per drive and unwrapped
    assert [repr(r) for r in partial] == [repr(r) for r in full]
    two = recompared(records, drives, first, reference, places, config=config, workers=2)
    assert [repr(r) for r in two] == [repr(r) for r in full]
    for got, want in zip(unwrapped(partial, config), fleet_comparison(drives, reference, places, config=config)):
        assert [repr(e) for e in got] == [repr(e) for e in want]
    # the reference matters: some drives compared again read otherwise than against the first map
    assert any(repr(records[i]) != repr(full[i]) for i in again)


def test_the_edge_line_the_consensus_took_is_a_candidate():
    # an opened lane: at places 3-5 the map of every drive holds the new edge line 2.5 m out, so
    # the 8 drives before read the old edge 2.5 m inside it and the 3 after read ~0; at place 6 the
    # map still has the old edge (the drives before read ~0, those after -2.5): a change itself,
    # which follow_map skips once confirmed. Each steps at drive 7 (the earliest split with 3 of
    # the 4 after it on the step's side: one drive of the old road among them at most)
    from hdmap_core.updates.edges import EdgeEvidence

    rng = np.random.default_rng(2)
    edges = []
    for d in range(11):
        for i in (3, 4, 5, 6):
            took = i < 6
            move = (2.5 if d < 8 else 0.0) if took else (0.0 if d < 8 else -2.5)
            edges.append(EdgeEvidence(f"d{d:02d}", d * 100, (i, 0, 0), move + rng.normal(0, 0.08), 10))
    got = moved_consensus([], ChangeConfig(), edges=edges)
    assert got == {(i, 0, 0): 700 for i in (3, 4, 5, 6)}
    assert moved_consensus([], ChangeConfig()) == {}
    # the edge read alike by every drive (no change, the drives' scatter): none
    calm = [EdgeEvidence(e.drive_id, e.time_ns, e.key, rng.normal(0, 0.1), 10) for e in edges]
    assert moved_consensus([], ChangeConfig(), edges=calm) == {}
