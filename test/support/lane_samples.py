"""Small hand-made maps for the lane tests: straight one-way roads along +x with a topology node
every 2 m at the road middle.

``three_lanes`` (lateral positions, + = left of the driving direction):

    +6.5  ==========================  road border
    +5.25 --------------------------  solid
    +1.75 - - - - - - - - - - - - -   dashed
    -1.75 - - - - - - - - - - - - -   dashed
    -5.25 --------------------------  solid
    -6.5  ==========================  road border

``lane_gain``: the same up to x = 400; then the right edge line moves out to -8.75 over 100 m
(a taper) and a dashed line starts at -5.25 at x = 450: an exit lane opens on the right.
"""

from __future__ import annotations

import numpy as np

from hdmap_core.model import FeatureType, HDMap, MapFeature, TopologyNode

THREE = (
    (6.5, FeatureType.ROAD_BORDER),
    (5.25, FeatureType.SOLID),
    (1.75, FeatureType.DASHED),
    (-1.75, FeatureType.DASHED),
    (-5.25, FeatureType.SOLID),
    (-6.5, FeatureType.ROAD_BORDER),
)


def _feature(fid: int, ftype: FeatureType, pts: np.ndarray) -> MapFeature:
    return MapFeature(fid, ftype, pts, np.full(len(pts), 10), np.full(len(pts), 0.05))


def _topology(length_m: float, width: np.ndarray | float, y0: float = 0.0) -> tuple[TopologyNode, ...]:
    x = np.arange(1.0, length_m, 2.0)
    w = np.broadcast_to(np.asarray(width, dtype=float), x.shape)
    ids = 1000 + np.arange(len(x))
    return tuple(
        TopologyNode(int(ids[i]), np.array([x[i], y0]), 0.0, float(w[i]), (int(ids[i + 1]),) if i + 1 < len(x) else ())
        for i in range(len(x))
    )


def three_lanes(length_m: float = 800.0) -> HDMap:
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    feats = tuple(_feature(i + 1, t, np.stack([x, np.full_like(x, y)], axis=1)) for i, (y, t) in enumerate(THREE))
    return HDMap(features=feats, topology=_topology(length_m, 13.0))


def missing_marking(length_m: float = 600.0) -> HDMap:
    """``three_lanes`` without the right dashed line (-1.75) between x = 100 and x = 350."""
    base = three_lanes(length_m)
    feats = [f for f in base.features if f.id != 4]
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    for fid, keep in ((4, x <= 100.0), (8, x >= 350.0)):
        feats.append(_feature(fid, FeatureType.DASHED, np.stack([x[keep], np.full(keep.sum(), -1.75)], axis=1)))
    return HDMap(features=tuple(feats), topology=base.topology)


def junction_gap(length_m: float = 600.0) -> HDMap:
    """``three_lanes`` with no line at all between x = 300 and x = 330 (a junction without markings)."""
    base = three_lanes(length_m)
    feats = []
    for f in base.features:
        for part, keep in ((0, f.points[:, 0] <= 300.0), (100, f.points[:, 0] >= 330.0)):
            feats.append(_feature(f.id + part, f.type, f.points[keep]))
    return HDMap(features=tuple(feats), topology=base.topology)


def lane_gain(length_m: float = 800.0) -> HDMap:
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    edge = -5.25 - 3.5 * np.clip((x - 400.0) / 100.0, 0.0, 1.0)
    outer = edge - 1.25
    feats = [_feature(i + 1, t, np.stack([x, np.full_like(x, y)], axis=1)) for i, (y, t) in enumerate(THREE[:4])]
    feats.append(_feature(5, FeatureType.SOLID, np.stack([x, edge], axis=1)))
    feats.append(_feature(6, FeatureType.ROAD_BORDER, np.stack([x, outer], axis=1)))
    xd = x[x >= 450.0]
    feats.append(_feature(7, FeatureType.DASHED, np.stack([xd, np.full_like(xd, -5.25)], axis=1)))
    xt = np.arange(1.0, length_m, 2.0)
    half_right = 6.5 + 3.5 * np.clip((xt - 400.0) / 100.0, 0.0, 1.0)
    # the node sits in the middle of the road: its width grows with the taper
    nodes = _topology(length_m, 6.5 + half_right)
    nodes = tuple(
        TopologyNode(n.id, np.array([n.position[0], (6.5 - hr) / 2.0]), n.heading, n.width, n.successors)
        for n, hr in zip(nodes, half_right, strict=True)
    )
    return HDMap(features=tuple(feats), topology=nodes)


