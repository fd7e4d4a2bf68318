"""Road-level splits and merges (GT lane graph vs the map's topology graph) with known answers.

The hand-made junction, driving direction +x (y in metres)::

    lane "A" (0..300 m, y = 0) -> "M" (300..900 m, y = 0)          main road
                               -> "X" (300..900 m): 3.5 m right of the main road for 100 m,
                                  then curving away to y = -60 (an exit) or staying at
                                  y = -3.5 (a lane added inside the carriageway)
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.evaluation.config import EvalConfig
from hdmap_core.evaluation.evaluate import evaluate_map, hdmap_from_ground_truth
from hdmap_core.evaluation.roads import topology_from_lanes
from hdmap_core.evaluation.summary import format_summary
from hdmap_core.groundtruth import GroundTruth, GTLane, GTRoute
from hdmap_core.model import HDMap, TopologyNode
from hdmap_core.simulation.synthetic import synthetic_highway


def _lane_xy(x0: float, x1: float, y_of_x) -> np.ndarray:
    x = np.arange(x0, x1 + 1e-9, 1.0)
    return np.stack([x, y_of_x(x)], axis=1)


def _exit_y(x: np.ndarray) -> np.ndarray:
    u = np.clip((x - 400.0) / 500.0, 0.0, 1.0)
    return -3.5 - 56.5 * u * u


def _junction(exit_: bool) -> GroundTruth:
    x_y = _exit_y if exit_ else (lambda x: np.full_like(x, -3.5))
    lanes = {
        "A": GTLane("A", _lane_xy(0, 300, np.zeros_like), successors=("M", "X")),
        "M": GTLane("M", _lane_xy(300, 900, np.zeros_like), predecessors=("A",)),
        "X": GTLane("X", np.vstack([[300.0, 0.0], _lane_xy(310, 900, x_y)]), predecessors=("A",)),
    }
    routes = (GTRoute("main", ("A", "M")), GTRoute("exit", ("A", "X")))
    return GroundTruth("junction", (), lanes, routes)


def _without_link(hdmap: HDMap, from_xy: np.ndarray, towards_xy: np.ndarray, steps: int = 30) -> HDMap:
    """The map with one topology link removed: from the node nearest to ``from_xy`` to the one of its
    successors whose chain (``steps`` nodes on) comes nearest to ``towards_xy``."""
    nodes = list(hdmap.topology)
    by_id = {n.id: n for n in nodes}
    i = int(np.argmin([np.linalg.norm(n.position - from_xy) for n in nodes]))

    def walk(nid: int) -> float:
        for _ in range(steps):
            if not by_id[nid].successors:
                break
            nid = by_id[nid].successors[0]
        return float(np.linalg.norm(by_id[nid].position - towards_xy))

    target = min(nodes[i].successors, key=walk)
    nodes[i] = dataclasses.replace(nodes[i], successors=tuple(s for s in nodes[i].successors if s != target))
    return dataclasses.replace(hdmap, topology=tuple(nodes))


def test_exit_found_with_the_ground_truth_topology() -> None:
    gt = _junction(exit_=True)
    rep = evaluate_map(hdmap_from_ground_truth(gt), gt)
    assert (rep.gt_road_splits, rep.found_road_splits, rep.gt_road_merges) == (1, 1, 0)
    (b,) = rep.road_branch_points
    assert b.kind == "split" and b.gt_lanes == ("A",) and b.branch_lanes == (("M",), ("X",))
    assert b.found and all(b.branch_connected) and min(b.branch_nodes) > 0 and b.single_nodes > 0
    assert (b.x, b.y) == pytest.approx((300.0, 0.0))


def test_lane_added_inside_the_carriageway_is_no_road_split() -> None:
    gt = _junction(exit_=False)
    rep = evaluate_map(hdmap_from_ground_truth(gt), gt)
    assert rep.road_branch_points == () and rep.gt_road_splits == 0
    assert rep.gt_lane_splits == 1  # the lane graph does branch there


def test_unlinked_ramp_topology_is_missing() -> None:
    gt = _junction(exit_=True)
    hdmap = _without_link(hdmap_from_ground_truth(gt), np.array([299.0, 0.0]), np.array([360.0, -3.5]))
    rep = evaluate_map(hdmap, gt)
    assert (rep.gt_road_splits, rep.found_road_splits) == (1, 0)
    (b,) = rep.missing_road_branch_points
    assert b.branch_connected == (True, False) and "1 branch(es) not connected to the incoming road" in b.reason


def test_a_ramp_pivot_linked_to_the_main_road_is_found() -> None:
    """Road-level topology as the pipeline makes it: one node chain per road (wide nodes on the
    main road), the exit's chain starting on the main road, linked to it only at its start."""
    gt = _junction(exit_=True)
    main = [
        TopologyNode(id=k + 1, position=np.array([x, -1.75]), heading=0.0, width=7.0, successors=(k + 2,))
        for k, x in enumerate(np.arange(1.0, 900.0, 2.0))
    ]
    main[-1] = dataclasses.replace(main[-1], successors=())
    xs = np.arange(301.0, 900.0, 2.0)
    first = len(main) + 1
    ramp = [
        TopologyNode(
            id=first + k,
            position=np.array([x, _exit_y(np.array([x]))[0]]),
            heading=0.0,
            width=4.0,
            successors=(first + k + 1,) if k + 1 < len(xs) else (),
        )
        for k, x in enumerate(xs)
    ]
    fork = dataclasses.replace(main[149], successors=(151, first))
    linked = HDMap(topology=tuple(main[:149] + [fork] + main[150:] + ramp))
    rep = evaluate_map(linked, gt)
    assert rep.found_road_splits == rep.gt_road_splits == 1
    (b,) = rep.road_branch_points
    assert b.branch_nodes[0] > 0 and b.branch_nodes[1] > 0
    # The ramp's chain alone (no link from the main road): evaluable, missing.
    rep = evaluate_map(HDMap(topology=tuple(main + ramp)), gt)
    assert (rep.gt_road_splits, rep.found_road_splits) == (1, 0)
    # No node on the ramp: not evaluable, listed with the reason.
    rep = evaluate_map(HDMap(topology=tuple(main)), gt)
    assert rep.gt_road_splits == 0
    (b,) = rep.road_branch_points
    assert not b.evaluable and "topology nodes on 1 of 2 branches" in b.reason


