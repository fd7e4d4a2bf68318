"""A move of the markings near a lane width is measured as the move, not as its alias (the move
minus a lane): each moved line would otherwise pair with its neighbour's old place. A shift zone
starts with a taper from 0, which each drive follows along the road."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.evidence import PlaceEvidence, fleet_evidence, unwrap_aliases
from hdmap_core.updates.places import places_of

LENGTH_M = 700.0
TAPER_M = (200.0, 300.0)  # the move grows from 0 to its size over this stretch of x
LANE_M = 3.5
BORDERS = (-4.0, 3 * LANE_M + 4.0)  # barrier and shoulder border, staying
MARKINGS = (0.0, LANE_M, 2 * LANE_M, 3 * LANE_M)  # y of the lines along x
TYPES = (FeatureType.SOLID, FeatureType.DASHED, FeatureType.DASHED, FeatureType.SOLID)
ROW_Y = 40.0  # every line in one row of 100 m cells


def _line(y: float, shift_m: float = 0.0) -> np.ndarray:
    x = np.arange(0.0, LENGTH_M + 1.0, 2.0)
    ramp = np.clip((x - TAPER_M[0]) / (TAPER_M[1] - TAPER_M[0]), 0.0, 1.0)
    return np.stack([x, ROW_Y + y + shift_m * ramp], axis=1)


def _map() -> HDMap:
    ys = [(FeatureType.ROAD_BORDER, y) for y in BORDERS] + list(zip(TYPES, MARKINGS))
    feats = []
    for i, (t, y) in enumerate(ys):
        pts = _line(y)
        feats.append(MapFeature(i, t, pts, np.ones(len(pts), np.int64), np.zeros(len(pts))))
    return HDMap(features=tuple(feats))


def _drive(shift_m: float, lane: int) -> Drive:
    """A drive along lane ``lane`` (0 = next to the barrier) of the road whose markings moved by
    ``shift_m`` to the left past the taper, the borders staying; it sees every line within 10 m."""
    xy = _line(MARKINGS[0] + (lane + 0.5) * LANE_M, shift_m)
    dets = [Detection(FeatureType.ROAD_BORDER, _line(y)) for y in BORDERS]
    dets += [Detection(t, _line(y, shift_m)) for t, y in zip(TYPES, MARKINGS)]
    dets = [d for d in dets if abs(d.points[0, 1] - xy[0, 1]) <= 10.0]
    yaw = np.arctan2(np.gradient(xy[:, 1]), np.gradient(xy[:, 0]))
    return Drive(f"d{lane}", xy, yaw, np.arange(len(xy), dtype=np.int64) * 10**8, tuple(dets))


@pytest.mark.parametrize("shift_m", [0.0, 1.0, 3.0, -3.0])
def test_a_move_near_a_lane_width_is_not_read_as_its_alias(shift_m):
    drives = [_drive(shift_m, lane) for lane in (0, 1)]
    config = ChangeConfig()
    places = places_of(drives, cell_m=config.cell_m)
    ev = [e for e in fleet_evidence(drives, _map(), places, config=config) if e.n_cuts >= 10]
    # map - drive: the markings moved left by shift_m read as -shift_m past the taper, 0 before it
    past = [e.displacement_m for e in ev if e.key[0] * config.cell_m >= TAPER_M[1]]
    before = [e.displacement_m for e in ev if (e.key[0] + 1) * config.cell_m <= TAPER_M[0]]
    assert len(past) >= 6 and len(before) >= 2
    assert np.all(np.abs(np.array(past) + shift_m) < 0.1), past
    assert np.all(np.abs(np.array(before)) < 0.1), before


def _ev(drive: str, t: int, disp: float, key=(0, 0, 0)) -> PlaceEvidence:
    return PlaceEvidence(drive, t, key, 25, disp, 0.0, True, disp, 40, 40, 0, 40, 0, 40, 0)


def test_a_drive_reading_the_alias_of_the_places_move_reads_the_move():
    """A drive after the change that missed the taper reads the move less a lane; two others read
    the move: it is read as the move too. Drives before the first of them, and places where
    fewer than two drives read a lane-sized move, stay as they are."""
    ev = [_ev("b1", 1, -0.3), _ev("b2", 2, 0.05), _ev("a1", 10, 3.1), _ev("a2", 11, -0.4), _ev("a3", 12, 3.2)]
    ev += [_ev("a1", 10, 3.1, (1, 0, 0)), _ev("a2", 11, -0.4, (1, 0, 0))]
    out = {(e.drive_id, e.key): e.displacement_m for e in unwrap_aliases(ev, ChangeConfig())}
    assert out[("a2", (0, 0, 0))] == pytest.approx(3.1)
    assert out[("b1", (0, 0, 0))] == pytest.approx(-0.3)  # before the move was seen
    assert out[("b2", (0, 0, 0))] == pytest.approx(0.05)
    assert out[("a2", (1, 0, 0))] == pytest.approx(-0.4)  # one drive is no move