def handover(length_m: float = 250.0) -> HDMap:
    """``three_lanes`` whose left edge line (+5.25) ends at x = 100 where another solid line goes on
    0.7 m further out (the map hands the line over to another feature), and whose right dashed line
    (-1.75) is called solid for 6 m at x = 150 (a flicker of the type, not a change of the lanes)."""
    base = three_lanes(length_m)
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    feats = [f for f in base.features if f.id not in (2, 4)]
    left = x <= 100.0
    feats.append(_feature(2, FeatureType.SOLID, np.stack([x[left], np.full(left.sum(), 5.25)], axis=1)))
    feats.append(_feature(12, FeatureType.SOLID, np.stack([x[~left], np.full((~left).sum(), 5.95)], axis=1)))
    for fid, keep, t in (
        (4, x < 150.0, FeatureType.DASHED),
        (14, (x >= 150.0) & (x <= 156.0), FeatureType.SOLID),
        (24, x > 156.0, FeatureType.DASHED),
    ):
        feats.append(_feature(fid, t, np.stack([x[keep], np.full(keep.sum(), -1.75)], axis=1)))
    return HDMap(features=tuple(feats), topology=base.topology)


def two_way(length_m: float = 250.0) -> HDMap:
    """A two-way road along x, one lane each way: road borders at -4 (mapped eastbound) and +4
    (mapped westbound) and a dashed centre line at 0 mapped westbound only (as a map does that
    saw it from one direction); a topology chain each way along the middle."""
    x = np.arange(0.0, length_m + 1e-9, 1.0)
    east = _feature(1, FeatureType.ROAD_BORDER, np.stack([x, np.full_like(x, -4.0)], axis=1))
    west = _feature(2, FeatureType.ROAD_BORDER, np.stack([x[::-1], np.full_like(x, 4.0)], axis=1))
    centre = _feature(3, FeatureType.DASHED, np.stack([x[::-1], np.zeros_like(x)], axis=1))
    xs = np.arange(length_m - 1.0, 0.0, -2.0)
    ids = 5000 + np.arange(len(xs))
    back = tuple(
        TopologyNode(int(ids[i]), np.array([xs[i], 0.0]), np.pi, 8.0, (int(ids[i + 1]),) if i + 1 < len(xs) else ())
        for i in range(len(xs))
    )
    return HDMap(features=(east, west, centre), topology=_topology(length_m, 8.0) + back)


TURN_RADIUS_M = 30.0  # ``turn_without_lines``: the turn's radius, centre (300, -30)


def turn_without_lines() -> HDMap:
    """A one-lane road east along y = 0 up to x = 300 and a one-lane road south along x = 330 from
    y = -30 (solid lines 1.75 m either side of each), joined by a right turn of radius 30 m
    about (300, -30) that has no line and no topology: a junction where the markings stop."""
    x = np.arange(0.0, 300.0 + 1e-9, 1.0)
    y = np.arange(-30.0, -300.0 - 1e-9, -1.0)
    feats = (
        _feature(1, FeatureType.SOLID, np.stack([x, np.full_like(x, 1.75)], axis=1)),
        _feature(2, FeatureType.SOLID, np.stack([x, np.full_like(x, -1.75)], axis=1)),
        _feature(3, FeatureType.SOLID, np.stack([np.full_like(y, 331.75), y], axis=1)),  # left, heading south
        _feature(4, FeatureType.SOLID, np.stack([np.full_like(y, 328.25), y], axis=1)),
    )
    east = _topology(300.0, 6.0)
    ys = np.arange(-31.0, -300.0, -2.0)
    south = tuple(
        TopologyNode(5000 + i, np.array([330.0, ys[i]]), -np.pi / 2, 6.0, (5000 + i + 1,) if i + 1 < len(ys) else ())
        for i in range(len(ys))
    )
    return HDMap(features=feats, topology=east + south)


