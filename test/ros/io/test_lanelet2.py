"""The Lanelet2 export checked with the real ``lanelet2`` package (loading, routing graph, routes)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hdmap_core.lanes.connectors import trajectory_connectors
from hdmap_core.lanes.derive import _proper, derive_lanes
from hdmap_core.lanes.model import Boundary, Lane, LaneMap
from hdmap_core.model import FeatureType, GeoOrigin
from hdmap_ros.io.lanelet2 import MAP_FILE, PROJECTOR_FILE, write_lanelet2

from lane_samples import junction_gap, lane_gain, taper_open, three_lanes, turn_drives, turn_without_lines

lanelet2 = pytest.importorskip("lanelet2")
from lanelet2.projection import LocalCartesianProjector  # noqa: E402

ORIGIN = GeoOrigin(48.7758, 9.1829, 250.0)


def load(directory: Path, origin: GeoOrigin = ORIGIN):
    """(map, load errors, routing graph, validity problems) of an export."""
    proj = LocalCartesianProjector(lanelet2.io.Origin(origin.latitude_deg, origin.longitude_deg, origin.altitude_m))
    llmap, errors = lanelet2.io.loadRobust(str(directory / MAP_FILE), proj)
    rules = lanelet2.traffic_rules.create(
        lanelet2.traffic_rules.Locations.Germany, lanelet2.traffic_rules.Participants.Vehicle
    )
    graph = lanelet2.routing.RoutingGraph(llmap, rules)
    return llmap, errors, graph, graph.checkValidity(False)


def by_lane_id(llmap) -> dict[int, object]:
    return {int(ll.attributes["hdmap:lane_id"]): ll for ll in llmap.laneletLayer}


@pytest.mark.parametrize("make", [three_lanes, lane_gain, junction_gap, taper_open])
def test_loads_clean_and_routes(tmp_path, make):
    lanes = derive_lanes(make())
    write_lanelet2(lanes, ORIGIN, tmp_path)
    llmap, errors, graph, problems = load(tmp_path)
    assert list(errors) == [] and list(problems) == []
    assert len(llmap.laneletLayer) == len(lanes.lanes)
    ll = by_lane_id(llmap)
    # every successor of the lane model is a following lanelet in Lanelet2 (shared node ids)
    for ln in lanes.lanes:
        following = {int(x.attributes["hdmap:lane_id"]) for x in graph.following(ll[ln.id])}
        assert following == set(ln.successors)
    # from the leftmost first lane to the rightmost last lane, with lane changes
    first = min((ln for ln in lanes.lanes if not ln.predecessors), key=lambda x: -x.centerline[0, 1])
    last = min((ln for ln in lanes.lanes if not ln.successors), key=lambda x: x.centerline[-1, 1])
    assert graph.getRoute(ll[first.id], ll[last.id]) is not None


def test_line_less_junction_is_routable_with_trajectory_connectors(tmp_path):
    """A right turn without lines or topology: Lanelet2 finds no route from the road before it to
    the road after it on the map's lanes alone, and one through a lanelet with virtual bounds
    once the drives' trajectories add a connector."""
    lanes = derive_lanes(turn_without_lines())
    east = next(ln for ln in lanes.lanes if abs(ln.centerline[0, 1]) < 1.0)
    south = next(ln for ln in lanes.lanes if ln.centerline[0, 1] < -29.0)
    routes = []
    for name, lm in (("lines", lanes), ("drives", trajectory_connectors(lanes, turn_drives(4, seed=3)))):
        write_lanelet2(lm, ORIGIN, tmp_path / name)
        llmap, errors, graph, problems = load(tmp_path / name)
        assert list(errors) == [] and list(problems) == []
        ll = by_lane_id(llmap)
        routes.append(graph.getRoute(ll[east.id], ll[south.id]))
    assert routes[0] is None and routes[1] is not None
    path = [int(x.attributes["hdmap:lane_id"]) for x in routes[1].shortestPath()]
    assert path[0] == east.id and path[-1] == south.id and len(path) == 3
    con = ll[path[1]]
    assert con.leftBound.attributes["type"] == "virtual" and con.rightBound.attributes["type"] == "virtual"


def test_tags_projector_and_coordinates(tmp_path):
    lanes = derive_lanes(three_lanes())
    write_lanelet2(lanes, ORIGIN, tmp_path)
    info = (tmp_path / PROJECTOR_FILE).read_text()
    assert "projector_type: LocalCartesian" in info and "vertical_datum: WGS84" in info
    assert "latitude: 48.7758" in info and "longitude: 9.1829" in info and "altitude: 250.0" in info
    llmap, *_ = load(tmp_path)
    ll = by_lane_id(llmap)
    for ln in lanes.lanes:
        x = ll[ln.id]
        assert x.attributes["type"] == "lanelet" and x.attributes["subtype"] == "road"
        assert x.attributes["location"] == "nonurban" and x.attributes["one_way"] == "yes"
        # the bounds come back at the map-frame coordinates (LocalCartesian = the ENU tangent plane)
        left = np.array([[p.x, p.y, p.z] for p in x.leftBound])
        want = lanes.boundary(ln.left_boundary).points
        np.testing.assert_allclose(left[[0, -1], :2], want[[0, -1]], atol=1e-3)
        np.testing.assert_allclose(left[:, 2], 0.0, atol=1e-3)
    kinds = {
        (ls.attributes["type"], ls.attributes["subtype"] if "subtype" in ls.attributes else "")
        for ls in llmap.lineStringLayer
    }
    assert kinds == {("line_thin", "solid"), ("line_thin", "dashed")}
    # a lane change shares one way: the middle lane's left bound is the left lane's right bound
    mid = next(ln for ln in lanes.lanes if ln.left is not None and ln.right is not None)
    assert ll[mid.id].leftBound.id == ll[mid.left].rightBound.id


