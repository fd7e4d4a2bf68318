"""Tests of hdmap_core.incremental: tiles, clipping, step selection, debounce, id carry-over."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.errors import ConfigError
from hdmap_core.incremental import (
    TileConfig,
    carry_over_ids,
    clip_drive,
    needs_update,
    select_steps,
    tile_bounds,
    tile_seed,
    tiles_of_drive,
)
from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.steps import Segment, StepResult


def _drive(xy, drive_id="d", dets=()):
    xy = np.asarray(xy, dtype=float)
    return Drive(
        drive_id=drive_id,
        xy=xy,
        yaw=np.zeros(len(xy)),
        stamps_ns=np.arange(len(xy), dtype=np.int64),
        detections=tuple(dets),
    )


def _line(x0, x1, y=0.0, n=None):
    n = n or int(abs(x1 - x0)) + 1
    return np.stack([np.linspace(x0, x1, n), np.full(n, y)], axis=1)


@pytest.mark.parametrize(
    "kwargs",
    [dict(tile_size_m=0), dict(margin_m=-1), dict(margin_m=256.0), dict(min_growth_fraction=-0.1), dict(min_growth_drives=0)],
)
def test_tile_config_rejects_bad_values(kwargs):
    with pytest.raises(ConfigError):
        TileConfig(**kwargs)


def test_tiles_of_drive_straight_line_with_margin():
    #   tiles of 100 m, margin 10 m; drive along y=50 from x=5 to x=195
    #   |  (0,0)  |  (1,0)  |
    #   x=5 ................ x=195 -> also within 10 m of tile (-1,0) (x<10) and (2,0) (x>190)
    cfg = TileConfig(tile_size_m=100.0, margin_m=10.0)
    keys = tiles_of_drive(_drive(_line(5, 195, y=50)), config=cfg)
    assert keys == {(-1, 0), (0, 0), (1, 0), (2, 0)}


def test_tiles_of_drive_densifies_long_pose_gaps():
    # two poses 1 km apart: every tile in between is covered
    cfg = TileConfig(tile_size_m=100.0, margin_m=0.0)
    keys = tiles_of_drive(_drive([[50, 50], [1050, 50]]), config=cfg)
    assert {(i, 0) for i in range(11)} == keys


def test_tile_bounds_and_seed_are_deterministic():
    assert tile_bounds((1, -2), tile_size_m=256.0, margin_m=10.0) == (246.0, -522.0, 522.0, -246.0)
    assert tile_seed((3, 4), seed=1) == tile_seed((3, 4), seed=1)
    assert tile_seed((3, 4), seed=1) != tile_seed((4, 3), seed=1)
    assert tile_seed((3, 4), seed=1) != tile_seed((3, 4), seed=2)


def test_clip_drive_cuts_trajectory_and_detection_runs():
    #        box x in [0, 100)
    #  traj  -20 ....................... 130
    #  det   -10 ..... 40      60 .. 99.5  (second run inside), 120..125 outside
    det_a = Detection(FeatureType.SOLID, _line(-10, 40, y=2))
    det_b = Detection(FeatureType.DASHED, _line(60, 125, y=-2, n=66))
    d = _drive(_line(-20, 130, n=151), dets=[det_a, det_b])
    c = clip_drive(d, (0.0, -50.0, 100.0, 50.0))
    assert c is not None and c.drive_id == d.drive_id
    np.testing.assert_allclose(c.xy[[0, -1], 0], [0.0, 99.0])
    assert len(c.yaw) == len(c.xy) == len(c.stamps_ns)
    assert [det.type for det in c.detections] == [FeatureType.SOLID, FeatureType.DASHED]
    np.testing.assert_allclose(c.detections[0].points[[0, -1], 0], [0.0, 40.0])
    assert c.detections[1].points[:, 0].max() < 100.0
    # input untouched
    assert len(d.xy) == 151 and len(d.detections[0].points) == 51


def test_clip_drive_outside_returns_none():
    assert clip_drive(_drive(_line(200, 300)), (0.0, 0.0, 100.0, 100.0)) is None


def _step(pivot, i, x):
    return StepResult(
        pivot_id=pivot, index=i, s_m=2.0 * i, midpoint=np.array([x, 0.0]), heading=0.0, width_m=10.0,
        valid=True, processed_before=False, lateral_m=np.array([-1.0, 1.0]), types=np.array([1, 2]),
        counts=np.array([3, 3]), std_m=np.array([0.1, 0.1]), drive_ids=("a",),
    )


def test_select_steps_keeps_inside_and_splits_runs():
    # steps at x = -4, -2, 0, 2, 4, 200, 6 (pivot leaves and comes back) ; box x in [0, 100)
    xs = [-4, -2, 0, 2, 4, 200, 6]
    seg = Segment("p", tuple(_step("p", i, x) for i, x in enumerate(xs)))
    out = select_steps([seg, Segment("q", ())], (0.0, -10.0, 100.0, 10.0))
    assert [[s.index for s in o.steps] for o in out] == [[2, 3, 4], [6]]
    assert all(o.pivot_id == "p" for o in out)


@pytest.mark.parametrize(
    "old,now,due",
    [(0, 0, False), (0, 1, True), (5, 5, False), (5, 6, True), (20, 21, False), (20, 22, True), (100, 109, False), (100, 110, True)],
)
def test_needs_update_debounce(old, now, due):
    assert needs_update(old, now, config=TileConfig(min_growth_fraction=0.10, min_growth_drives=1)) is due


def _feat(fid, pts, ftype=FeatureType.SOLID, succ=()):
    pts = np.asarray(pts, dtype=float)
    return MapFeature(
        id=fid, type=ftype, points=pts, drive_count=np.ones(len(pts), int), lateral_std=np.zeros(len(pts)),
        successors=tuple(succ),
    )


def test_carry_over_ids_keeps_ids_of_persisting_features():
    old = HDMap(features=(_feat(11, _line(0, 100, 0)), _feat(12, _line(0, 100, 3.5), FeatureType.DASHED)))
    # new version: same lines slightly moved and longer, plus one new line; stitcher ids differ
    new = HDMap(
        features=(
            _feat(7, _line(0, 150, 3.6), FeatureType.DASHED, succ=(8,)),
            _feat(8, _line(0, 120, 0.1)),
            _feat(11, _line(0, 100, 7.0)),  # new feature whose stitcher id collides with a carried one
        ),
        topology=(TopologyNode(id=1, position=np.zeros(2), heading=0.0, width=7.0, features=(7, 8, 11)),),
    )
    out = carry_over_ids(new, old)
    ids = [f.id for f in out.features]
    assert ids[0] == 12 and ids[1] == 11
    assert ids[2] not in (11, 12) and len(set(ids)) == 3
    assert out.features[0].successors == (11,)
    assert out.topology[0].features == (12, 11, ids[2])
    np.testing.assert_array_equal(out.features[2].points, new.features[2].points)


def test_carry_over_ids_type_must_match_and_no_old_map():
    old = HDMap(features=(_feat(5, _line(0, 100, 0), FeatureType.ROAD_BORDER),))
    new = HDMap(features=(_feat(9, _line(0, 100, 0)),))
    assert carry_over_ids(new, old).features[0].id == 9
    assert carry_over_ids(new, None) is new


def test_clean_drive_drops_short_and_unknown_and_thins():
    from hdmap_core.incremental import clean_drive

    straight = Detection(FeatureType.SOLID, _line(0, 50, y=1))  # 51 collinear points
    short = Detection(FeatureType.DASHED, _line(0, 2, y=2))  # 2 m < 3 m
    unknown = Detection(FeatureType.UNKNOWN, _line(0, 50, y=3))
    bend = Detection(FeatureType.ROAD_BORDER, np.array([[0.0, 0], [10, 0], [20, 5], [30, 10]]))
    d = _drive(_line(0, 50), dets=[straight, short, unknown, bend])
    c = clean_drive(d)
    assert [x.type for x in c.detections] == [FeatureType.SOLID, FeatureType.ROAD_BORDER]
    np.testing.assert_allclose(c.detections[0].points, [[0, 1], [50, 1]])
    np.testing.assert_allclose(c.detections[1].points, [[0, 0], [10, 0], [30, 10]])
    assert len(d.detections) == 4  # input untouched
