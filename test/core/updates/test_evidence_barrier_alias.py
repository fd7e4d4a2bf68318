"""A drive's border anchor is the barrier it saw, not the opposite carriageway's: a drive sees
the opposite median barrier too, which pairs with the map's median barrier a barrier gap off
(the map's opposite barrier runs the other way and pairs with nothing). A drive whose
localisation error puts its true border pair near the end of the search window, and which saw
its own barrier less than the opposite one, would read every place's markings off by their
lane alias against that anchor: a badly localised drive looking like a changed road."""

from __future__ import annotations

import numpy as np
import pytest

from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.evidence import fleet_evidence
from hdmap_core.updates.places import places_of

LENGTH_M = 600.0
LANE_M = 3.5
BARRIER, OPPOSITE = -4.0, -6.5  # the median barrier and the opposite carriageway's
MARKINGS = (0.0, LANE_M, 2 * LANE_M, 3 * LANE_M)
TYPES = (FeatureType.SOLID, FeatureType.DASHED, FeatureType.DASHED, FeatureType.SOLID)
SHOULDER = 3 * LANE_M + 4.0
ROW_Y = 40.0


def _line(y: float, x0: float = 0.0, x1: float = LENGTH_M) -> np.ndarray:
    x = np.arange(x0, x1 + 1.0, 2.0)
    return np.stack([x, np.full(len(x), ROW_Y + y)], axis=1)


def _map() -> HDMap:
    lines = [(FeatureType.ROAD_BORDER, _line(BARRIER)), (FeatureType.ROAD_BORDER, _line(SHOULDER))]
    lines.append((FeatureType.ROAD_BORDER, _line(OPPOSITE)[::-1]))  # mapped by the other direction
    lines += [(t, _line(y)) for t, y in zip(TYPES, MARKINGS)]
    return HDMap(
        features=tuple(
            MapFeature(i, t, p, np.ones(len(p), np.int64), np.zeros(len(p))) for i, (t, p) in enumerate(lines)
        )
    )


def _drive(error_m: float, barrier_seen: tuple[tuple[float, float], ...]) -> Drive:
    """A drive in the lane next to the barrier, everything it reports ``error_m`` to the left of
    the truth; it saw its own barrier over ``barrier_seen`` (x ranges) only, the opposite one all
    along, every marking within 10 m."""
    xy = _line(0.5 * LANE_M)
    dets = [Detection(FeatureType.ROAD_BORDER, _line(BARRIER, a, b)) for a, b in barrier_seen]
    dets.append(Detection(FeatureType.ROAD_BORDER, _line(OPPOSITE)))
    dets += [Detection(t, _line(y)) for t, y in zip(TYPES, MARKINGS) if abs(y - 0.5 * LANE_M) <= 10.0]
    dets = [Detection(d.type, d.points + [0.0, error_m]) for d in dets]
    yaw = np.zeros(len(xy))
    return Drive("d", xy + [0.0, error_m], yaw, np.arange(len(xy), dtype=np.int64) * 10**8, tuple(dets))


@pytest.mark.parametrize("seen", [((0.0, LENGTH_M),), ((0.0, 200.0), (300.0, 480.0))])
def test_a_badly_localised_drive_is_anchored_on_its_own_barrier(seen):
    error_m = 2.7  # map - drive: -2.7 m; the opposite barrier pairs at 2.5 - 2.7 = -0.2 m
    drive = _drive(error_m, seen)
    config = ChangeConfig()
    places = places_of([drive], cell_m=config.cell_m)
    ev = [e for e in fleet_evidence([drive], _map(), places, config=config) if e.n_cuts >= 10]
    assert len(ev) >= 5
    assert all(e.anchor_m == pytest.approx(-error_m, abs=0.1) for e in ev), [e.anchor_m for e in ev]
    disp = np.array([e.displacement_m for e in ev])
    assert np.isfinite(disp).sum() >= 5 and np.nanmax(np.abs(disp)) < 0.1, disp
