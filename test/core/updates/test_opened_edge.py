"""An opened shoulder's edge line no drive after the change saw, moved by the confirmed move
(``updates.edges.opened_edge_moved``)."""

from __future__ import annotations

from dataclasses import replace

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


def test_an_edge_piece_the_first_map_has_moved_already_is_not_moved_again():
    # the first map (every drive) has the moved edge (y = 48) where the 2 drives after the change
    # saw it (drive_count 2) beside the old one; the drives after it of the rebuilt map saw neither
    young = line_feature(7, SOLID, 48.0, 200.0, 399.0)
    young = type(young)(7, SOLID, young.points, np.full(len(young.points), 2), young.lateral_std)
    wide = tuple(line_feature(5, BORDER, 44.0) if f.id == 5 else f for f in carriageway_lines())
    first = HDMap(features=(*wide, young))
    local = _local((DASHED, 50.0), (DASHED, 53.5), (DASHED, 57.0), (SOLID, 60.5))
    moved, _ = opened_edge_moved(first, local, PLACES, [_change()], REBUILT)
    # the old edge moves onto it, it stays (not 2 m further out, y = 46)
    assert _ys(moved.map, SOLID) == [48.0, 48.0, 60.5]
    assert all(p.feature_id == 1 for p in moved.pieces)


def test_no_marking_moves_beyond_the_road_border_right_of_it():
    # a 2.5 m shoulder (border y = 47.5); the drives after the change measured 3 m
    narrow = HDMap(features=tuple(line_feature(5, BORDER, 47.5) if f.id == 5 else f for f in carriageway_lines()))
    local = _local((DASHED, 50.0), (DASHED, 53.5), (DASHED, 57.0), (SOLID, 60.5))
    moved, _ = opened_edge_moved(narrow, local, PLACES, [_change(effect=-3.0)], REBUILT)
    assert moved.pieces
    assert _ys(moved.map, SOLID) == [47.5, 60.5]  # on the border, not 0.5 m beyond it
    # within the modelled edge's uncertainty (0.2 m) of the mapped border the move stands
    moved, _ = opened_edge_moved(narrow, local, PLACES, [_change(effect=-2.6)], REBUILT)
    assert _ys(moved.map, SOLID) == [47.4, 60.5]
    # an edge on the border already: nothing to move
    at_border = HDMap(features=tuple(line_feature(5, BORDER, 49.8) if f.id == 5 else f for f in carriageway_lines()))
    assert not opened_edge_moved(at_border, local, PLACES, [_change()], REBUILT)[0].pieces
    # ... or a little beyond it (the first map's border 0.2 m left of the line)
    beyond = HDMap(features=tuple(line_feature(5, BORDER, 50.2) if f.id == 5 else f for f in carriageway_lines()))
    assert not opened_edge_moved(beyond, local, PLACES, [_change()], REBUILT)[0].pieces


def test_a_taper_place_one_drive_measured_gets_no_edge_model():
    # places 2, 3 confirmed (both drives after the change measured 2.5 m), place 4 joined along
    # the road (a taper): one drive measured 1.2 m there, the other saw too little
    places = tuple(PlaceChange(k, "lane_opened", 10, 5, -2.5, 9.0, ("b1", "b2", "b3"), ("a1", "a2")) for k in CHANGED)
    taper = PlaceChange((4, 0, 0), "lane_opened", 10, 5, -1.2, np.nan, ("b1", "b2", "b3"), ("a1",), extended=True)
    change = DetectedChange(7, 10, ("lane_opened",), (*places, taper), ("a1", "a2"), 0.9)
    keys = [*CHANGED, (4, 0, 0)]
    rows = [EdgeEvidence(d, 1, k, 0.0, 10) for d in ("b1", "b2", "b3") for k in keys]
    rows += [EdgeEvidence(d, 20, k, -2.5, 10) for d in ("a1", "a2") for k in CHANGED]
    local = _local((DASHED, 50.0), (DASHED, 53.5), (DASHED, 57.0), (SOLID, 60.5))
    one = [*rows, EdgeEvidence("a1", 20, (4, 0, 0), -1.2, 10)]
    moved, _ = opened_edge_moved(FIRST, local, PLACES, [change], REBUILT, evidence=one)
    assert _ys(moved.map, SOLID) == [47.5, 60.5]  # the confirmed places moved
    assert _ys(moved.map, SOLID, x=450.0) == [50.0, 60.5]  # the taper place not
    # two drives that measured it: the taper place's move is theirs
    two = [*one, EdgeEvidence("a2", 20, (4, 0, 0), -1.2, 10)]
    change2 = replace(change, places=(*places, replace(taper, drives_after=("a1", "a2"))))
    moved, _ = opened_edge_moved(FIRST, local, PLACES, [change2], REBUILT, evidence=two)
    assert _ys(moved.map, SOLID, x=450.0) == [48.8, 60.5]
    # one drive that measured the change's move there (within the match radius): it moves by it
    full = [*rows, EdgeEvidence("a1", 20, (4, 0, 0), -2.4, 10)]
    moved, _ = opened_edge_moved(FIRST, local, PLACES, [change], REBUILT, evidence=full)
    assert _ys(moved.map, SOLID, x=450.0) == [47.6, 60.5]
