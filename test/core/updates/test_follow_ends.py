"""The ends of a shift zone: the rebuilt places reach past a cell's corner, and the first map's
lines no drive after the change saw stay where the lines the drives saw had not moved yet."""

from __future__ import annotations

import numpy as np

from hdmap_core.model import Drive, FeatureType, HDMap, MapFeature
from hdmap_core.updates.follow import along_drives
from hdmap_core.updates.places import places_of
from hdmap_core.updates.unseen import unseen_at_ends


def _drive(xy: np.ndarray) -> Drive:
    yaw = np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0]))
    return Drive("d", xy, yaw, np.arange(len(xy), dtype=np.int64) * 10**8, ())


def test_a_corner_of_a_cell_is_no_place_along_the_drive():
    """With one place each way, the place before the changed one is a 30 m corner: the 70 m
    place before it is taken too; after it, one place of 100 m."""
    x = np.arange(0.0, 500.0, 1.0)
    drive = _drive(np.stack([x, 90.0 + 10.0 / 270.0 * x], axis=1))  # crosses y = 100 at x = 270
    places = places_of([drive], cell_m=100.0)
    out = along_drives([drive], places, {(3, 1, 0): 7}, 1)
    assert set(out) == {(3, 1, 0), (2, 1, 0), (2, 0, 0), (4, 1, 0)}
    assert set(out.values()) == {7}


LANE_M = 3.5


def _move(x: np.ndarray) -> np.ndarray:
    """A 3 m shift with 100 m tapers: 0 before x = 200, 3 m from 300 to 700, 0 again from 800."""
    return 3.0 * np.clip(np.minimum((x - 200.0) / 100.0, (800.0 - x) / 100.0), 0.0, 1.0)


def _map(lines: list[np.ndarray]) -> HDMap:
    return HDMap(
        features=tuple(
            MapFeature(i, FeatureType.DASHED, p, np.ones(len(p), np.int64), np.zeros(len(p)))
            for i, p in enumerate(lines)
        )
    )


def test_unseen_lines_stay_where_the_seen_ones_had_not_moved():
    x = np.arange(0.0, 1001.0, 1.0)
    y0 = 50.0
    first = _map([np.stack([x, np.full(len(x), y0 + k * LANE_M)], axis=1) for k in range(3)])
    # the drives after the change saw the first line only (moved right: -y), all along
    seen = np.stack([x[100:901], y0 - _move(x[100:901])], axis=1)
    local = _map([seen])
    places = places_of([_drive(np.stack([x, np.full(len(x), y0 - 1.75)], axis=1))], cell_m=100.0)
    rebuilt = {(i, 0, 0) for i in range(1, 9)}  # x 100-900: the zone with its tapers
    kept = unseen_at_ends(first, local, places, rebuilt)
    assert len(kept) > 0
    # only the unseen lines (not the seen one), near the tapers' outer ends, where the seen line
    # had moved by less than about the threshold
    assert np.all(np.abs(kept[:, 1] - y0) > LANE_M - 0.1)
    assert np.all(_move(kept[:, 0]) <= 1.0), kept[_move(kept[:, 0]) > 1.0]
    assert kept[:, 0].min() <= 101.0 and kept[:, 0].max() >= 899.0  # from both ends
    assert np.all((kept[:, 0] < 300.0) | (kept[:, 0] > 700.0))  # none where it moved 3 m


def test_unseen_lines_are_not_kept_where_the_drives_measured_the_move():
    """Once several drives passed after the change, the first map (every drive's consensus) holds
    the moved line as well: the seen line lies on a first-map line all along and the walk from
    the ends would run through the zone, keeping the old lines where they moved 3 m. The places
    where the drives measured the move end it."""
    x = np.arange(0.0, 1001.0, 1.0)
    y0 = 50.0
    old = [np.stack([x, np.full(len(x), y0 + k * LANE_M)], axis=1) for k in range(3)]
    seen = np.stack([x[100:901], y0 - _move(x[100:901])], axis=1)
    first = _map([*old, seen])
    local = _map([seen])
    places = places_of([_drive(np.stack([x, np.full(len(x), y0 - 1.75)], axis=1))], cell_m=100.0)
    rebuilt = {(i, 0, 0) for i in range(1, 9)}
    through = unseen_at_ends(first, local, places, rebuilt)
    assert np.any((through[:, 0] > 300.0) & (through[:, 0] < 700.0))  # what the places' rule is for
    moved = frozenset((i, 0, 0) for i in range(3, 7))  # x 300-700: the lines moved 3 m there
    kept = unseen_at_ends(first, local, places, rebuilt, moved)
    assert len(kept) > 0 and kept[:, 0].min() <= 101.0 and kept[:, 0].max() >= 899.0
    assert np.all((kept[:, 0] < 300.0) | (kept[:, 0] >= 700.0))
