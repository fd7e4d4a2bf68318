"""An opened shoulder's edge line no drive after the change saw, moved by the confirmed move
(``updates.edges.opened_edge_moved``)."""

from __future__ import annotations

import numpy as np
from carriageway_samples import CHANGED, DASHED, PLACES, REBUILT, SOLID, carriageway_lines, line_feature

from hdmap_core.model import HDMap
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.edges import opened_edge_moved
from hdmap_core.updates.splice import Reach, splice

# The carriageway of carriageway_samples (right edge y = 50); the shoulder of places 2 and 3
# (x 200-400) opened: the edge moved 2 m out (y = 48), the old one turned a dashed divider.
FIRST = HDMap(features=(*carriageway_lines(),))


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
    moved = opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT)
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
    assert not opened_edge_moved(FIRST, local, PLACES, [_change()], REBUILT).pieces
    bare = _local((SOLID, 60.5))
    assert not opened_edge_moved(FIRST, bare, PLACES, [_change("lane_closed", 3.5)], REBUILT).pieces
    assert not opened_edge_moved(FIRST, bare, PLACES, [_change("geometry", -2.0)], REBUILT).pieces