@pytest.mark.slow
def test_sample_bag_export_is_routable(tmp_path, sample_bags):
    """bags/ramps_20 through bag2map --lanelet2, then every ground-truth route the fleet drove is
    routable in Lanelet2 from its first lanelet to its last (lanes found along the route)."""
    import json

    from hdmap_core.evaluation.lanes import route_ends
    from hdmap_core.groundtruth import load_ground_truth
    from hdmap_ros import cli
    from hdmap_ros.io.bagio import read_fleet_bag, read_map_bag

    bag = sample_bags / "ramps_20"
    out = tmp_path / "map"
    assert cli.main(["bag2map", str(bag), "-o", str(out), "--no-progress", "--lanelet2", str(tmp_path / "ll")]) == 0
    # bag2map adds connectors from the drives where the lanes lack one; export does with --fleet
    assert cli.main(["export", str(out), "--lanelet2", str(tmp_path / "ll2"), "--fleet", str(bag)]) == 0
    assert (tmp_path / "ll" / MAP_FILE).read_bytes() == (tmp_path / "ll2" / MAP_FILE).read_bytes()
    sim = json.loads((sample_bags / "ramps_20.sim.json").read_text())
    origin = GeoOrigin(**sim["origin"])
    llmap, errors, graph, problems = load(tmp_path / "ll", origin)
    assert list(errors) == [] and list(problems) == []
    gt = load_ground_truth(sample_bags / "ramps_20.gt.json")
    lanes = trajectory_connectors(derive_lanes(read_map_bag(out)), [d.xy for d in read_fleet_bag(bag).drives])
    ll = by_lane_id(llmap)
    driven = sorted({t["route_id"] for t in sim["truth"].values()})
    assert driven
    for rid in driven:
        ends = route_ends(lanes, gt, rid)
        assert ends is not None, rid
        assert graph.getRoute(ll[ends[0]], ll[ends[1]]) is not None, rid
    assert (
        cli.main(
            [
                "evaluate",
                str(out),
                str(sample_bags / "ramps_20.gt.json"),
                "--fleet",
                str(bag),
                "--lanes",
                "--json",
                str(tmp_path / "e.json"),
            ]
        )
        == 0
    )
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["lanes"]["routes"] == len(driven) and doc["lanes"]["precision"] > 0.9


def test_export_of_a_bag_without_map_is_an_error(tmp_path, sample_bags, capsys):
    from hdmap_ros import cli

    assert cli.main(["export", str(sample_bags / "e6mini_20"), "--lanelet2", str(tmp_path / "ll")]) == 1
    assert "no hdmap_msgs/msg/Map" in capsys.readouterr().err
    assert not (tmp_path / "ll" / MAP_FILE).exists()


@pytest.mark.parametrize(
    ("left_y", "right_y"),
    [
        ((1.75, 1.75, 1.75), (-1.75, -1.75, -1.75)),  # a lane
        ((-1.75, -1.75, -1.75), (1.75, 1.75, 1.75)),  # sides crossed over
        ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),  # zero width
        ((0.0, 1.0, 2.0), (0.0, -1.0, -2.0)),  # opening from a point (a gore): a lane
    ],
)
def test_degenerate_lanes_are_those_lanelet2_turns_round(tmp_path, left_y, right_y):
    """RULE 14 predicts Lanelet2's loader: it aligns a lanelet's bounds by the side the other
    bound's middle lies on, and the lanes the rule drops are those it turns round."""
    x = np.array([0.0, 5.0, 10.0])
    left, right = np.stack([x, left_y], axis=1), np.stack([x, right_y], axis=1)
    nodes = {1: left[0], 2: left[-1], 3: right[0], 4: right[-1]}
    if left_y[0] == right_y[0]:
        nodes.pop(3)
    start_r = 3 if 3 in nodes else 1
    bounds = (
        Boundary(11, 1, FeatureType.SOLID, left, 1, 2),
        Boundary(12, 2, FeatureType.SOLID, right, start_r, 4 if left_y[-1] != right_y[-1] else 2),
    )
    lane = Lane(
        7, (left + right) / 2, np.abs(np.array(left_y) - right_y), 11, 12, 1, 2, FeatureType.SOLID, FeatureType.SOLID
    )
    write_lanelet2(LaneMap((lane,), bounds, nodes), ORIGIN, tmp_path)
    llmap, *_ = load(tmp_path)
    (ll,) = list(llmap.laneletLayer)
    turned = ll.leftBound.inverted() or ll.rightBound.inverted()
    b_l, b_r = bounds
    assert turned == (not _proper(left, right, (b_l.start_node, b_l.end_node), (b_r.start_node, b_r.end_node)))
