"""An opened shoulder's edge line no drive after the change saw, moved by the confirmed move
(``updates.edges.opened_edge_moved``)."""

from __future__ import annotations

import numpy as np
from carriageway_samples import (
    BORDER,
    CHANGED,
    DASHED,
    PLACES,
    REBUILT,
    SOLID,
    carriageway_lines,
    line_feature,
)

from hdmap_core.model import HDMap
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.edges import EdgeEvidence, opened_edge_moved
from hdmap_core.updates.splice import Reach, splice

# The carriageway of carriageway_samples (right edge y = 50) with a 3.5 m shoulder (its right
# border y = 46.5, not 49: an opened lane lies within the road); the shoulder of places 2 and 3
# (x 200-400) opened: the edge moved 2 m out (y = 48), the old one turned a dashed divider.
FIRST = HDMap(
    features=tuple(line_feature(5, BORDER, 46.5) if f.id == 5 else f for f in carriageway_lines()),
)


def _change(kind="lane_opened", effect=-2.0):
    places = tuple(PlaceChange(k, kind, 10, 5, effect, 9.0, ("b1", "b2", "b3"), ("a1", "a2")) for k in CHANGED)
    return DetectedChange(7, 10, (kind,), places, ("a1", "a2"), 0.9)


def _local(*lines, x0=100.0, x1=499.0):
    return HDMap(features=tuple(line_feature(100 + i, t, y, x0, x1) for i, (t, y) in enumerate(lines)))


def _ys(hdmap, ftype, x=300.0):
    return sorted(
        round(float(y), 2)
        for f in hdmap.features
        if int(f.type) == int(ftype)
        for y in f.points[np.abs(f.points[:, 0] - x) < 0.5, 1]
    )


def test_the_edge_no_drive_after_the_change_saw_moves_out_by_the_confirmed_move():
    # the drives after it kept to the left lanes: they saw the old edge turned divider, not the
    # moved edge line
    local = _local((DASHED, 50.0), (DASHED, 53.5), (DASHED, 57.0), (SOLID, 60.5))
    moved, kept = opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT)
    assert len(kept) == 0  # the local map saw every other line
    assert moved.pieces and all(p.feature_id == 1 for p in moved.pieces)
    assert _ys(moved.map, SOLID) == [48.0, 60.5]  # only the rightmost marking moved
    assert _ys(moved.map, SOLID, x=150.0) == [50.0, 60.5]  # not beside the opened places
    edge = next(f for f in moved.map.features if f.id == 1)
    assert np.all(edge.drive_count[np.abs(edge.points[:, 0] - 300.0) < 50.0] == 0)
    # spliced: the moved edge stays, the old solid edge goes, the divider is the local map's
    poses = np.stack([np.arange(0.0, 600.0, 2.0), np.full(300, 58.75)], axis=1)
    reach = Reach(poses, 12.0, keep=moved.moved_to, take=moved.moved_from)
    out = splice(moved.map, local, PLACES, REBUILT, reach=reach)
    assert _ys(out, SOLID) == [48.0, 60.5]
    assert 50.0 in _ys(out, DASHED)
    # without it the rebuilt places had no right edge line at all
    plain = splice(FIRST, local, PLACES, REBUILT, reach=Reach(poses, 12.0))
    assert _ys(plain, SOLID) == [60.5]


def test_an_edge_the_drives_saw_is_theirs_and_other_changes_move_nothing():
    local = _local((SOLID, 48.1), (DASHED, 50.0), (DASHED, 53.5), (DASHED, 57.0), (SOLID, 60.5))
    assert not opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT)[0].pieces
    bare = _local((SOLID, 60.5))
    for other in (_change("lane_closed", 3.5), _change("geometry", -2.0)):
        moved, kept = opened_edge_moved(FIRST, bare, PLACES, [other], REBUILT)
        assert not moved.pieces and len(kept) == 0


def test_the_lines_a_lane_opened_left_alone_stay_where_the_drives_missed_them():
    # the drives after it saw the left edge and the first divider only: the second divider (53.5)
    # stays; the old edge (50) does not stay, it moves
    local = _local((DASHED, 57.0), (SOLID, 60.5))
    moved, kept = opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT)
    inside = kept[(kept[:, 0] > 200.0) & (kept[:, 0] < 400.0)]
    assert len(inside) and np.allclose(inside[:, 1], 53.5)
    # beside the opened places (rebuilt: a taper detection left out) the old edge does not stay
    # either, the other lines do
    assert not np.any(np.isclose(kept[:, 1], 50.0))
    assert np.any(np.isclose(kept[kept[:, 0] < 190.0, 1], 53.5))
    assert _ys(moved.map, SOLID) == [48.0, 60.5]


def test_a_place_where_no_drive_measured_the_move_gets_no_edge_model():
    # the drives after the change saw only the old edge turned divider (not measured): the edge
    # move there is unknown, the old edge neither moves nor stays
    local = _local((DASHED, 50.0), (DASHED, 53.5), (DASHED, 57.0), (SOLID, 60.5))
    rows = [EdgeEvidence(d, 1, k, 0.0, 10) for d in ("b1", "b2", "b3") for k in CHANGED]
    rows += [EdgeEvidence(d, 20, k, -1.8, 10, measured=False) for d in ("a1", "a2") for k in CHANGED]
    moved, kept = opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT, evidence=rows)
    assert not moved.pieces and len(kept) == 0
    # one of them measured 3 m: the edge moves by that, not by the mean with the divider's reading
    rows[-1] = EdgeEvidence("a2", 20, CHANGED[1], -3.0, 10)
    rows[-2] = EdgeEvidence("a2", 20, CHANGED[0], -3.0, 10)
    moved, _ = opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT, evidence=rows)
    assert _ys(moved.map, SOLID) == [47.0, 60.5]
