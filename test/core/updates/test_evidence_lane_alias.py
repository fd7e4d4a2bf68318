"""A move of the markings near a lane width is measured as the move, not as its alias (the move
minus a lane): each moved line would otherwise pair with its neighbour's old place."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.evidence import fleet_evidence
from hdmap_core.updates.places import places_of

LENGTH_M = 400.0
LANE_M = 3.5
BORDERS = (-4.0, 3 * LANE_M + 4.0)  # barrier and shoulder border, staying
MARKINGS = (0.0, LANE_M, 2 * LANE_M, 3 * LANE_M)  # y of the lines along x
TYPES = (FeatureType.SOLID, FeatureType.DASHED, FeatureType.DASHED, FeatureType.SOLID)  # edges solid


def _line(y: float) -> np.ndarray:
    x = np.arange(0.0, LENGTH_M + 1.0, 2.0)
    return np.stack([x, np.full_like(x, 40.0 + y)], axis=1)  # all in one row of 100 m cells


def _map() -> HDMap:
    ys = [(FeatureType.ROAD_BORDER, y) for y in BORDERS] + list(zip(TYPES, MARKINGS))
    feats = []
    for i, (t, y) in enumerate(ys):
        pts = _line(y)
        feats.append(MapFeature(i, t, pts, np.ones(len(pts), np.int64), np.zeros(len(pts))))
    return HDMap(features=tuple(feats))


def _drive(shift_m: float, lane: int, name: str) -> Drive:
    """A drive in lane ``lane`` (0 = next to the barrier) of the road whose markings moved by
    ``shift_m`` to the left, the borders staying; it sees every line within 12 m."""
    y0 = MARKINGS[0] + shift_m + (lane + 0.5) * LANE_M
    xy = _line(y0)
    dets = [Detection(FeatureType.ROAD_BORDER, _line(y)) for y in BORDERS]
    dets += [Detection(t, _line(y + shift_m)) for t, y in zip(TYPES, MARKINGS)]
    dets = [d for d in dets if abs(d.points[0, 1] - xy[0, 1]) <= 12.0]
    return Drive(name, xy, np.zeros(len(xy)), np.arange(len(xy), dtype=np.int64) * 10**8, tuple(dets))


@pytest.mark.parametrize("shift_m", [0.0, 1.0, 3.0, -3.0])
def test_a_move_near_a_lane_width_is_not_read_as_its_alias(shift_m):
    """Two drives, one per lane, each seeing every line: their displacement is the move, not the
    move minus a lane (which pairs the solid edge line with a dashed one)."""
    drives = [_drive(shift_m, lane, f"d{lane}") for lane in (0, 1)]
    config = ChangeConfig()
    places = places_of(drives, cell_m=config.cell_m)
    ev = [e for e in fleet_evidence(drives, _map(), places, config=config) if e.n_cuts >= 10]
    assert len({e.drive_id for e in ev}) == 2
    disp = np.array([e.displacement_m for e in ev])
    # map - drive: the markings moved left by shift_m read as -shift_m
    assert np.all(np.abs(disp + shift_m) < 0.1), disp


def test_one_drive_alone_does_not_take_an_alias():
    """What a single drive's lines say is not enough to read a move a lane away."""
    drive = _drive(3.0, 0, "d0")
    config = ChangeConfig()
    places = places_of([drive], cell_m=config.cell_m)
    ev = [e for e in fleet_evidence([drive], _map(), places, config=config) if e.n_cuts >= 10]
    assert ev
    assert all(abs(e.displacement_m - (LANE_M - 3.0)) < 0.1 for e in ev)
    assert all(abs(e.alias_m + 3.0) < 0.1 and e.alias_gain > 0.5 for e in ev)
