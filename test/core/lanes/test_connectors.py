"""Connector lanes from the drives' trajectories (``lanes/connectors.py``) on hand-made maps."""

from __future__ import annotations

import numpy as np

from hdmap_core.lanes.connectors import connections, trajectory_connectors
from hdmap_core.lanes.derive import derive_lanes
from hdmap_core.lanes.lane_graph import lane_graph, lane_route
from hdmap_core.model import FeatureType

from lane_samples import TURN_RADIUS_M, three_lanes, turn_drives, turn_without_lines


def _ends(lanes):
    east = next(ln for ln in lanes.lanes if ln.centerline[-1, 0] < 301.0 and abs(ln.centerline[0, 1]) < 1.0)
    south = next(ln for ln in lanes.lanes if ln.centerline[0, 1] < -29.0 and abs(ln.centerline[0, 0] - 330.0) < 1.0)
    return east, south


def test_turn_without_lines_gets_a_connector_along_the_drives():
    lanes = derive_lanes(turn_without_lines())
    east, south = _ends(lanes)
    assert lane_route(lane_graph(lanes), east.id, south.id) is None  # the map alone: no way through

    out = trajectory_connectors(lanes, turn_drives(4, seed=1))
    assert len(out.lanes) == len(lanes.lanes) + 1
    route = lane_route(lane_graph(out), east.id, south.id)
    assert route is not None and len(route) == 3
    con = out.lane(route[1])
    assert (con.left_type, con.right_type) == (FeatureType.UNKNOWN, FeatureType.UNKNOWN)
    assert (con.left_feature, con.right_feature) == (0, 0)
    # its sides share the end nodes of the lanes it joins (Lanelet2 routes along shared nodes)
    left, right = out.boundary(con.left_boundary), out.boundary(con.right_boundary)
    assert (left.start_node, right.start_node) == (
        out.boundary(east.left_boundary).end_node,
        out.boundary(east.right_boundary).end_node,
    )
    assert (left.end_node, right.end_node) == (
        out.boundary(south.left_boundary).start_node,
        out.boundary(south.right_boundary).start_node,
    )
    assert con.successors == (south.id,) and con.predecessors == (east.id,)
    assert out.lane(east.id).successors == (con.id,) and out.lane(south.id).predecessors == (con.id,)
    # along the turn the drives made (each biased by up to 0.8 m), and a lane wide
    c = con.centerline
    arc = (c[:, 0] >= 300.0) & (c[:, 1] >= -30.0)
    radius = np.hypot(c[arc, 0] - 300.0, c[arc, 1] + 30.0)
    assert arc.sum() >= 10 and np.abs(radius - TURN_RADIUS_M).max() < 0.3
    assert np.all(np.abs(con.width - 3.5) < 0.2)


def test_no_drives_or_drives_along_joined_lanes_change_nothing():
    lanes = derive_lanes(turn_without_lines())
    assert trajectory_connectors(lanes, []) is lanes
    straight = derive_lanes(three_lanes(400.0))
    rng = np.random.default_rng(0)
    x = np.arange(0.0, 400.0, 1.0)
    drives = [np.stack([x, np.full_like(x, y) + rng.normal(0.0, 0.1, len(x))], axis=1) for y in (3.5, 0.0, -3.5)]
    # a lane change from the middle lane to the right one is a way the lanes have
    drives.append(np.stack([x, np.clip((x - 150.0) / 40.0, 0.0, 1.0) * -3.5], axis=1))
    assert connections(straight, drives) == {}
    assert trajectory_connectors(straight, drives) is straight


def test_connections_need_min_drives_and_are_stable():
    lanes = derive_lanes(turn_without_lines())
    drives = turn_drives(3, seed=2)
    assert trajectory_connectors(lanes, drives, min_drives=4) is lanes
    a = trajectory_connectors(lanes, drives)
    b = trajectory_connectors(lanes, drives[::-1])
    assert [ln.id for ln in a.lanes] == [ln.id for ln in b.lanes]
    con = next(ln for ln in a.lanes if ln.left_type == FeatureType.UNKNOWN)
    con_b = b.lane(con.id)
    assert np.allclose(con.centerline, con_b.centerline)


def test_bad_trajectories_are_no_evidence():
    """Non-finite poses, empty, one-point and standing trajectories neither crash nor connect."""
    lanes = derive_lanes(turn_without_lines())
    drives = turn_drives(2, seed=4)
    drives[0][50] = np.nan
    drives[1][10:20] = np.inf
    junk = [np.zeros((0, 2)), np.zeros((1, 2)), np.ones((5, 2)), np.full((4, 2), np.nan)]
    assert trajectory_connectors(lanes, junk) is lanes
    out = trajectory_connectors(lanes, drives + junk)
    assert len(out.lanes) == len(lanes.lanes) + 1
