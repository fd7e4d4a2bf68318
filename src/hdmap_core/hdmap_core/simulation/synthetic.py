"""Built-in synthetic highways in the ground-truth format of data/maps.

Three layouts of a divided, curved motorway (two carriageways, 3 lanes each way, 3.5 m lanes):

* ``motorway``: plain, lanes cut into ~500 m sections (successor links between them).
* ``motorway_ramps``: per carriageway one interchange per ~3 km: an exit (deceleration lane that
  splits off lane 3: a lane with two successors) and, 1.4 km later, an entry (acceleration lane
  merging into lane 3: a lane with two predecessors).
* ``lane_drop``: in the ``fwd`` carriageway lane 3 ends with a 200 m taper (merge into lane 2); at
  the same place the ``bwd`` carriageway gains a lane (split from lane 2).

Cross-section of one carriageway, lateral offsets to the right of its driving direction, measured
from the reference line in the median (so both carriageways mirror each other)::

    1.25 median barrier (road border) | 2.0 left edge line (solid) | lanes of 3.5 m with dashed
    lines at 5.5 and 9.0 | 12.5 right edge line (solid) | 2.5 m hard shoulder | 15.0 road border

Everything is in a local metric frame (x east, y north). Points are at most 1 m apart and every
polyline is ordered in its carriageway's driving direction. The reference line is seeded: straights
and arcs of 1200-3000 m radius, joined by smooth (clothoid-like) curvature transitions.
``GroundTruth.extra["route_directions"]`` maps each route id to ``"fwd"`` or ``"bwd"``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from hdmap_core.errors import ConfigError
from hdmap_core.geometry import left_normal
from hdmap_core.groundtruth import GroundTruth, GTFeature, GTLane, GTRoute
from hdmap_core.model import FeatureType

__all__ = ["SYNTHETIC_NAMES", "LANE_WIDTH_M", "synthetic_highway"]

SYNTHETIC_NAMES = ("motorway", "motorway_ramps", "lane_drop")
LANE_WIDTH_M = 3.5

# Cross-section [m, to the right of the driving direction, from the median reference line].
_BARRIER_R = 1.25
_LEFT_EDGE_R = 2.0
_N_LANES = 3
_SHOULDER_M = 2.5
_RAMP_INNER_SHOULDER_M = 1.0
_SECTION_M = 500.0
_POINT_STEP_M = 0.8  # sampling step along the reference; offset curves stay below 1 m spacing

# Ramps (Sec. of the module docstring): deceleration lane taper, parallel part, diverging part.
_RAMP_TAPER_M = 80.0
_RAMP_PARALLEL_M = 250.0
_RAMP_DIVERGE_M = 350.0
_RAMP_DIVERGE_RADIUS_M = 600.0
_RAMP_MAX_SLOPE = 0.105  # tan(6 deg): final divergence angle of a ramp from the main line
_RAMP_LEN_M = _RAMP_TAPER_M + _RAMP_PARALLEL_M + _RAMP_DIVERGE_M
_INTERCHANGE_GAP_M = 40.0  # between the exit ramp's end and the entry ramp's start
_DROP_TAPER_M = 200.0
_MIN_LENGTH_M = {"motorway": 200.0, "motorway_ramps": 2000.0, "lane_drop": 800.0}

RFunc = Callable[[np.ndarray], np.ndarray]


def _lane_r(i: int) -> float:
    """Centre offset of main lane ``i`` (1 = leftmost) [m]."""
    return _LEFT_EDGE_R + LANE_WIDTH_M * (i - 0.5)


def _line_r(i: int) -> float:
    """Offset of the line right of lane ``i`` [m] (i = 0: left edge line)."""
    return _LEFT_EDGE_R + LANE_WIDTH_M * i


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _ramp_offset(u: np.ndarray) -> np.ndarray:
    """Lateral offset of a ramp lane from lane 3 [m] at ``u`` metres after the split.

    Taper 0 -> lane width, parallel, then diverge along a 600 m radius up to a 6 deg slope.
    Zero for u < 0, constant beyond the ramp end.
    """
    u = np.asarray(u, dtype=float)
    d = LANE_WIDTH_M * _smoothstep(u / _RAMP_TAPER_M)
    v = np.clip(u - _RAMP_TAPER_M - _RAMP_PARALLEL_M, 0.0, _RAMP_DIVERGE_M)
    v1 = _RAMP_MAX_SLOPE * _RAMP_DIVERGE_RADIUS_M
    curved = np.minimum(v, v1)
    return d + curved**2 / (2.0 * _RAMP_DIVERGE_RADIUS_M) + _RAMP_MAX_SLOPE * np.maximum(v - v1, 0.0)


def _gore_nose_u() -> float:
    """Distance after the split where the ramp's inner border meets the main road border [m]."""
    u = np.arange(0.0, _RAMP_LEN_M, 0.05)
    inner_border = _line_r(_N_LANES) - LANE_WIDTH_M + _ramp_offset(u) - _RAMP_INNER_SHOULDER_M
    return float(u[np.argmax(inner_border >= _line_r(_N_LANES) + _SHOULDER_M)])


