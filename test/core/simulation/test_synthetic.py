"""Synthetic highways: well-formed ground truth of the data/maps format."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.groundtruth import load_ground_truth, save_ground_truth
from hdmap_core.model import FeatureType
from hdmap_core.simulation.synthetic import LANE_WIDTH_M, SYNTHETIC_NAMES, synthetic_highway

LENGTH_M = 2500.0


@pytest.fixture(scope="module", params=SYNTHETIC_NAMES)
def gt(request):
    return synthetic_highway(request.param, length_m=LENGTH_M, seed=0)


def _steps(xy: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(xy, axis=0), axis=1)


def test_point_spacing_at_most_one_metre(gt):
    assert max(_steps(ln.centerline).max() for ln in gt.lanes.values()) <= 1.0
    assert max(_steps(f.points).max() for f in gt.features) <= 1.0
    assert min(_steps(ln.centerline).min() for ln in gt.lanes.values()) > 0.1


def test_links_and_neighbours_are_symmetric(gt):
    lanes = gt.lanes.values()
    assert any(lane.successors for lane in lanes) and any(lane.left or lane.right for lane in lanes)
    for lane in lanes:
        for s in lane.successors:
            assert lane.id in gt.lanes[s].predecessors
            np.testing.assert_allclose(lane.centerline[-1], gt.lanes[s].centerline[0], atol=0.01)
        for p in lane.predecessors:
            assert lane.id in gt.lanes[p].successors
        if lane.left:
            assert gt.lanes[lane.left].right == lane.id
        if lane.right:
            assert gt.lanes[lane.right].left == lane.id


def test_neighbours_are_one_lane_apart_on_the_correct_side(gt):
    assert any(lane.left or lane.right for lane in gt.lanes.values())
    for lane in gt.lanes.values():
        mid = len(lane.centerline) // 2
        p = lane.centerline[mid]
        t = lane.centerline[mid + 1] - lane.centerline[mid - 1]
        left = np.array([-t[1], t[0]]) / np.linalg.norm(t)
        for side, sign in (("left", 1.0), ("right", -1.0)):
            nid = getattr(lane, side)
            if nid:
                q = gt.lanes[nid].centerline
                lat = (q[np.argmin(np.linalg.norm(q - p, axis=1))] - p) @ left
                assert sign * lat == pytest.approx(LANE_WIDTH_M, abs=0.1)


def test_routes_are_connected_chains(gt):
    for route in gt.routes:
        for i, (a, b) in enumerate(zip(route.lanes[:-1], route.lanes[1:])):
            assert b in gt.lanes[a].successors or i in route.lane_changes, (route.id, a, b)
        assert _steps(gt.route_centerline(route)).max() <= 1.0


def test_through_route_per_lane_and_direction(gt):
    dirs = gt.extra["route_directions"]
    for d in ("fwd", "bwd"):
        lane_routes = [r for r in gt.routes if r.id.startswith(f"{d}_lane")]
        assert len(lane_routes) == 3
        for r in lane_routes:
            assert dirs[r.id] == d
            length = _steps(gt.route_centerline(r)).sum()
            assert length == pytest.approx(LENGTH_M, rel=0.02)


def test_features_ordered_in_driving_direction(gt):
    # Every feature runs parallel (not anti-parallel) to the lane centreline nearest to it.
    pts = np.concatenate([ln.centerline for ln in gt.lanes.values()])
    tan = np.concatenate([np.gradient(ln.centerline, axis=0) for ln in gt.lanes.values()])
    for f in gt.features:
        mid = len(f.points) // 2
        k = np.argmin(np.linalg.norm(pts - f.points[mid], axis=1))
        assert np.dot(f.points[min(mid + 1, len(f.points) - 1)] - f.points[mid - 1], tan[k]) > 0, f.id


def test_both_median_barriers_and_all_types_present(gt):
    types = {f.type for f in gt.features}
    assert types == {FeatureType.SOLID, FeatureType.DASHED, FeatureType.ROAD_BORDER}
    borders = [f for f in gt.features if f.type == FeatureType.ROAD_BORDER and _steps(f.points).sum() > 0.9 * LENGTH_M]
    # The two median barriers run 2.5 m apart over the whole length.
    gaps = []
    for i, a in enumerate(borders):
        for b in borders[i + 1 :]:
            d = np.min(np.linalg.norm(b.points[::50, None, :] - a.points[None, ::5, :], axis=2), axis=1)
            gaps.append(np.median(d))
    assert min(gaps) == pytest.approx(2.5, abs=0.2)


def test_ramps_split_and_merge():
    gt = synthetic_highway("motorway_ramps", length_m=LENGTH_M)
    splits = [ln for ln in gt.lanes.values() if len(ln.successors) == 2]
    merges = [ln for ln in gt.lanes.values() if len(ln.predecessors) == 2]
    assert {ln.id.split(":")[0] for ln in splits} == {"fwd", "bwd"}
    assert {ln.id.split(":")[0] for ln in merges} == {"fwd", "bwd"}
    for lane in splits:
        a, b = (gt.lanes[s] for s in lane.successors)
        np.testing.assert_allclose(a.centerline[0], b.centerline[0], atol=0.01)  # they start together
        ramp = a if len(a.successors) == 0 or "x" in a.id else b
        # follow the ramp to its end: it ends far off the main line
        while ramp.successors:
            ramp = gt.lanes[ramp.successors[0]]
        main = np.concatenate([ln.centerline for ln in gt.lanes.values() if ln.id.endswith(":3")])
        assert np.min(np.linalg.norm(main - ramp.centerline[-1], axis=1)) > 20.0
    ids = {r.id for r in gt.routes}
    assert {"fwd_exit0", "fwd_entry0", "bwd_exit0", "bwd_entry0"} <= ids
    exit_route = next(r for r in gt.routes if r.id == "fwd_exit0")
    assert any(len(gt.lanes[ln].successors) == 2 for ln in exit_route.lanes)
    entry_route = next(r for r in gt.routes if r.id == "fwd_entry0")
    assert any(len(gt.lanes[ln].predecessors) == 2 for ln in entry_route.lanes)


def test_lane_drop_has_a_merge_and_the_opposite_side_a_split():
    gt = synthetic_highway("lane_drop", length_m=LENGTH_M)
    merges = [ln.id for ln in gt.lanes.values() if len(ln.predecessors) == 2]
    splits = [ln.id for ln in gt.lanes.values() if len(ln.successors) == 2]
    assert [m.split(":")[0] for m in merges] == ["fwd"]
    assert [s.split(":")[0] for s in splits] == ["bwd"]
    first = [ln for ln in gt.lanes.values() if ln.id.startswith("fwd:0:")]
    last_j = max(int(ln.id.split(":")[1]) for ln in gt.lanes.values() if ln.id.startswith("fwd:"))
    last = [ln for ln in gt.lanes.values() if ln.id.startswith(f"fwd:{last_j}:")]
    assert (len(first), len(last)) == (3, 2)


def test_round_trip_through_the_json_format(gt, tmp_path):
    path = tmp_path / "syn.gt.json"
    save_ground_truth(gt, path)
    back = load_ground_truth(path)
    assert back.name == gt.name
    assert [r.lanes for r in back.routes] == [r.lanes for r in gt.routes]
    assert set(back.lanes) == set(gt.lanes)
    for lid, lane in gt.lanes.items():
        assert back.lanes[lid].successors == lane.successors
        np.testing.assert_allclose(back.lanes[lid].centerline, lane.centerline, atol=1e-3)


def test_seeded_shape_is_curved_and_deterministic():
    a = synthetic_highway("motorway", length_m=LENGTH_M, seed=0)
    b = synthetic_highway("motorway", length_m=LENGTH_M, seed=0)
    c = synthetic_highway("motorway", length_m=LENGTH_M, seed=1)
    np.testing.assert_array_equal(a.features[0].points, b.features[0].points)
    assert not np.allclose(a.features[0].points[-1], c.features[0].points[-1])
    xy = a.lanes["fwd:0:1"].centerline
    heading = np.unwrap(np.arctan2(*np.diff(a.route_centerline(a.routes[0]), axis=0)[:, ::-1].T))
    assert heading.max() - heading.min() > 0.05  # it is not a straight line
    assert len(xy) > 2


@pytest.mark.parametrize(
    ("name", "length"), [("freeway", 3000.0), ("motorway_ramps", 1000.0), ("motorway", float("nan"))]
)
def test_bad_arguments_raise_config_error(name, length):
    with pytest.raises(ConfigError, match=name if name == "freeway" else "length_m"):
        synthetic_highway(name, length_m=length)
