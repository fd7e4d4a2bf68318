"""The unseen markings along a shift's tapers, moved as the lines seen beside them (``updates.tapers``)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from carriageway_samples import BORDER, CHANGED, DASHED, PLACES, REBUILT, carriageway_lines, line_feature

from hdmap_core.model import HDMap
from hdmap_core.updates.detect import DetectedChange, PlaceChange
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.tapers import taper_moved
from hdmap_core.updates.unseen import unseen_moved

# The carriageway of carriageway_samples and a ramp's dashed line beyond the right barrier (49) at
# 46; places 2 and 3 (x 200-400) shifted 1.5 m right, the tapers 150-200 and 400-450 (in the
# rebuilt places 1 and 4).
FIRST = HDMap(features=(*carriageway_lines(), line_feature(7, DASHED, 46.0, 100.0, 499.0)))


def _taper(x):
    return -1.5 * np.clip(np.minimum(x - 150.0, 450.0 - x) / 50.0, 0.0, 1.0)


def _local():
    """The aligned rebuild of places 1-4 from the drives after the change: they saw the two
    dividers (the edge lines and the ramp's line they did not)."""
    return HDMap(
        features=tuple(line_feature(100 + i, DASHED, y, 100.0, 499.0, shift=_taper) for i, y in enumerate((53.5, 57.0)))
    )


def _evidence():
    out = []
    for d in ("a1", "a2"):
        for key in sorted(REBUILT):
            disp = 1.5 if key in CHANGED else 0.0  # the markings moved right of the drives
            out.append(PlaceEvidence(d, 10, key, 25, disp, 0.0, True, disp, 40, 40, 0, 40, 0, 40, 0))
    return out


def _change(kinds=("geometry",)):
    places = tuple(PlaceChange(k, "geometry", 10, 5, 1.5, 9.0, ("b1", "b2", "b3"), ("a1", "a2")) for k in CHANGED)
    return DetectedChange(7, 10, kinds, places, ("a1", "a2"), 0.9)


def _at(hdmap, fid, x):
    f = next(f for f in hdmap.features if f.id == fid)
    i = int(np.argmin(np.abs(f.points[:, 0] - x)))
    return f.points[i, 1], int(np.asarray(f.drive_count)[i])


def test_the_unseen_lines_of_the_tapers_follow_the_lines_seen_beside_them():
    moved = unseen_moved(FIRST, _local(), PLACES, [_change()], _evidence(), REBUILT)
    # the shifted places' unseen edge lines moved 1.5 m; along the tapers nothing yet (the
    # places there are no moved carriageway: most of their lines did not move)
    assert _at(moved.map, 1, 300.0)[0] == 50.0 - 1.5
    assert _at(moved.map, 1, 180.0)[0] == 50.0
    got = taper_moved(FIRST, moved, _local(), PLACES, [_change()], REBUILT)
    for fid, y in ((1, 50.0), (4, 60.5)):  # the edge lines no drive after the change saw
        for x in (165.0, 180.0, 195.0, 405.0, 420.0, 435.0):
            at, count = _at(got.map, fid, x)
            assert abs(at - (y + _taper(np.array(x)))) < 0.15, (fid, x, at)
            assert count == 0  # a model, not an observation
        # the shifted places keep unseen_moved's model
        assert _at(got.map, fid, 300.0) == _at(moved.map, fid, 300.0)
    # before the tapers the lines stay where they were (a move of the field's scatter at most)
    assert abs(_at(got.map, 1, 120.0)[0] - 50.0) < 0.05
    # a piece shorter than a place that begins and ends in the rebuilt places (the consensus's
    # blend of both roads) is no line of the road as it was: it does not move
    stub = line_feature(8, DASHED, 52.0, 160.0, 190.0)
    first = HDMap(features=(*FIRST.features, stub))
    with_stub = taper_moved(
        first,
        unseen_moved(first, _local(), PLACES, [_change()], _evidence(), REBUILT),
        _local(),
        PLACES,
        [_change()],
        REBUILT,
    )
    np.testing.assert_array_equal(next(f for f in with_stub.map.features if f.id == 8).points, stub.points)
    assert _at(with_stub.map, 1, 180.0) == _at(got.map, 1, 180.0)
    # the ramp's line beyond the barrier is not on the moved carriageway; the barriers stay
    for fid, y in ((7, 46.0), (5, 49.0), (6, 61.5)):
        assert {_at(got.map, fid, x)[0] for x in (170.0, 300.0, 430.0)} == {y}
    # recorded as the change's modelled pieces, after unseen_moved's
    assert got.pieces[: len(moved.pieces)] == moved.pieces
    taper = got.pieces[len(moved.pieces) :]
    assert taper and {p.change_id for p in taper} == {7}
    assert all(np.all(np.abs(p.points[:, 1] - p.from_points[:, 1] - p.move_m) < 1e-9) for p in taper)


def test_no_taper_model_without_a_shift_nor_against_its_direction():
    moved = unseen_moved(FIRST, _local(), PLACES, [_change()], _evidence(), REBUILT)
    for kinds in (("geometry", "lane_closed"), ("geometry", "type"), ("type",)):
        assert taper_moved(FIRST, moved, _local(), PLACES, [_change(kinds)], REBUILT) is moved
    # the drives measured the shift to the left: the lines seen moved right are no model for it
    left = DetectedChange(
        7, 10, ("geometry",), tuple(replace(p, effect=-1.5) for p in _change().places), ("a1", "a2"), 0.9
    )
    got = taper_moved(FIRST, moved, _local(), PLACES, [left], REBUILT)
    assert _at(got.map, 1, 180.0)[0] == 50.0
    # the control: with the change as measured the taper moves
    assert _at(taper_moved(FIRST, moved, _local(), PLACES, [_change()], REBUILT).map, 1, 180.0)[0] < 49.5


def test_a_shift_near_a_lanes_width_pairs_each_line_with_its_own_old_place():
    """3 m right on 3.5 m lanes: past half the taper a moved divider lies nearer its right
    neighbour's old place (1.0 m) than its own (2.5 m); paired by the move in the shift's
    direction, the unseen edge lines follow the taper all along."""

    def taper3(x):
        return 2.0 * _taper(x)

    first = HDMap(features=(*carriageway_lines()[:4], line_feature(5, BORDER, 45.0), line_feature(6, BORDER, 65.0)))
    local = HDMap(
        features=tuple(line_feature(100 + i, DASHED, y, 100.0, 499.0, shift=taper3) for i, y in enumerate((53.5, 57.0)))
    )
    change = DetectedChange(
        7, 10, ("geometry",), tuple(replace(p, effect=3.0) for p in _change().places), ("a1", "a2"), 0.9
    )
    got = taper_moved(
        first, unseen_moved(first, local, PLACES, [change], [], REBUILT), local, PLACES, [change], REBUILT
    )
    for fid, y in ((1, 50.0), (4, 60.5)):
        for x in (160.0, 175.0, 190.0, 410.0, 425.0, 440.0):
            assert abs(_at(got.map, fid, x)[0] - (y + taper3(np.array(x)))) < 0.15, (fid, x)


def test_the_places_where_the_drives_measured_the_lines_moved_are_left_to_unseen_moved():
    """There the lines seen moved 1.5 and 0.9 m (not alike): ``unseen_moved`` models nothing, and
    no field may move the unseen lines either."""
    local = HDMap(
        features=(
            line_feature(100, DASHED, 53.5, 100.0, 499.0, shift=_taper),
            line_feature(101, DASHED, 57.0, 100.0, 499.0, shift=lambda x: 0.6 * _taper(x)),
        )
    )
    moved = unseen_moved(FIRST, local, PLACES, [_change()], _evidence(), REBUILT)
    assert _at(moved.map, 1, 300.0)[0] == 50.0
    got = taper_moved(FIRST, moved, local, PLACES, [_change()], REBUILT)
    for x in (210.0, 300.0, 390.0):
        assert _at(got.map, 1, x) == (50.0, 20)
    # the control: the same lines, the change's places not measured as moved (effect below the
    # smallest shift), are moved by the field
    small = DetectedChange(
        7, 10, ("geometry",), tuple(replace(p, effect=0.4) for p in _change().places), ("a1", "a2"), 0.9
    )
    assert _at(taper_moved(FIRST, moved, local, PLACES, [small], REBUILT).map, 1, 300.0)[0] < 50.0 - 0.2