def test_path_length_bound() -> None:
    gt = _junction(exit_=True)
    rep = evaluate_map(hdmap_from_ground_truth(gt), gt, config=EvalConfig(road_path_m=1.0))
    (b,) = rep.road_branch_points
    assert b.evaluable and not b.found


def test_map_without_topology_has_no_evaluable_road_point() -> None:
    gt = _junction(exit_=True)
    rep = evaluate_map(hdmap_from_ground_truth(gt, with_topology=False), gt)
    assert rep.gt_road_splits == 0 and len(rep.road_branch_points) == 1
    assert "no topology node on the incoming road" in rep.road_branch_points[0].reason
    doc = rep.to_dict()
    assert doc["gt_road_splits"] == 0 and doc["road_branch_points"][0]["branch_lanes"] == [["M"], ["X"]]
    assert "road splits/merges connected in the map's topology: splits 0/0" in format_summary(rep)


@pytest.mark.slow
def test_motorway_ramps_has_its_exits_and_entries() -> None:
    """One exit and one entry per carriageway; the deceleration lane runs 330 m beside lane 3 before
    it parts (hence road_follow_m 600 m); lane_drop's taper and added lane are no road points."""
    gt = synthetic_highway("motorway_ramps")
    rep = evaluate_map(hdmap_from_ground_truth(gt), gt)
    assert (rep.gt_road_splits, rep.gt_road_merges, rep.found_road_splits, rep.found_road_merges) == (2, 2, 2, 2)
    lanes = sorted(b.gt_lanes[0] for b in rep.road_branch_points)
    assert lanes == sorted(["bwd:1:3", "bwd:11:3", "fwd:1:3", "fwd:11:3"])
    exit_fwd = next(b for b in rep.road_branch_points if b.gt_lanes == ("fwd:1:3",))
    exit_lane = gt.lanes["fwd:2:x0"].centerline
    cut = _without_link(hdmap_from_ground_truth(gt), gt.lanes["fwd:1:3"].centerline[-1], exit_lane[-1], steps=40)
    rep_cut = evaluate_map(cut, gt)
    assert rep_cut.found_road_splits == 1 and rep_cut.found_road_merges == 2
    (missing,) = rep_cut.missing_road_branch_points
    assert (missing.x, missing.y) == (exit_fwd.x, exit_fwd.y)
    drop = synthetic_highway("lane_drop")
    rep = evaluate_map(hdmap_from_ground_truth(drop), drop)
    assert rep.road_branch_points == () and rep.gt_lane_splits + rep.gt_lane_merges == 2


