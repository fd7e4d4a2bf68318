"""Drive-path lanes from the drives' trajectories (``lanes/drivepath.py``) on hand-made maps."""

from __future__ import annotations

import numpy as np

from hdmap_core.lanes.derive import derive_lanes
from hdmap_core.lanes.drivepath import drive_path_lanes, trajectory_lanes
from hdmap_core.lanes.lane_graph import lane_graph, lane_route
from hdmap_core.model import FeatureType

from lane_samples import three_lanes


def _drive(x: np.ndarray, y: np.ndarray, rng: np.random.Generator, bias_m: float = 0.5) -> np.ndarray:
    """A trajectory along (x, y) with a constant sideways bias and white noise."""
    return np.stack([x, y + rng.uniform(-bias_m, bias_m) + rng.normal(0.0, 0.1, len(x))], axis=1)


def test_drives_beyond_the_lanes_end_get_a_lane_joined_to_it():
    lanes = derive_lanes(three_lanes(400.0))  # the lines stop at x = 400, the drives go on
    rng = np.random.default_rng(2)
    x = np.arange(0.0, 500.0, 1.0)
    drives = [_drive(x, np.zeros_like(x), rng) for _ in range(3)]
    out = drive_path_lanes(lanes, drives)
    assert len(out.lanes) == len(lanes.lanes) + 1
    new = next(ln for ln in out.lanes if ln.id not in {x.id for x in lanes.lanes})
    middle = next(ln for ln in lanes.lanes if ln.centerline[-1, 0] > 398.0 and abs(ln.centerline[-1, 1]) < 0.5)
    assert (new.left_type, new.right_type) == (FeatureType.UNKNOWN, FeatureType.UNKNOWN)
    # it starts at the end nodes of the lane the drives came from and follows the drives
    left, right = out.boundary(new.left_boundary), out.boundary(new.right_boundary)
    assert (left.start_node, right.start_node) == (
        out.boundary(middle.left_boundary).end_node,
        out.boundary(middle.right_boundary).end_node,
    )
    assert new.predecessors == (middle.id,) and out.lane(middle.id).successors == (new.id,)
    assert new.centerline[-1, 0] > 480.0 and np.abs(new.centerline[:, 1]).max() < 0.3
    assert np.all(np.abs(new.width - 3.5) < 0.2)
    assert lane_route(lane_graph(out), middle.id, new.id) == [middle.id, new.id]
    # the export path adds the same lane (no connector here)
    assert {ln.id for ln in trajectory_lanes(lanes, drives).lanes} == {ln.id for ln in out.lanes}


def test_drives_beyond_a_mapped_line_need_two_and_more_than_the_drives_in_the_lane():
    lanes = derive_lanes(three_lanes(400.0))
    rng = np.random.default_rng(3)
    x = np.arange(0.0, 400.0, 1.0)
    # drives leave the right lane (-3.5) beyond its solid line and the road border at x = 320
    y = np.where(x < 310.0, -3.5, np.where(x < 320.0, -3.5 - 0.35 * (x - 310.0), -7.0))
    lost = [_drive(x, y, rng, bias_m=0.1) for _ in range(2)]
    assert drive_path_lanes(lanes, lost[:1]) is lanes  # one drive beside a mapped line: its error
    two = drive_path_lanes(lanes, lost)
    assert len(two.lanes) == len(lanes.lanes) + 1  # two: a way the line map missed
    new = next(ln for ln in two.lanes if ln.id not in {x.id for x in lanes.lanes})
    beyond = new.centerline[new.centerline[:, 0] > 325.0]
    assert len(beyond) > 50 and np.abs(beyond[:, 1] + 7.0).max() < 0.3
    others = [_drive(x, np.full_like(x, -3.5), rng) for _ in range(4)]
    assert drive_path_lanes(lanes, [*lost, *others]) is lanes  # more drive in the lane there


def test_lane_changes_and_drives_along_lanes_make_no_lane():
    lanes = derive_lanes(three_lanes(400.0))
    rng = np.random.default_rng(4)
    x = np.arange(0.0, 400.0, 1.0)
    change = np.clip((x - 100.0) / 150.0, 0.0, 1.0) * -3.5  # a slow change from the middle to the right lane
    drives = [_drive(x, change, rng, bias_m=0.1) for _ in range(3)]
    drives += [_drive(x, np.full_like(x, y), rng) for y in (3.5, 0.0, -3.5)]
    assert drive_path_lanes(lanes, drives) is lanes
    assert drive_path_lanes(lanes, []) is lanes
