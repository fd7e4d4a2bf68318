"""The first map's markings no drive after a shift saw, moved by the measured shift (``updates.unseen``)."""

from __future__ import annotations

import numpy as np
from carriageway_samples import CHANGED, DASHED, PLACES, REBUILT, SOLID, carriageway_lines, line_feature

from hdmap_core.model import HDMap
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.follow import retired_features
from hdmap_core.updates.splice import Reach, splice
from hdmap_core.updates.unseen import unseen_moved

# The carriageway of carriageway_samples and a ramp's dashed line beyond the right barrier at 46;
# places 2 and 3 (x 200-400) shifted 1.5 m right.
FIRST = HDMap(
    features=(
        *carriageway_lines(),
        line_feature(7, DASHED, 46.0, 150.0, 450.0),
    )
)


def _in_zone(x):
    return np.where((x >= 200.0) & (x < 400.0), -1.5, 0.0)


def _local(moves=(-1.5, -1.5)):
    """The aligned rebuild of places 1-4 from the drives after the change: they saw the two dividers."""
    feats = [
        line_feature(
            100 + i, DASHED, y, 100.0, 499.0, shift=lambda x, m=m: np.where((x >= 200.0) & (x < 400.0), m, 0.0)
        )
        for i, (y, m) in enumerate(((53.5, moves[0]), (57.0, moves[1])))
    ]
    return HDMap(features=tuple(feats))


def _evidence(shift=1.5):
    out = []
    for d in ("a1", "a2"):
        for key in sorted(REBUILT):
            disp = shift if key in CHANGED else 0.0
            out.append(PlaceEvidence(d, 10, key, 25, disp, 0.0, True, disp, 40, 40, 0, 40, 0, 40, 0))
    return out


def _change(kinds=("geometry",)):
    places = tuple(PlaceChange(k, "geometry", 10, 5, 1.5, 9.0, ("b1", "b2", "b3"), ("a1", "a2")) for k in CHANGED)
    return DetectedChange(7, 10, kinds, places, ("a1", "a2"), 0.9)


def _ys(hdmap, fid, x0=220.0, x1=380.0):
    f = next(f for f in hdmap.features if f.id == fid)
    sel = (f.points[:, 0] > x0) & (f.points[:, 0] < x1)
    return f.points[sel, 1], np.asarray(f.drive_count)[sel], np.asarray(f.lateral_std)[sel]


def test_the_unseen_markings_of_a_shifted_carriageway_move_by_the_measured_shift():
    got = unseen_moved(FIRST, _local(), PLACES, [_change()], _evidence(), REBUILT)
    assert got.pieces and {p.change_id for p in got.pieces} == {7}
    for fid, y in ((1, 50.0), (4, 60.5)):  # the edge lines no drive after the change saw
        ys, count, std = _ys(got.map, fid)
        np.testing.assert_allclose(ys, y - 1.5, atol=0.05)
        assert np.all(count == 0) and np.all(std >= 0.1)  # a model, not an observation
    # the barriers stay; the ramp beyond the barrier is not on the moved carriageway; outside the
    # rebuilt places nothing moves
    for fid, y in ((5, 49.0), (6, 61.5), (7, 46.0)):
        np.testing.assert_array_equal(_ys(got.map, fid)[0], y)
    np.testing.assert_array_equal(_ys(got.map, 1, 0.0, 99.0)[0], 50.0)
    np.testing.assert_array_equal(_ys(got.map, 1, 0.0, 99.0)[1], 20)


def test_no_model_for_a_lane_closed_or_opened_or_re_striping_nor_where_the_seen_lines_disagree():
    for kinds in (("geometry", "lane_closed"), ("geometry", "lane_opened"), ("geometry", "type")):
        got = unseen_moved(FIRST, _local(), PLACES, [_change(kinds)], _evidence(), REBUILT)
        assert got.pieces == () and got.map is FIRST

    def moved_in_zone(got):
        return [p for p in got.pieces if np.any((p.from_points[:, 0] >= 200.0) & (p.from_points[:, 0] < 400.0))]

    # the dividers moved 1.5 and 0.9 m: not alike
    assert moved_in_zone(unseen_moved(FIRST, _local((-1.5, -0.9)), PLACES, [_change()], _evidence(), REBUILT)) == []
    # both moved alike, but not as far as the drives measured the shift
    assert moved_in_zone(unseen_moved(FIRST, _local(), PLACES, [_change()], _evidence(2.2), REBUILT)) == []
    # (nor the taper places, where every line seen stayed)
    got = unseen_moved(FIRST, _local((-1.5, -0.9)), PLACES, [_change()], _evidence(), REBUILT)
    assert got.pieces == () and got.map is FIRST
    # the control: moved alike, as measured
    assert moved_in_zone(unseen_moved(FIRST, _local(), PLACES, [_change()], _evidence(), REBUILT))


def test_the_splice_keeps_the_moved_markings_and_retires_where_they_were():
    local = _local()
    got = unseen_moved(FIRST, local, PLACES, [_change()], _evidence(), REBUILT)
    # the drives after the change drove at y = 55: everything here is within their reach
    poses = np.stack([np.arange(100.0, 500.0, 2.0), np.full(200, 55.0)], axis=1)
    plain = Reach(poses, 12.0)
    reach = Reach(poses, 12.0, keep=got.moved_to, take=got.moved_from)
    without = splice(FIRST, local, PLACES, REBUILT, reach=plain)
    spliced = splice(got.map, local, PLACES, REBUILT, reach=reach)

    def right_edge(hdmap):
        pts = np.concatenate([f.points for f in hdmap.features if f.type == SOLID])
        return pts[(pts[:, 0] > 220.0) & (pts[:, 0] < 380.0) & (pts[:, 1] < 52.0)]

    assert len(right_edge(without)) == 0  # no drive after the change saw it: gone
    np.testing.assert_allclose(right_edge(spliced)[:, 1], 48.5, atol=0.05)
    retired = retired_features(FIRST, PLACES, [_change()], valid_from_ns=0, reach=reach)
    old_edge = np.concatenate([r.points for r in retired if r.feature_id == 1])
    assert np.all(old_edge[:, 1] == 50.0) and old_edge[:, 0].min() <= 220.0 and old_edge[:, 0].max() >= 380.0


def test_no_model_where_the_local_map_has_markings_the_moved_first_map_does_not_explain():
    """A shift near a lane's width (3 m on 3.5 m lanes) is measured as -0.5 m: each divider pairs
    with its neighbour and moved 'alike', but the new edge lines are left over."""

    def moved(y, m):
        return lambda x: np.where((x >= 200.0) & (x < 400.0), m, 0.0)

    dividers = [line_feature(100 + i, DASHED, y, 100.0, 499.0, shift=moved(y, 0.5)) for i, y in enumerate((53.5, 57.0))]
    edges = [line_feature(110 + i, SOLID, y, 200.0, 399.0) for i, y in enumerate((46.5, 63.0))]
    left = _evidence(-0.5)
    got = unseen_moved(FIRST, HDMap(features=tuple(dividers + edges)), PLACES, [_change()], left, REBUILT)
    assert got.pieces == () and got.map is FIRST
    # the control: without the left-over edge lines the same moves are modelled
    got = unseen_moved(FIRST, HDMap(features=tuple(dividers)), PLACES, [_change()], left, REBUILT)
    assert got.pieces and all(np.allclose(p.move_m, 0.5, atol=0.05) for p in got.pieces)