def test_ground_truth_topology_nodes() -> None:
    gt = _junction(exit_=True)
    nodes = topology_from_lanes(gt.lanes)
    ids = {n.id for n in nodes}
    assert all(s in ids for n in nodes for s in n.successors)
    a_last = max((n for n in nodes if n.position[1] == 0.0 and n.position[0] < 300), key=lambda n: n.position[0])
    assert len(a_last.successors) == 2 and a_last.position[0] == pytest.approx(299.0)
    assert all(n.width == 3.5 and math.isfinite(n.heading) for n in nodes)


@pytest.mark.parametrize("field", ["road_follow_m", "road_apart_m", "road_cluster_m", "road_path_m"])
def test_road_config_must_be_positive(field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        EvalConfig(**{field: 0.0})
    with pytest.raises(ConfigError, match="road_node_margin_m"):
        EvalConfig(road_node_margin_m=-1.0)


# ------------------------------------------------------------------------------ topology link precision


def _two_carriageways() -> GroundTruth:
    """The exit junction plus the opposite carriageway ("O", x 900 -> 0 at y = 10) and an entry
    ramp ("E", starting at (600, -30), merging nowhere near: a separate road beside the main one)."""
    gt = _junction(exit_=True)
    lanes = dict(gt.lanes)
    lanes["O"] = GTLane("O", _lane_xy(0, 900, lambda x: np.full_like(x, 10.0))[::-1])
    lanes["E"] = GTLane("E", _lane_xy(600, 900, lambda x: np.full_like(x, -30.0)))
    routes = gt.routes + (GTRoute("opposite", ("O",)), GTRoute("entry", ("E",)))
    return GroundTruth("junction2", (), lanes, routes)


def _with_link(hdmap: HDMap, from_xy, to_xy) -> HDMap:
    """The map with one more topology link, from the node nearest ``from_xy`` to the one nearest ``to_xy``."""
    nodes = list(hdmap.topology)
    pos = np.array([n.position for n in nodes])
    i = int(np.argmin(np.linalg.norm(pos - np.asarray(from_xy), axis=1)))
    j = int(np.argmin(np.linalg.norm(pos - np.asarray(to_xy), axis=1)))
    nodes[i] = dataclasses.replace(nodes[i], successors=nodes[i].successors + (nodes[j].id,))
    return dataclasses.replace(hdmap, topology=tuple(nodes))


@pytest.mark.slow
def test_ground_truth_topology_has_link_precision_one() -> None:
    for gt in (_two_carriageways(), synthetic_highway("motorway_ramps")):
        rep = evaluate_map(hdmap_from_ground_truth(gt), gt)
        assert rep.n_topology_links_evaluable > 0.9 * rep.n_topology_links
        assert rep.topology_link_precision == 1.0 and rep.false_topology_links == ()
        # The lane-to-lane joints (2 m or less) are no long links; the GT map has none.
        assert rep.n_long_links == 0 and math.isnan(rep.long_link_precision)


def test_links_to_the_opposite_carriageway_or_an_unconnected_ramp_are_false() -> None:
    gt = _two_carriageways()
    base = hdmap_from_ground_truth(gt)
    # The opposite carriageway 10 m beside; the entry ramp 30 m beside, which joins nothing here.
    for from_xy, to_xy in (([200.0, 0.0], [205.0, 10.0]), ([600.0, 0.0], [611.0, -30.0])):
        rep = evaluate_map(_with_link(base, from_xy, to_xy), gt)
        assert (rep.n_long_links, rep.n_long_links_evaluable, rep.n_long_links_supported) == (1, 1, 0)
        assert rep.long_link_precision == 0.0
        (t,) = rep.false_topology_links
        assert t.verdict == "false" and (t.x, t.y) == pytest.approx((from_xy[0] - 1.0, 0.0))
        assert t.length_m == pytest.approx(np.hypot(*(np.array(to_xy) - from_xy)), abs=1.5)
        doc = rep.to_dict()
        assert doc["false_topology_links"][0]["length_m"] == pytest.approx(t.length_m)
        assert "false link" in format_summary(rep) and "long (> 3 m) 0/1" in format_summary(rep)


def test_a_link_across_the_exit_is_supported() -> None:
    """Main road before the split -> exit ramp 60 m later: a lane path (A, then X) exists."""
    gt = _junction(exit_=True)
    exit_xy = [360.0, float(_exit_y(np.array([360.0]))[0])]
    rep = evaluate_map(_with_link(hdmap_from_ground_truth(gt), [299.0, 0.0], exit_xy), gt)
    assert (rep.n_long_links_evaluable, rep.n_long_links_supported) == (1, 1)
    assert rep.false_topology_links == ()
    # ... but not backwards: exit ramp -> main road before the split.
    rep = evaluate_map(_with_link(hdmap_from_ground_truth(gt), exit_xy, [299.0, 0.0]), gt)
    assert (rep.n_long_links_evaluable, rep.n_long_links_supported) == (1, 0)
    # The path bound: 2 x |AB| + 20 m (config), here 61 m of lane path for a 61 m link.
    rep = evaluate_map(
        _with_link(hdmap_from_ground_truth(gt), [199.0, 0.0], [299.0, 0.0]),
        gt,
        config=EvalConfig(link_path_factor=0.5, link_path_slack_m=0.0),
    )
    assert rep.n_long_links_supported == 0


def test_nodes_off_every_lane_are_unevaluable() -> None:
    gt = _junction(exit_=True)
    base = hdmap_from_ground_truth(gt)
    off = TopologyNode(id=10**6, position=np.array([200.0, 40.0]), heading=0.0, width=3.5, successors=())
    hdmap = _with_link(dataclasses.replace(base, topology=base.topology + (off,)), [150.0, 0.0], [200.0, 40.0])
    rep = evaluate_map(hdmap, gt)
    assert rep.n_long_links == 1 and rep.n_long_links_evaluable == 0 and rep.false_topology_links == ()
    (t,) = rep.unevaluable_long_links
    assert t.verdict == "unevaluable" and "to node on no ground-truth lane" in t.reason
    assert rep.topology_link_precision == 1.0
    # A map without topology: nothing to judge.
    rep = evaluate_map(hdmap_from_ground_truth(gt, with_topology=False), gt)
    assert rep.n_topology_links == 0 and math.isnan(rep.topology_link_precision)


@pytest.mark.parametrize("field", ["link_path_factor", "link_long_m"])
def test_link_config_must_be_positive(field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        EvalConfig(**{field: 0.0})
    with pytest.raises(ConfigError, match="link_back_m"):
        EvalConfig(link_back_m=-1.0)


def test_a_link_that_changes_lanes_is_supported() -> None:
    r"""Two lanes side by side (R at y 0, L at y 3.5, neighbours), one carriageway: a link from the
    node on R at x 100 to the node on L at x 110 is a lane change, which a carriageway's topology
    may make; with the lanes not marked as neighbours (two separate roads) it is false."""

    def road(neighbours: bool) -> GroundTruth:
        lanes = {
            "R": GTLane("R", _lane_xy(0, 300, np.zeros_like), left="L" if neighbours else None),
            "L": GTLane("L", _lane_xy(0, 300, lambda x: np.full_like(x, 3.5)), right="R" if neighbours else None),
        }
        return GroundTruth("two_lanes", (), lanes, (GTRoute("r", ("R",)), GTRoute("l", ("L",))))

    for neighbours, supported in ((True, 1), (False, 0)):
        gt = road(neighbours)
        rep = evaluate_map(_with_link(hdmap_from_ground_truth(gt), [100.0, 0.0], [110.0, 3.5]), gt)
        assert (rep.n_long_links, rep.n_long_links_evaluable, rep.n_long_links_supported) == (1, 1, supported)
