"""Lanes derived from hand-made maps (sketches in test/support/lane_samples.py)."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.lanes.derive import LANELET_MAX_M, derive_lanes
from hdmap_core.lanes.lane_graph import lane_graph, lane_route, lanes_at, reachable_lanes
from hdmap_core.model import FeatureType, HDMap

from lane_samples import (
    handover,
    junction_gap,
    lane_gain,
    lines_stop,
    missing_marking,
    taper_open,
    three_lanes,
    two_way,
)


def _lane_at(lanes, x: float, y: float) -> int:
    return int(lanes_at(lanes, np.array([[x, y]]), np.array([0.0]))[0])


def test_three_lanes_centerlines_sides_and_pieces():
    lanes = derive_lanes(three_lanes())
    # 3 lanes, each cut into pieces of at most LANELET_MAX_M (800 m -> 3 pieces)
    assert len(lanes.lanes) == 9
    assert all(ln.length_m <= LANELET_MAX_M + 4.0 for ln in lanes.lanes)
    ys = sorted({round(float(np.median(ln.centerline[:, 1])), 2) for ln in lanes.lanes})
    np.testing.assert_allclose(ys, [-3.5, 0.0, 3.5], atol=1e-6)
    np.testing.assert_allclose(np.concatenate([ln.width for ln in lanes.lanes]), 3.5, atol=1e-6)
    mid = lanes.lane(_lane_at(lanes, 100.0, 0.0))
    assert mid.left_type == mid.right_type == FeatureType.DASHED
    assert mid.change_left and mid.change_right
    left = lanes.lane(mid.left)
    assert left.left_type == FeatureType.SOLID and left.left is None and not left.change_left
    assert left.right == mid.id and left.right_feature == 3 and left.left_feature == 2


def test_three_lanes_successors_follow_shared_nodes():
    lanes = derive_lanes(three_lanes())
    g = lane_graph(lanes)
    start, end = _lane_at(lanes, 10.0, 3.5), _lane_at(lanes, 790.0, -3.5)
    route = lane_route(g, start, end)
    assert route is not None and route[0] == start and route[-1] == end
    first = lanes.lane(start)
    assert len(first.successors) == 1 and not first.predecessors
    nxt = lanes.lane(first.successors[0])
    lb, nb = lanes.boundary(first.left_boundary), lanes.boundary(nxt.left_boundary)
    assert lb.end_node == nb.start_node
    # no way back against the direction
    assert lane_route(g, end, start) is None
    assert start in reachable_lanes(g, start) and end in reachable_lanes(g, start)


def test_ids_are_stable():
    a, b = derive_lanes(three_lanes()), derive_lanes(three_lanes())
    assert [ln.id for ln in a.lanes] == [ln.id for ln in b.lanes]
    assert [x.id for x in a.boundaries] == [x.id for x in b.boundaries]


def test_lane_gain_opens_beside_the_through_lane():
    lanes = derive_lanes(lane_gain())
    new = _lane_at(lanes, 600.0, -7.0)
    through = _lane_at(lanes, 600.0, -3.5)
    before = _lane_at(lanes, 100.0, -3.5)
    assert new and through and before and new != through
    g = lane_graph(lanes)
    assert lane_route(g, before, new) is not None  # across the new dashed line or as a split
    assert lane_route(g, _lane_at(lanes, 100.0, 3.5), new) is not None
    # the exit lane is not a strip of two lanes' width anywhere after the dashed line starts
    widths = np.concatenate([ln.width[ln.centerline[:, 0] > 460.0] for ln in lanes.lanes])
    assert widths.max() < 4.0


def test_missing_marking_is_inferred_between_two_lanes():
    lanes = derive_lanes(missing_marking())
    at = [lanes.lane(_lane_at(lanes, x, -3.5)) for x in (50.0, 250.0, 550.0)]
    assert all(at)
    gap = at[1]
    np.testing.assert_allclose(np.median(gap.centerline[:, 1]), -3.5, atol=0.05)
    left = lanes.boundary(gap.left_boundary)
    assert left.inferred and left.feature_id == 0 and left.type == FeatureType.DASHED
    assert gap.left_feature == 0 and gap.change_left
    g = lane_graph(lanes)
    assert lane_route(g, at[0].id, at[2].id) is not None


def test_connectors_cross_a_junction_without_markings():
    lanes = derive_lanes(junction_gap())
    g = lane_graph(lanes)
    for y in (3.5, 0.0, -3.5):
        before, after = _lane_at(lanes, 290.0, y), _lane_at(lanes, 340.0, y)
        route = lane_route(g, before, after)
        assert route is not None
        inside = [lanes.lane(i) for i in route if i not in (before, after)]
        # the way through is one connector with virtual sides, in the lane's line
        assert len(inside) == 1 and inside[0].left_type == FeatureType.UNKNOWN
        np.testing.assert_allclose(inside[0].centerline[:, 1], y, atol=0.05)
    # side by side connectors share their virtual side, and no lane change crosses it
    connectors = [ln for ln in lanes.lanes if ln.left_type == FeatureType.UNKNOWN]
    assert len(connectors) == 3 and sum(ln.left is not None for ln in connectors) == 2
    assert not any(ln.change_left or ln.change_right for ln in connectors)


def test_lanes_are_not_cut_where_a_line_is_handed_over_or_its_type_flickers():
    """RULE 10: the edge line taken over by another feature 0.7 m out, and a 6 m stretch of a
    dashed line mapped as solid, change nothing in the lane structure: 3 lanes, one piece each."""
    lanes = derive_lanes(handover())
    assert len(lanes.lanes) == 3
    assert all(ln.length_m > 240.0 for ln in lanes.lanes)
    mid = lanes.lane(_lane_at(lanes, 150.0, 0.0))
    assert mid.right_type == FeatureType.DASHED and mid.change_right
    # the feature hand-over: one boundary piece, the first feature most of its length
    left = lanes.lane(mid.left)
    assert lanes.boundary(left.left_boundary).feature_id == 12


def test_two_way_road_lane_beside_a_centre_line_mapped_the_other_way():
    """RULE 12: the centre line, mapped westbound only, bounds the eastbound lane on its left; the
    eastbound border (a road border against the westbound direction) bounds no westbound lane."""
    lanes = derive_lanes(two_way())
    east = [ln for ln in lanes.lanes if ln.centerline[-1, 0] > ln.centerline[0, 0]]
    west = [ln for ln in lanes.lanes if ln.centerline[-1, 0] < ln.centerline[0, 0]]
    assert len(east) == len(west) == 1
    np.testing.assert_allclose(east[0].centerline[:, 1], -2.0, atol=1e-6)
    np.testing.assert_allclose(west[0].centerline[:, 1], 2.0, atol=1e-6)
    assert east[0].left_feature == west[0].left_feature == 3 and east[0].left_type == FeatureType.DASHED
    assert east[0].right_type == FeatureType.ROAD_BORDER
    # no lane change into the oncoming lane
    assert east[0].left is None and not east[0].change_left


@pytest.mark.parametrize("hdmap", [HDMap(), HDMap(features=three_lanes().features)])
def test_no_topology_or_features_gives_no_lanes(hdmap):
    lanes = derive_lanes(hdmap)
    assert lanes.lanes == () and lanes.boundaries == ()


def test_two_lines_handed_over_to_one_heir_keep_two_tracks():
    """RULE 10: line A ends, B takes it over (0.3 m aside), B pauses and C takes over, then B is
    back beside C: each cross section keeps one track per line (one track for both gave a lane of
    width 0 between them on paper_like and lost the lane beside)."""
    from hdmap_core.lanes.derive import _handover, _Section, _Stations

    k = 5
    st = _Stations(
        np.arange(k, dtype=np.int64),
        np.stack([2.0 * np.arange(k), np.zeros(k)], axis=1),
        np.tile([1.0, 0.0], (k, 1)),
        np.full(k, 10.0),
        [[i + 1] for i in range(k - 1)] + [[]],
    )
    st.relink()
    rows = [[(1, 0.0)], [(2, 0.3)], [(3, 0.6)], [(2, 0.3), (3, -3.0)], [(2, 0.3), (3, -3.0)]]
    sections = [
        _Section(tuple(t for t, _ in r), tuple(0 for _ in r), np.array([s for _, s in r]), np.zeros((len(r), 2)))
        for r in rows
    ]
    out = _handover(st, sections, [int(FeatureType.DASHED)])
    assert all(len(set(sec.features)) == len(sec.features) for sec in out)
    assert out[0].features == out[1].features == out[2].features  # one line handed over twice
    assert out[3].features == out[4].features  # and the two lines keep their tracks after


def test_lanes_whose_lines_stop_together_end_where_they_are():
    """RULE 4b: where the lines of two lanes stop at once beside a lane that goes on (a junction
    whose markings stop), the two lanes end a lane wide where their lines end; they do not all
    close onto the line that continues (the drives' connectors start at the lanes' ends)."""
    lanes = derive_lanes(lines_stop())
    ending = sorted(
        (ln for ln in lanes.lanes if not ln.successors and ln.centerline[-1, 0] < 410.0),
        key=lambda ln: -ln.centerline[-1, 1],
    )
    assert len(ending) == 2
    np.testing.assert_allclose([ln.centerline[-1, 1] for ln in ending], [0.0, -3.5], atol=0.2)
    assert all(ln.width[-1] > 3.0 for ln in ending)
    assert _lane_at(lanes, 600.0, 3.5) and not _lane_at(lanes, 600.0, 0.0)


def _routable(lanes, a: tuple[float, float], b: tuple[float, float]) -> bool:
    la, lb = _lane_at(lanes, *a), _lane_at(lanes, *b)
    return bool(la and lb and lane_route(lane_graph(lanes), la, lb) is not None)


def test_a_lane_opened_in_a_taper_splits_off_and_merges_back_beside_the_through_lane():
    """RULE 15: in the tapers the strip between the divider and the moving edge is 5.5-6.0 m wide
    (one lane too wide, too narrow for two); the dashed line that starts after the taper is
    continued back through it as an inferred line, so the through lane keeps its 3.5 m there, and
    the opened lane is reached from it (the split) and reaches it again (the merge): 15 m before
    and after the dashed line's ends, as the zone's link probes ask."""
    lanes = derive_lanes(taper_open())
    for x in (485.0, 815.0):  # in the tapers, strip 5.85 m: the through lane, 3.5 m wide
        through = lanes.lane(_lane_at(lanes, x, -3.5))
        np.testing.assert_allclose(np.median(through.width), 3.5, atol=0.05)
        right = lanes.boundary(through.right_boundary)
        assert right.inferred and right.type == FeatureType.DASHED
        # where the new lane is born (dies) the line starts (ends) on the edge line (RULE 4)
        np.testing.assert_allclose(right.points[1:-1, 1], -5.25, atol=0.05)
    assert _routable(lanes, (485.0, -3.5), (515.0, -6.5))  # split
    assert _routable(lanes, (785.0, -6.5), (815.0, -3.5))  # merge
    opened = lanes.lane(_lane_at(lanes, 650.0, -6.5))
    np.testing.assert_allclose(np.median(opened.width), 2.5, atol=0.05)
    # the narrow part of the new lane in the tapers is no lane: one lane right of -1.75 there
    for x in (430.0, 470.0, 830.0, 870.0):
        assert _lane_at(lanes, x, -3.5) and not _lane_at(lanes, x, -6.0)


def test_cut_lines_reach_the_lines_where_the_road_width_of_the_nodes_dips():
    """RULE 16: the nodes at 460-500 m estimate the road 9 m wide and 3 m left of its middle; their
    cut lines reach as far as those of the nodes around them, so the moving edge is still crossed
    and the split found as without the dip."""
    lanes = derive_lanes(taper_open(dip=True))
    through = lanes.lane(_lane_at(lanes, 485.0, -3.5))
    np.testing.assert_allclose(np.median(through.width), 3.5, atol=0.05)
    assert _routable(lanes, (485.0, -3.5), (515.0, -6.5))


def test_a_taper_keeps_the_through_lane_when_the_lane_gained_is_the_wider_one():
    """RULE 15's side: a 3.0 m lane opened beside a 2.75 m through lane (a works zone). The divider
    is continued at its distance from the line that runs on (the lane divider -1.75, whose distance
    to the line left of it stays), not from the moving edge, although the lane on that side is the
    wider one."""
    lanes = derive_lanes(taper_open(size_m=3.0, lane_m=2.75))
    through = lanes.lane(_lane_at(lanes, 485.0, -3.1))
    np.testing.assert_allclose(np.median(through.width), 2.75, atol=0.05)
    assert lanes.boundary(through.right_boundary).inferred
    assert _routable(lanes, (485.0, -3.1), (515.0, -6.0))
    assert _routable(lanes, (785.0, -6.0), (815.0, -3.1))