@dataclass(frozen=True)
class _Reference:
    """The median reference line, densely sampled: s (K,), xy (K, 2), theta (K,)."""

    s: np.ndarray
    xy: np.ndarray
    theta: np.ndarray

    @property
    def length_m(self) -> float:
        return float(self.s[-1])

    def place(self, direction: str, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """(N, 2) points at carriageway distance ``t`` and right offset ``r`` [m]."""
        s = t if direction == "fwd" else self.length_m - t
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        th = np.interp(s, self.s, self.theta)
        left = left_normal(th)
        sign = -1.0 if direction == "fwd" else 1.0  # right of fwd = -left; right of bwd = +left
        return np.stack([x, y], axis=1) + (sign * r)[:, None] * left


def _reference_line(length_m: float, rng: np.random.Generator) -> _Reference:
    """Straights and arcs (radius 1200-3000 m) with smoothed curvature transitions."""
    ds = 0.1
    s = np.arange(0.0, length_m + ds, ds)
    s[-1] = min(s[-1], length_m)
    kappa = np.zeros_like(s)
    pos = 0.0
    while pos < length_m:
        seg = rng.uniform(400.0, 900.0)
        if rng.random() < 0.7:
            kappa[(s >= pos) & (s < pos + seg)] = rng.choice([-1.0, 1.0]) / rng.uniform(1200.0, 3000.0)
        pos += seg
    win = int(150.0 / ds)
    kappa = np.convolve(np.pad(kappa, win // 2, mode="edge"), np.ones(win) / win, mode="same")[win // 2 : -(win // 2)]
    theta = rng.uniform(-0.5, 0.5) + np.concatenate([[0.0], np.cumsum(0.5 * (kappa[1:] + kappa[:-1]) * ds)])
    dx = np.cos(theta)
    dy = np.sin(theta)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (dx[1:] + dx[:-1]) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (dy[1:] + dy[:-1]) * ds)])
    return _Reference(s, np.stack([x, y], axis=1), theta)


def _const(r: float) -> RFunc:
    return lambda t: np.full(np.shape(t), float(r))


def _ramp_out(base: float, t_split: float) -> RFunc:
    """``base`` plus the ramp lane's offset ``t - t_split`` metres after a split."""
    return lambda t: base + _ramp_offset(t - t_split)


def _ramp_in(base: float, t_merge: float) -> RFunc:
    """``base`` plus the ramp lane's offset ``t_merge - t`` metres before a merge."""
    return lambda t: base + _ramp_offset(t_merge - t)


def _samples(t0: float, t1: float) -> np.ndarray:
    n = max(2, int(np.ceil((t1 - t0) / _POINT_STEP_M)) + 1)
    return np.linspace(t0, t1, n)


@dataclass
class _Carriageway:
    """Collects features and lane pieces of one carriageway in its own (t, r) coordinates."""

    direction: str
    ref: _Reference
    features: list[tuple[FeatureType, float, float, RFunc]]
    lanes: dict[str, tuple[float, float, RFunc]]  # lane key -> extent and offset function

    def feature(self, ftype: FeatureType, t0: float, t1: float, rfunc: RFunc) -> None:
        if t1 - t0 > 1.0:
            self.features.append((ftype, t0, t1, rfunc))

    def polyline(self, t0: float, t1: float, rfunc: RFunc) -> np.ndarray:
        t = _samples(t0, t1)
        return self.ref.place(self.direction, t, rfunc(t))


