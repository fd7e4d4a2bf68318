"""A tiny deterministic fleet on a gently curved one-way road, for the stage 1-4 tests.

Road (lateral positions from the road centre line, + = left of the driving direction):

    +6.5  ========================  road border
    +5.25 ------------------------  solid
    +1.75 - - - - - - - - - - - -   dashed
    -1.75 - - - - - - - - - - - -   dashed
    -5.25 ------------------------  solid
    -6.5  ========================  road border

Each drive drives one lane centre (-3.5, 0, +3.5) over [s0, s1] and has one lateral offset
``bias``: its trajectory and every detection are shifted by ``bias`` to the left (a localization
error), so the correction to ADD to its samples is ``-bias``.
"""

from __future__ import annotations

import numpy as np

from hdmap_core.model import Detection, Drive, FeatureType

LINES = (
    (6.5, FeatureType.ROAD_BORDER),
    (5.25, FeatureType.SOLID),
    (1.75, FeatureType.DASHED),
    (-1.75, FeatureType.DASHED),
    (-5.25, FeatureType.SOLID),
    (-6.5, FeatureType.ROAD_BORDER),
)
RADIUS_M = 2000.0


def centre(s: np.ndarray, *, reverse: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 2), heading (N,)) of the road centre line at distance s; an arc of RADIUS_M."""
    phi = s / RADIUS_M
    pts = np.stack([RADIUS_M * np.sin(phi), RADIUS_M * (1.0 - np.cos(phi))], axis=1)
    return pts, phi


def offset_line(s: np.ndarray, lateral: float) -> tuple[np.ndarray, np.ndarray]:
    pts, h = centre(s)
    n = np.stack([-np.sin(h), np.cos(h)], axis=1)
    return pts + lateral * n, h


def make_drive(
    drive_id: str,
    *,
    lane: float,
    bias: float,
    s0: float = 0.0,
    s1: float = 300.0,
    noise_m: float = 0.0,
    lines: tuple = LINES,
    rng: np.random.Generator | None = None,
    reverse: bool = False,
) -> Drive:
    """One drive along lane centre ``lane`` with lateral error ``bias`` [m] (see module doc).

    ``reverse``: the drive goes the other way (its points and yaw reversed).
    """
    s = np.arange(s0, s1 + 1e-9, 1.0)
    xy, h = offset_line(s, lane + bias)
    dets = []
    for lat, ftype in lines:
        p, _ = offset_line(s, lat + bias)
        if noise_m > 0 and rng is not None:
            p = p + rng.normal(0.0, noise_m, p.shape)
        if reverse:
            p = p[::-1]
        dets.append(Detection(type=ftype, points=p))
    yaw = h
    if reverse:
        xy, yaw = xy[::-1], (h[::-1] + np.pi + np.pi) % (2 * np.pi) - np.pi
    stamps = (np.arange(len(s)) * 50_000_000).astype(np.int64)
    return Drive(drive_id=drive_id, xy=xy, yaw=yaw, stamps_ns=stamps, detections=tuple(dets))


def make_fleet(biases: list[float], *, noise_m: float = 0.0, seed: int = 0, s1: float = 300.0) -> list[Drive]:
    rng = np.random.default_rng(seed)
    lanes = (-3.5, 0.0, 3.5)
    return [
        make_drive(f"d{i}", lane=lanes[i % 3], bias=b, noise_m=noise_m, rng=rng, s1=s1) for i, b in enumerate(biases)
    ]
