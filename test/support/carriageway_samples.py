"""A straight carriageway along +x for the tests of a changed place (``updates``).

Left of the driving direction is +y; places of 100 m. Right edge line (solid) y = 50, dashed
dividers 53.5 and 57, left edge 60.5; barriers 49 and 61.5. Places 2 and 3 (x 200-400) changed,
rebuilt with one place either side.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hdmap_core.model import FeatureType, MapFeature
from hdmap_core.updates.places import Places

PLACES = Places(100.0, {(i, 0): 0.0 for i in range(0, 6)})
SOLID, DASHED, BORDER = FeatureType.SOLID, FeatureType.DASHED, FeatureType.ROAD_BORDER
CHANGED = [(2, 0, 0), (3, 0, 0)]
REBUILT = {(1, 0, 0), *CHANGED, (4, 0, 0)}


def line_feature(
    fid: int,
    ftype: FeatureType,
    y: float,
    x0: float = 0.0,
    x1: float = 600.0,
    step: float = 1.0,
    shift: Callable[[np.ndarray], np.ndarray] | None = None,
) -> MapFeature:
    """A map line at ``y`` from ``x0`` to ``x1`` (plus ``shift(x)``), 20 drives, std 0.05 m."""
    x = np.arange(x0, x1 + 1e-9, step)
    yy = np.full(len(x), float(y)) if shift is None else float(y) + shift(x)
    return MapFeature(fid, ftype, np.stack([x, yy], axis=1), np.full(len(x), 20), np.full(len(x), 0.05))


def carriageway_lines() -> tuple[MapFeature, ...]:
    """The carriageway's four markings and two barriers (ids 1-6)."""
    return (
        line_feature(1, SOLID, 50.0),
        line_feature(2, DASHED, 53.5),
        line_feature(3, DASHED, 57.0),
        line_feature(4, SOLID, 60.5),
        line_feature(5, BORDER, 49.0),
        line_feature(6, BORDER, 61.5),
    )