def turn_drives(n: int = 4, *, seed: int = 0, bias_m: float = 0.8, noise_m: float = 0.1) -> list[np.ndarray]:
    """``n`` trajectories (N, 2) through ``turn_without_lines``'s turn along the lanes' middle,
    each with a constant sideways bias (uniform within ``bias_m``) and white noise."""
    rng = np.random.default_rng(seed)
    a = np.linspace(np.pi / 2, 0.0, 48)  # angle about the turn's centre: from (300, 0) to (330, -30)
    path = np.concatenate(
        [
            np.stack([np.arange(100.0, 300.0, 1.0), np.zeros(200)], axis=1),
            np.stack([300.0 + TURN_RADIUS_M * np.cos(a), -30.0 + TURN_RADIUS_M * np.sin(a)], axis=1),
            np.stack([np.full(150, 330.0), np.arange(-31.0, -181.0, -1.0)], axis=1),
        ]
    )
    d = np.gradient(path, axis=0)
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.hypot(*d.T)[:, None]
    return [path + rng.uniform(-bias_m, bias_m) * normal + rng.normal(0.0, noise_m, path.shape) for _ in range(n)]


def lines_stop(length_m: float = 800.0) -> HDMap:
    """``three_lanes`` whose three right lines (-1.75 dashed, -5.25 solid, -6.5 border) stop at
    x = 400 (a junction where the markings of two lanes stop) while the left lane goes on."""
    base = three_lanes(length_m)
    feats = tuple(
        f if f.points[0, 1] > 0.0 else _feature(f.id, f.type, f.points[f.points[:, 0] <= 400.0]) for f in base.features
    )
    return HDMap(features=feats, topology=base.topology)


def taper_open(length_m: float = 1300.0, *, size_m: float = 2.5, lane_m: float = 3.5, dip: bool = False) -> HDMap:
    """``three_lanes`` whose right edge line (-5.25; -1.75 - ``lane_m``) moves ``size_m`` (2.5) out
    over a 100 m taper (400-500, smoothstep, as ``simulation.changes`` does) onto the road border
    and back over 800-900, a dashed line drawn where the edge was between the tapers (500-800): the
    shoulder opened as a lane ``size_m`` wide. In the tapers the strip between the divider (-1.75)
    and the edge is 3.5-6.0 m wide. The nodes sit in the middle of the road; with ``dip`` the road
    width of the nodes at 460-500 falls to 9 m and their middle moves 3 m left (a map's width
    estimate in a taper): their cut lines miss the moved edge."""
    x = np.arange(0.0, length_m + 1e-9, 1.0)

    def ramp(u: np.ndarray) -> np.ndarray:
        u = np.clip(u, 0.0, 1.0)
        return u * u * (3.0 - 2.0 * u)

    y_edge = -1.75 - lane_m
    edge = y_edge - size_m * ramp((x - 400.0) / 100.0) * ramp((900.0 - x) / 100.0)
    feats = [_feature(i + 1, t, np.stack([x, np.full_like(x, y)], axis=1)) for i, (y, t) in enumerate(THREE[:4])]
    feats.append(_feature(5, FeatureType.SOLID, np.stack([x, edge], axis=1)))
    feats.append(_feature(6, FeatureType.ROAD_BORDER, np.stack([x, np.full_like(x, y_edge - size_m)], axis=1)))
    xd = x[(x >= 500.0) & (x <= 800.0)]
    feats.append(_feature(7, FeatureType.DASHED, np.stack([xd, np.full_like(xd, y_edge)], axis=1)))
    nodes = _topology(length_m, 6.5 - y_edge + size_m, y0=(6.5 + y_edge - size_m) / 2.0)
    if dip:
        inside = [460.0 <= n.position[0] <= 500.0 for n in nodes]
        nodes = tuple(
            TopologyNode(n.id, n.position + [0.0, 3.0], n.heading, 9.0, n.successors) if dips else n
            for n, dips in zip(nodes, inside, strict=True)
        )
    return HDMap(features=tuple(feats), topology=nodes)
