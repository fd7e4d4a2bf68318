"""`hdmap bag2map` with one hostile drive in a good fleet: the map is the map without that drive,
and the report names the drive and the reason (issue: far poses and detections, a zigzag drive)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap_core.model import Detection, GeoOrigin
from hdmap_ros import cli
from hdmap_ros.io.bagio import read_map_bag, write_fleet_bag

from bag_samples import assert_maps_equal
from pipeline_fleet import make_fleet


def _pose_at(d, value):
    xy = np.array(d.xy, dtype=float)
    xy[len(xy) // 2, 1] = value
    return replace(d, xy=xy)


def _detection_at(d, value):
    pts = np.array(d.detections[0].points, dtype=float)
    pts[len(pts) // 2, 0] = value
    return replace(d, detections=(Detection(d.detections[0].type, pts), *d.detections[1:]))


def _zigzag(d):
    xy = np.array(d.xy, dtype=float)
    xy[1::2, 1] += 50.0
    return replace(d, xy=xy)


CASES = {
    "pose 1e9": (lambda d: _pose_at(d, 1e9), "coordinate_out_of_bounds"),
    "pose 1e12": (lambda d: _pose_at(d, 1e12), "coordinate_out_of_bounds"),
    "pose 1e200": (lambda d: _pose_at(d, 1e200), "coordinate_out_of_bounds"),
    "detection 1e12": (lambda d: _detection_at(d, 1e12), "coordinate_out_of_bounds"),
    "detection 1e60": (lambda d: _detection_at(d, 1e60), "coordinate_out_of_bounds"),
    "zigzag +50 m": (_zigzag, "too_fast"),
}


@pytest.fixture(scope="module")
def good_map(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("good")
    fleet = make_fleet([0.3, -0.2, 0.1, -0.4, 0.2, 0.0], noise_m=0.05, seed=3)
    bag = write_fleet_bag(tmp / "fleet", fleet, GeoOrigin(57.7, 11.97, 5.0))
    assert cli.main(["bag2map", str(bag), "-o", str(tmp / "map"), "--workers", "1", "--no-progress"]) == 0
    return fleet, read_map_bag(tmp / "map")


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(CASES))
def test_a_hostile_drive_leaves_the_map_as_without_it(tmp_path, capsys, good_map, case):
    fleet, reference = good_map
    spoil, reason = CASES[case]
    bad = spoil(replace(fleet[0], drive_id="hostile"))
    bag = write_fleet_bag(tmp_path / "fleet", [*fleet[:3], bad, *fleet[3:]], GeoOrigin(57.7, 11.97, 5.0))
    capsys.readouterr()
    assert cli.main(["bag2map", str(bag), "-o", str(tmp_path / "map"), "--workers", "1", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert f"rejected 'hostile': {reason}" in out
    assert_maps_equal(reference, read_map_bag(tmp_path / "map"))