def _plain_features(cw: _Carriageway, length_m: float, *, right_edge: bool = True) -> None:
    """Barrier, left edge line and the two dashed lines over the whole length."""
    cw.feature(FeatureType.ROAD_BORDER, 0.0, length_m, _const(_BARRIER_R))
    cw.feature(FeatureType.SOLID, 0.0, length_m, _const(_LEFT_EDGE_R))
    for i in range(1, _N_LANES):
        cw.feature(FeatureType.DASHED, 0.0, length_m, _const(_line_r(i)))
    if right_edge:
        cw.feature(FeatureType.SOLID, 0.0, length_m, _const(_line_r(_N_LANES)))
        cw.feature(FeatureType.ROAD_BORDER, 0.0, length_m, _const(_line_r(_N_LANES) + _SHOULDER_M))


def _interchanges(length_m: float) -> list[tuple[float, float]]:
    """(split t, merge t) of each interchange of one carriageway."""
    n = max(1, int(length_m // 3000.0))
    half = _RAMP_LEN_M + _INTERCHANGE_GAP_M / 2.0
    return [((k + 0.5) * length_m / n - half, (k + 0.5) * length_m / n + half) for k in range(n)]


def _ramp_features(cw: _Carriageway, length_m: float, ics: list[tuple[float, float]]) -> None:
    """Right-side lines and borders of a carriageway with exits and entries.

    The outer edge line and border follow the outside of each ramp (the deceleration lane bends
    them out; after an entry they continue as the main line's); a dashed line separates lane 3
    from the parallel part of each ramp lane; solid lines and borders start/end at the gore.
    """
    edge, border = _line_r(_N_LANES), _line_r(_N_LANES) + _SHOULDER_M
    u_nose = _gore_nose_u()
    u_gore = _RAMP_TAPER_M + _RAMP_PARALLEL_M
    starts = [0.0] + [tm - _RAMP_LEN_M for _, tm in ics]
    ends = [te + _RAMP_LEN_M for te, _ in ics] + [length_m]
    prev_merge = [None] + [tm for _, tm in ics]
    next_split = [te for te, _ in ics] + [None]
    for t0, t1, tm, te in zip(starts, ends, prev_merge, next_split):

        def outside(t: np.ndarray, base: float, tm=tm, te=te) -> np.ndarray:
            r = np.full(np.shape(t), base)
            if tm is not None:
                r += np.where(t <= tm, _ramp_offset(tm - t), 0.0)
            if te is not None:
                r += np.where(t >= te, _ramp_offset(t - te), 0.0)
            return r

        cw.feature(FeatureType.SOLID, t0, t1, partial(outside, base=edge))
        cw.feature(FeatureType.ROAD_BORDER, t0, t1, partial(outside, base=border))
    inner_line = edge - LANE_WIDTH_M
    inner_border = inner_line - _RAMP_INNER_SHOULDER_M
    for te, tm in ics:
        cw.feature(FeatureType.DASHED, te, te + u_gore, _const(edge))
        cw.feature(FeatureType.SOLID, te + u_gore, tm - u_gore, _const(edge))
        cw.feature(FeatureType.DASHED, tm - u_gore, tm, _const(edge))
        cw.feature(FeatureType.ROAD_BORDER, te + u_nose, tm - u_nose, _const(border))
        cw.feature(FeatureType.SOLID, te + u_gore, te + _RAMP_LEN_M, _ramp_out(inner_line, te))
        cw.feature(FeatureType.SOLID, tm - _RAMP_LEN_M, tm - u_gore, _ramp_in(inner_line, tm))
        cw.feature(FeatureType.ROAD_BORDER, te + u_nose, te + _RAMP_LEN_M, _ramp_out(inner_border, te))
        cw.feature(FeatureType.ROAD_BORDER, tm - _RAMP_LEN_M, tm - u_nose, _ramp_in(inner_border, tm))


@dataclass
class _Topology:
    """Lane pieces of one carriageway between common breakpoints, with their links."""

    direction: str
    breaks: np.ndarray  # (B,) section boundaries along t
    extents: dict[str, tuple[float, float]]  # lane key -> (t0, t1)
    rfuncs: dict[str, RFunc]
    links: list[tuple[str, str]]  # (key, to_key): splits into / merges from a lane

    def piece_ids(self, key: str) -> list[tuple[int, float, float]]:
        t0, t1 = self.extents[key]
        b = self.breaks
        out = []
        for j in range(len(b) - 1):
            if b[j] >= t0 - 1e-6 and b[j + 1] <= t1 + 1e-6:
                out.append((j, b[j], b[j + 1]))
        return out


def _lane_id(direction: str, j: int, key: str) -> str:
    return f"{direction}:{j}:{key}"


def _build_lanes(
    cw: _Carriageway,
    topo: _Topology,
    neighbours: Callable[[str, float, float], tuple[str | None, str | None]],
) -> dict[str, GTLane]:
    """Cut every lane at the breakpoints; link consecutive pieces, extra links and neighbours."""
    pieces: dict[str, list[tuple[int, float, float]]] = {k: topo.piece_ids(k) for k in topo.extents}
    at: dict[tuple[int, str], str] = {}
    for key, plist in pieces.items():
        for j, _, _ in plist:
            at[(j, key)] = _lane_id(cw.direction, j, key)
    succ: dict[str, list[str]] = {lid: [] for lid in at.values()}
    pred: dict[str, list[str]] = {lid: [] for lid in at.values()}
    for key, plist in pieces.items():
        for (j, _, _), (j2, _, _) in zip(plist[:-1], plist[1:]):
            succ[at[(j, key)]].append(at[(j2, key)])
            pred[at[(j2, key)]].append(at[(j, key)])
    for key, to_key in topo.links:
        # A split (to the first piece of `to_key`) or a merge (from the last piece of `key`):
        # the piece of `key` ending at a boundary links to the piece of `to_key` starting there.
        for j, _, t1 in pieces[key]:
            for j2, t0b, _ in pieces[to_key]:
                ends_or_starts = (j == pieces[key][-1][0]) or (j2 == pieces[to_key][0][0])
                if abs(t1 - t0b) < 1e-6 and ends_or_starts:
                    src, dst = at[(j, key)], at[(j2, to_key)]
                    succ[src].append(dst)
                    pred[dst].append(src)
    lanes = {}
    for key, plist in pieces.items():
        for j, t0, t1 in plist:
            lid = at[(j, key)]
            left_key, right_key = neighbours(key, t0, t1)
            lanes[lid] = GTLane(
                id=lid,
                centerline=cw.polyline(t0, t1, topo.rfuncs[key]),
                successors=tuple(succ[lid]),
                predecessors=tuple(pred[lid]),
                left=at.get((j, left_key)) if left_key else None,
                right=at.get((j, right_key)) if right_key else None,
            )
    return lanes


def _breaks(length_m: float, events: list[float]) -> np.ndarray:
    """Section boundaries: every ~500 m plus the events; grid points too near an event dropped."""
    ev = np.asarray(sorted(set([0.0, length_m] + [e for e in events if 0.0 < e < length_m])))
    n = max(1, int(round(length_m / _SECTION_M)))
    grid = np.linspace(0.0, length_m, n + 1)[1:-1]
    kept = [g for g in grid if np.min(np.abs(ev - g)) > 60.0]
    return np.unique(np.concatenate([ev, kept]))


def _main_neighbours(key: str) -> tuple[str | None, str | None]:
    if not key.isdigit():
        return None, None
    i = int(key)
    return (str(i - 1) if i > 1 else None), (str(i + 1) if i < _N_LANES else None)


def _route(topo: _Topology, keys_windows: list[tuple[str, float, float]]) -> tuple[str, ...]:
    """Lane ids of the pieces of each (key, t_from, t_to) window, in order."""
    out: list[str] = []
    for key, ta, tb in keys_windows:
        for j, t0, t1 in topo.piece_ids(key):
            if t1 > ta + 1e-6 and t0 < tb - 1e-6:
                out.append(_lane_id(topo.direction, j, key))
    return tuple(out)


def _carriageway(
    name: str, direction: str, ref: _Reference
) -> tuple[list[GTFeature], dict[str, GTLane], list[GTRoute]]:
    """Features, lanes and routes of one carriageway of layout ``name``."""
    length = ref.length_m
    cw = _Carriageway(direction, ref, [], {})
    main = {str(i): (0.0, length) for i in range(1, _N_LANES + 1)}
    rfuncs: dict[str, RFunc] = {str(i): _const(_lane_r(i)) for i in range(1, _N_LANES + 1)}
    links: list[tuple[str, str]] = []
    routes: list[tuple[str, list[tuple[str, float, float]]]] = []
    last = str(_N_LANES)
    if name == "motorway":
        _plain_features(cw, length)
        events: list[float] = []
        parallel: list[tuple[str, float, float]] = []
    elif name == "motorway_ramps":
        _plain_features(cw, length, right_edge=False)
        ics = _interchanges(length)
        _ramp_features(cw, length, ics)
        events, parallel = [], []
        for k, (te, tm) in enumerate(ics):
            x, n = f"x{k}", f"n{k}"
            main[x] = (te, te + _RAMP_LEN_M)
            main[n] = (tm - _RAMP_LEN_M, tm)
            rfuncs[x] = _ramp_out(_lane_r(_N_LANES), te)
            rfuncs[n] = _ramp_in(_lane_r(_N_LANES), tm)
            links += [(last, x), (n, last)]
            p0, p1 = _RAMP_TAPER_M, _RAMP_TAPER_M + _RAMP_PARALLEL_M
            events += [te, te + p0, te + p1, te + _RAMP_LEN_M, tm - _RAMP_LEN_M, tm - p1, tm - p0, tm]
            parallel += [(x, te + p0, te + p1), (n, tm - p1, tm - p0)]
            routes.append((f"{direction}_exit{k}", [(last, max(0.0, te - 1000.0), te), (x, te, te + _RAMP_LEN_M)]))
            routes.append((f"{direction}_entry{k}", [(n, tm - _RAMP_LEN_M, tm), (last, tm, min(length, tm + 1000.0))]))
    elif name == "lane_drop":
        _plain_features(cw, length, right_edge=False)
        cw.features.pop()  # the dashed line between lanes 2 and 3 is redrawn below
        t_mid = length / 2.0
        if direction == "fwd":  # lane 3 ends: taper into lane 2
            td = t_mid - _DROP_TAPER_M / 2.0

            def shape(t: np.ndarray, td: float = td) -> np.ndarray:
                return _smoothstep((t - td) / _DROP_TAPER_M)

            main[last] = (0.0, td + _DROP_TAPER_M)
            links.append((last, "2"))
            events = [td, td + _DROP_TAPER_M]
            cw.feature(FeatureType.DASHED, 0.0, td, _const(_line_r(2)))
        else:  # lane 3 begins: split from lane 2
            td = t_mid - _DROP_TAPER_M / 2.0

            def shape(t: np.ndarray, td: float = td) -> np.ndarray:
                return 1.0 - _smoothstep((t - td) / _DROP_TAPER_M)

            main[last] = (td, length)
            links.append(("2", last))
            events = [td, td + _DROP_TAPER_M]
            cw.feature(FeatureType.DASHED, td + _DROP_TAPER_M, length, _const(_line_r(2)))
        # shape and edge_fn are bound once in this branch: the closures see these values
        if direction == "fwd":
            rfuncs[last] = lambda t: _lane_r(3) - LANE_WIDTH_M * shape(t)
        else:
            rfuncs[last] = lambda t: _lane_r(2) + LANE_WIDTH_M * (1.0 - shape(t))
        edge_fn: RFunc = (
            (lambda t: _line_r(3) - LANE_WIDTH_M * shape(t))
            if direction == "fwd"
            else (lambda t: _line_r(2) + LANE_WIDTH_M * (1.0 - shape(t)))
        )
        cw.feature(FeatureType.SOLID, 0.0, length, edge_fn)
        cw.feature(FeatureType.ROAD_BORDER, 0.0, length, lambda t: edge_fn(t) + _SHOULDER_M)
        parallel = [(last, 0.0, td)] if direction == "fwd" else [(last, td + _DROP_TAPER_M, length)]
    else:
        raise ConfigError(f"unknown synthetic highway {name!r}; choose one of {', '.join(SYNTHETIC_NAMES)}")
    topo = _Topology(direction, _breaks(length, events), main, rfuncs, links)

    # Lanes in `parallel` are side by side with their partner only inside their windows (ramp
    # lanes beside lane 3 on the parallel part; lane 3 of lane_drop beside lane 2 outside the taper).
    partner = "2" if name == "lane_drop" else last
    special = {pk for pk, _, _ in parallel}

    def neighbours(key: str, t0: float, t1: float) -> tuple[str | None, str | None]:
        def beside(k: str) -> bool:
            return any(pk == k and t0 >= a - 1e-6 and t1 <= b + 1e-6 for pk, a, b in parallel)

        if key in special:
            return (partner, None) if beside(key) else (None, None)
        i = int(key)
        left = str(i - 1) if i > 1 else None
        right = str(i + 1) if i < _N_LANES and str(i + 1) not in special else None
        if key == partner:
            right = next((k for k in sorted(special) if beside(k)), right)
        return left, right

    lanes = _build_lanes(cw, topo, neighbours)
    feats = [(ftype, cw.polyline(t0, t1, rf)) for ftype, t0, t1, rf in cw.features]
    gt_routes = [GTRoute(f"{direction}_lane{k}", _route(topo, [(k, 0.0, length)])) for k in sorted(main) if k.isdigit()]
    if name == "lane_drop":  # lane 3's through route continues/starts in lane 2
        td = length / 2.0 - _DROP_TAPER_M / 2.0
        lane3 = (
            [(last, 0.0, td + _DROP_TAPER_M), ("2", td + _DROP_TAPER_M, length)]
            if direction == "fwd"
            else [("2", 0.0, td), (last, td, length)]
        )
        gt_routes[-1] = GTRoute(f"{direction}_lane{last}", _route(topo, lane3))
    gt_routes += [GTRoute(rid, _route(topo, wins)) for rid, wins in routes]
    return [GTFeature(0, t, p) for t, p in feats], lanes, gt_routes


def synthetic_highway(name: str, *, length_m: float = 3000.0, seed: int = 0) -> GroundTruth:
    """A synthetic divided motorway (see the module docstring for the layouts).

    Args:
        name: ``"motorway"``, ``"motorway_ramps"`` or ``"lane_drop"``.
        length_m: length of the reference line [m] (each carriageway is about this long);
            at least 200 (motorway), 2000 (motorway_ramps) or 800 (lane_drop).
        seed: seed of the road shape (curvature profile and initial heading).

    Returns:
        a ``GroundTruth`` with features (solid/dashed lines, road borders incl. both median
        barriers), lanes (centerlines <= 1 m spacing, links, neighbours) and routes (a through
        route per lane and direction, one route taking each exit, one coming from each entry).

    Raises:
        ConfigError: unknown name, or a length too short for the layout.
    """
    if name not in SYNTHETIC_NAMES:
        raise ConfigError(f"unknown synthetic highway {name!r}; choose one of {', '.join(SYNTHETIC_NAMES)}")
    if not np.isfinite(length_m) or length_m < _MIN_LENGTH_M[name]:
        raise ConfigError(f"synthetic highway {name!r}: length_m={length_m} is below {_MIN_LENGTH_M[name]:.0f} m")
    rng = np.random.default_rng(seed)
    ref = _reference_line(float(length_m), rng)
    features: list[GTFeature] = []
    lanes: dict[str, GTLane] = {}
    routes: list[GTRoute] = []
    for direction in ("fwd", "bwd"):
        f, lane_map, r = _carriageway(name, direction, ref)
        features += [GTFeature(len(features) + i + 1, g.type, g.points) for i, g in enumerate(f)]
        lanes.update(lane_map)
        routes += r
    extra = {
        "source": (
            f"hdmap_core.simulation.synthetic.synthetic_highway({name!r}, length_m={float(length_m)}, seed={seed})"
        ),
        "frame": "local metric frame (x east, y north), synthetic",
        "geo_reference": None,
        "route_directions": {r.id: r.id.split("_", 1)[0] for r in routes},
    }
    return GroundTruth(name, tuple(features), lanes, tuple(routes), extra)
