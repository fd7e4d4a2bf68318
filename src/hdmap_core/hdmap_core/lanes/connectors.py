"""Connector lanes from the drives' trajectories where the line map has no lane between two lanes.

The lanes of :func:`hdmap_core.lanes.derive.derive_lanes` come from the map's lines only: where a
junction or a gap has no painted line, a lane ends and the lane the drives went on to starts
elsewhere, and no connector of RULE 8 (made from the map alone) joins them when the turn is not
where the topology predicts. The drives went through; their trajectories say where.

RULE T1 (transitions): each trajectory, resampled every STEP_M, is placed in the lanes
(as ``lanes_at``, heading within ~35 deg) after its own constant sideways offset is removed (the
median offset of its points from the centerlines of the lanes they lie in: a localisation bias).
A stay in a lane shorter than MIN_STAY_M is noise (a corner cut). Where the trajectory leaves a
lane A and the next lane it stays in, B, is not reachable from A in the lane graph within HOPS
steps (successors and lane changes), the drive made a connection the lanes lack.
RULE T2 (ends): the connection runs from the end of A to the start of B where the trajectory
passes them within END_NEAR_M; where it does not and A (B) is a connector (virtual sides, RULE 8
or T3), from the end of a lane before A (to the start of a lane after B) that it passes (a drive
that turns off a straight connector through a junction); none: no connector. The pair of lanes
(P, Q) is the connection's key; one already joined (Q reachable from P within HOPS) is skipped.
RULE T3 (connector): per key, the mean path of the drives that made it (each trajectory piece
between P's end and Q's start resampled to the same number of points by arc length), moved so
that it starts at P's centerline end and ends at Q's centerline start (the differences fade out
linearly within _PIN_M of each end); the width blends from P's end width to Q's start width.
Its sides are virtual (``FeatureType.UNKNOWN``: no line in the map) and start at the end nodes
of P's sides and end at the start nodes of Q's (Lanelet2 routes along shared nodes).
RULE T4 (plausible): a connector is left out whose directions at its ends disagree with P's end
or Q's start by more than MAX_TURN_DEG (ONE_DRIVE_TURN_DEG when one drive made it: a lane that
starts right at a corner meets the drives at a right angle, one drive's kink is more often
noise), that is longer than MAX_LENGTH_M, or whose sides are degenerate
(:func:`hdmap_core.lanes.derive.proper_sides`, RULE 14).

Ids are stable: hashes of the two joined lanes' ids.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections import defaultdict
from collections.abc import Sequence

import networkx as nx
import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import left_normal, resample_evenly
from hdmap_core.lanes.derive import proper_sides
from hdmap_core.lanes.lane_graph import lane_graph
from hdmap_core.lanes.model import Boundary, Lane, LaneMap
from hdmap_core.model import FeatureType

__all__ = [
    "trajectory_connectors",
    "connections",
    "placed_trajectories",
    "Placed",
    "relinked",
    "stable_id",
    "virtual_lane",
    "STEP_M",
    "MIN_STAY_M",
    "END_NEAR_M",
    "HOPS",
    "MAX_TURN_DEG",
    "ONE_DRIVE_TURN_DEG",
    "MAX_LENGTH_M",
]

STEP_M = 1.0  # RULE T1: trajectory sampling
MIN_STAY_M = 4.0  # RULE T1: a shorter stay in a lane is a corner cut
HOPS = 4  # RULE T1/T2: lanes already joined within this many steps need no connector
END_NEAR_M = 2.5  # RULE T2: the trajectory passes the lane end this close
MAX_TURN_DEG = 90.0  # RULE T4: connector direction vs. the joined lanes' at its ends
ONE_DRIVE_TURN_DEG = 45.0  # RULE T4: the same for a connection one drive made
MAX_LENGTH_M = 300.0  # RULE T4: longest connector
_PIN_M = 6.0  # RULE T3: the ends' differences fade out within this way along the connector
_BIAS_EVERY = 5  # RULE T1: the sideways offset from every 5th trajectory point
_BIAS_MIN_M = 0.1  # RULE T1: a smaller sideways offset is left as it is
_ANGLE_RAD = 0.6  # RULE T1: heading agreement of a point and its lane
_SAMPLE_M = 0.5  # RULE T1: centerline samples of the lane locator
_NEIGHBOURS = 12  # RULE T1: centerline samples looked at per point
_HEADING_M = 5.0  # RULE T1: lane locator: metres per radian of heading difference
_CHUNK = 8192  # points the lane locator takes at a time (speed only)


def trajectory_connectors(
    lane_map: LaneMap, trajectories: Sequence[np.ndarray], *, min_drives: int = 1, placed: Placed | None = None
) -> LaneMap:
    """``lane_map`` with connector lanes (module docstring) for the connections at least
    ``min_drives`` of the (N, 2) ``trajectories`` [m, map frame, time ordered] made and the lanes
    lack; the lanes they join gain them as successors / predecessors. No trajectory, no change:
    then ``lane_map`` itself. ``placed``: :func:`placed_trajectories` of these, if already made."""
    if not lane_map.lanes or not len(trajectories):
        return lane_map
    found = connections(lane_map, trajectories, placed=placed)
    lanes = {ln.id: ln for ln in lane_map.lanes}
    bounds = {b.id: b for b in lane_map.boundaries}
    new_lanes: list[Lane] = []
    new_bounds: dict[int, Boundary] = {}
    for (p, q), pieces in sorted(found.items()):
        if len(pieces) < min_drives:
            continue
        made = _connector(lanes[p], lanes[q], bounds, pieces)
        if made is None:
            continue
        lane, left, right = made
        new_lanes.append(lane)
        new_bounds[left.id] = left
        new_bounds[right.id] = right
    if not new_lanes:
        return lane_map
    all_bounds = {**bounds, **new_bounds}
    return LaneMap(
        relinked([*lane_map.lanes, *new_lanes], all_bounds),
        tuple(sorted(all_bounds.values(), key=lambda b: b.id)),
        lane_map.nodes,
    )


def connections(
    lane_map: LaneMap, trajectories: Sequence[np.ndarray], *, placed: Placed | None = None
) -> dict[tuple[int, int], list[np.ndarray]]:
    """RULES T1-T2: (lane P, lane Q) -> the trajectory pieces (M, 2) from P's end to Q's start of
    the drives that went from P to Q where the lane graph has no way (within HOPS steps).
    ``placed``: :func:`placed_trajectories` of ``trajectories`` on ``lane_map``, if already made."""
    lanes = {ln.id: ln for ln in lane_map.lanes}
    g = lane_graph(lane_map)
    near: dict[int, set[int]] = {}

    def joined(a: int, b: int) -> bool:
        if a not in near:
            near[a] = set(nx.single_source_shortest_path_length(g, a, cutoff=HOPS))
        return b in near[a]

    out: dict[tuple[int, int], list[np.ndarray]] = defaultdict(list)
    if placed is None:
        placed = placed_trajectories(lane_map, lanes, trajectories)
    for pts, ids, _ in placed:
        stays = _stays(ids)
        for (a, a0, a1), (b, b0, b1) in zip(stays, stays[1:], strict=False):
            if a == b or joined(a, b):
                continue
            # RULE T2: the lane end the drive passed last (A's or a predecessor's), the lane
            # start it passed first (B's or a successor's)
            lo = max(0, a0 - int(20.0 / STEP_M))
            hi = min(len(pts), b1 + int(20.0 / STEP_M))
            p, ip = _passed(pts, lo, b0 + 1, [a], lanes, end=True)
            if p is None and _virtual(lanes[a]):
                p, ip = _passed(pts, lo, b0 + 1, list(lanes[a].predecessors), lanes, end=True)
            q, iq = _passed(pts, a1, hi, [b], lanes, end=False)
            if q is None and _virtual(lanes[b]):
                q, iq = _passed(pts, a1, hi, list(lanes[b].successors), lanes, end=False)
            if p is None or q is None or iq <= ip or p == q or joined(p, q):
                continue
            out[(p, q)].append(pts[ip : iq + 1])
    return dict(out)


#: :func:`placed_trajectories`' result: per trajectory (points, lane ids, offsets)
Placed = list[tuple[np.ndarray, np.ndarray, np.ndarray]]


def placed_trajectories(lane_map: LaneMap, lanes: dict[int, Lane], trajectories: Sequence[np.ndarray]) -> Placed:
    """RULE T1: per trajectory, its points every STEP_M, moved by its own median sideways offset
    from the lanes they lie in, the lane of each point (0: none) and its signed offset from that
    lane's centerline [m, + = left]. (All trajectories at once: one spatial index.)"""
    pts, yaw = [], []
    for traj in trajectories:
        xy = np.asarray(traj, dtype=float).reshape(-1, 2)
        xy = xy[np.isfinite(xy).all(axis=1)]  # bad poses are no evidence
        p = resample_evenly(xy, STEP_M) if len(xy) >= 2 else np.zeros((0, 2))
        if len(p) < 3:
            p = np.zeros((0, 2))
        d = np.asarray(np.gradient(p, axis=0)) if len(p) else np.zeros((0, 2))
        pts.append(p)
        yaw.append(np.arctan2(d[:, 1], d[:, 0]))
    if not any(len(p) for p in pts):
        return []
    sizes = np.cumsum([0] + [len(p) for p in pts])
    allyaw = np.concatenate(yaw)
    where = _Locator(lane_map)
    # the offsets from every _BIAS_EVERY-th point (the median needs no more)
    every = np.concatenate([np.arange(len(p)) % _BIAS_EVERY == 0 for p in pts])
    ids, off = np.zeros(sizes[-1], dtype=np.int64), np.zeros(sizes[-1])
    ids[every], off[every] = where(np.concatenate(pts)[every], allyaw[every])
    for i, p in enumerate(pts):
        own = off[sizes[i] : sizes[i + 1]][ids[sizes[i] : sizes[i + 1]] != 0]
        if len(own) and abs(bias := float(np.median(own))) > _BIAS_MIN_M:
            pts[i] = p - bias * left_normal(yaw[i])
    ids, off = where(np.concatenate(pts), allyaw)
    return [(p, ids[sizes[i] : sizes[i + 1]], off[sizes[i] : sizes[i + 1]]) for i, p in enumerate(pts) if len(p)]


class _Locator:
    """The lane a point lies in, heading within _ANGLE_RAD of the lane's (as ``lanes_at``, without
    its polygons: the nearest centerline sample, every _SAMPLE_M, of that direction whose cross
    line through the sample holds the point within half the lane's width there), and the point's
    signed offset from that centerline (+ = left). Samples and points are indexed by position and
    heading (_HEADING_M per radian), so that lanes of the other direction are far apart."""

    def __init__(self, lane_map: LaneMap) -> None:
        pts, dirs, half, owner = [], [], [], []
        for ln in lane_map.lanes:
            c = ln.centerline
            if len(c) < 2:
                continue
            s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(c, axis=0).T))])
            q = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / _SAMPLE_M)) + 1))
            xy = np.stack([np.interp(q, s, c[:, 0]), np.interp(q, s, c[:, 1])], axis=1)
            d = np.gradient(xy, axis=0)
            pts.append(xy)
            dirs.append(d / np.maximum(np.hypot(*d.T), 1e-9)[:, None])
            half.append(np.interp(q, s, ln.width) / 2.0)
            owner.append(np.full(len(q), ln.id, dtype=np.int64))
        self.xy = np.concatenate(pts) if pts else np.zeros((0, 2))
        self.dirs = np.concatenate(dirs) if pts else np.zeros((0, 2))
        self.half = np.concatenate(half) if pts else np.zeros(0)
        self.owner = np.concatenate(owner) if pts else np.zeros(0, dtype=np.int64)
        self.tree = cKDTree(np.concatenate([self.xy, _HEADING_M * self.dirs], axis=1)) if pts else None
        self.reach = (
            float(np.hypot(self.half.max() + _SAMPLE_M, 2.0 * _HEADING_M * np.sin(_ANGLE_RAD / 2.0))) if pts else 0.0
        )

    def __call__(self, xy: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(xy) <= _CHUNK:
            return self._locate(xy, yaw)
        # in chunks: the (points, neighbours) arrays of one stay in the cache (paper_like's 380 k
        # points: 0.77 s instead of 1.86 s CPU at once; each point is located on its own, so
        # the result is the same)
        parts = [self._locate(xy[i : i + _CHUNK], yaw[i : i + _CHUNK]) for i in range(0, len(xy), _CHUNK)]
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])

    def _locate(self, xy: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = np.zeros(len(xy), dtype=np.int64)
        off = np.zeros(len(xy))
        if self.tree is None or not len(xy):
            return out, off
        heading = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
        _, idx = self.tree.query(
            np.concatenate([xy, _HEADING_M * heading], axis=1), k=_NEIGHBOURS, distance_upper_bound=self.reach
        )
        found = idx < len(self.owner)
        safe = np.where(found, idx, 0)
        rel = xy[:, None, :] - self.xy[safe]
        d = self.dirs[safe]
        along = np.abs((rel * d).sum(axis=2))
        aside = d[..., 0] * rel[..., 1] - d[..., 1] * rel[..., 0]  # + = left of the centerline
        ok = found & (along <= _SAMPLE_M / 2.0 + 1e-6) & (np.abs(aside) <= self.half[safe])
        ok &= (d * heading[:, None, :]).sum(axis=2) >= np.cos(_ANGLE_RAD)
        dist = np.where(ok, np.hypot(*rel.transpose(2, 0, 1)), np.inf)
        k = np.argmin(dist, axis=1)
        rows = np.arange(len(xy))
        hit = np.isfinite(dist[rows, k])
        out[hit] = self.owner[safe[rows, k]][hit]
        off[hit] = aside[rows, k][hit]
        return out, off


def _virtual(lane: Lane) -> bool:
    """A connector (both sides virtual): a drive may leave it or join it midway."""
    return lane.left_type == FeatureType.UNKNOWN and lane.right_type == FeatureType.UNKNOWN


def _stays(ids: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs of one lane (lane id, first index, last index), at least MIN_STAY_M long."""
    if not len(ids):
        return []
    cut = np.flatnonzero(np.diff(ids) != 0) + 1
    first = np.concatenate([[0], cut])
    last = np.concatenate([cut - 1, [len(ids) - 1]])
    need = max(1, int(round(MIN_STAY_M / STEP_M)))
    return [
        (int(ids[f]), int(f), int(e))
        for f, e in zip(first.tolist(), last.tolist(), strict=True)
        if ids[f] != 0 and e - f + 1 >= need
    ]


def _passed(
    pts: np.ndarray, lo: int, hi: int, cands: list[int], lanes: dict[int, Lane], *, end: bool
) -> tuple[int | None, int]:
    """Of the lanes ``cands``, the one whose end (start) point the trajectory ``pts[lo:hi]``
    passes closest, within END_NEAR_M, and the index of that trajectory point; (None, -1) if none."""
    if hi <= lo:
        return None, -1
    window = pts[lo:hi]
    best: tuple[float, int | None, int] = (END_NEAR_M, None, -1)
    for c in cands:
        if c not in lanes:
            continue
        at = lanes[c].centerline[-1 if end else 0]
        dist = np.hypot(*(window - at).T)
        k = int(np.argmin(dist))
        if dist[k] <= best[0]:
            best = (float(dist[k]), c, lo + k)
    return best[1], best[2]


def _connector(
    p: Lane, q: Lane, bounds: dict[int, Boundary], pieces: list[np.ndarray]
) -> tuple[Lane, Boundary, Boundary] | None:
    """RULES T3-T4: the connector lane from ``p``'s end to ``q``'s start along the mean of
    ``pieces``, with its two virtual sides; None when implausible."""
    lengths = [float(np.hypot(*np.diff(x, axis=0).T).sum()) for x in pieces if len(x) >= 2]
    if not lengths:
        return None
    length = float(np.median(lengths))
    if length > MAX_LENGTH_M:
        return None
    n = max(3, int(length // 2.0) + 2)  # a point every ~2 m
    mean = np.mean([_by_fraction(x, n) for x in pieces if len(x) >= 2], axis=0)
    t = np.linspace(0.0, 1.0, n)[:, None]
    # the ends' differences fade out within _PIN_M (at most half the way): the drives' mean path
    # stays where they drove, not where a lane's skewed end puts it
    reach = min(_PIN_M / max(length, 1e-9), 0.5)
    w0, w1 = np.clip(1.0 - t / reach, 0.0, 1.0), np.clip(1.0 - (1.0 - t) / reach, 0.0, 1.0)
    c0, c1 = p.centerline[-1], q.centerline[0]
    center = mean + w0 * (c0 - mean[0]) + w1 * (c1 - mean[-1])
    d = np.gradient(center, axis=0)
    d /= np.maximum(np.hypot(*d.T), 1e-9)[:, None]
    turn = min(d[0] @ _direction(p.centerline, first=False), d[-1] @ _direction(q.centerline, first=True))
    if turn < np.cos(np.radians(MAX_TURN_DEG if len(pieces) >= 2 else ONE_DRIVE_TURN_DEG)):
        return None
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1)
    half = ((1.0 - t) * p.width[-1] + t * q.width[0]) / 2.0
    pl, pr, ql, qr = (
        bounds[p.left_boundary],
        bounds[p.right_boundary],
        bounds[q.left_boundary],
        bounds[q.right_boundary],
    )
    sides = []
    for sign, a, b in ((1.0, pl, ql), (-1.0, pr, qr)):
        pts = center + sign * half * normal
        pts = pts + w0 * (a.points[-1] - pts[0]) + w1 * (b.points[0] - pts[-1])
        sides.append(
            Boundary(stable_id("trajectory_side", a.id, b.id), 0, FeatureType.UNKNOWN, pts, a.end_node, b.start_node)
        )
    left, right = sides
    return virtual_lane(stable_id("trajectory_connector", p.id, q.id), left, right)


def virtual_lane(lane_id: int, left: Boundary, right: Boundary) -> tuple[Lane, Boundary, Boundary] | None:
    """The lane between two virtual sides (a connector, a drive path): (lane, left, right), or
    None where RULE 14 finds the sides degenerate (``proper_sides``)."""
    if not proper_sides(
        left.points, right.points, (left.start_node, left.end_node), (right.start_node, right.end_node)
    ):
        return None
    lane = Lane(
        id=lane_id,
        centerline=(left.points + right.points) / 2.0,
        width=np.hypot(*(left.points - right.points).T),
        left_boundary=left.id,
        right_boundary=right.id,
        left_feature=0,
        right_feature=0,
        left_type=FeatureType.UNKNOWN,
        right_type=FeatureType.UNKNOWN,
    )
    return lane, left, right


def _by_fraction(line: np.ndarray, n: int) -> np.ndarray:
    """``n`` points at equal fractions of the polyline's arc length."""
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(line, axis=0).T))])
    q = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(q, s, line[:, 0]), np.interp(q, s, line[:, 1])], axis=1)


def _direction(line: np.ndarray, *, first: bool) -> np.ndarray:
    """Unit direction of a polyline over its first (last) few points."""
    k = min(len(line) - 1, 5)
    d = line[k] - line[0] if first else line[-1] - line[len(line) - 1 - k]
    return d / max(float(np.hypot(*d)), 1e-9)


def relinked(lanes: list[Lane], bounds: dict[int, Boundary]) -> tuple[Lane, ...]:
    """Successors and predecessors again by shared end nodes of both sides (Lanelet2's rule)."""
    by_start: dict[tuple[int, int], list[int]] = defaultdict(list)
    for ln in lanes:
        by_start[(bounds[ln.left_boundary].start_node, bounds[ln.right_boundary].start_node)].append(ln.id)
    succ: dict[int, list[int]] = defaultdict(list)
    pred: dict[int, list[int]] = defaultdict(list)
    for ln in lanes:
        for j in by_start.get((bounds[ln.left_boundary].end_node, bounds[ln.right_boundary].end_node), []):
            if j != ln.id:
                succ[ln.id].append(j)
                pred[j].append(ln.id)
    out = [
        dataclasses.replace(ln, successors=tuple(sorted(succ[ln.id])), predecessors=tuple(sorted(pred[ln.id])))
        for ln in lanes
    ]
    return tuple(sorted(out, key=lambda x: x.id))


def stable_id(name: str, *keys: int) -> int:
    """A stable 63-bit id (never 0) from a name and integer keys."""
    raw = name.encode() + b"".join(int(k).to_bytes(8, "little", signed=False) for k in keys)
    x = int.from_bytes(hashlib.blake2b(raw, digest_size=8).digest(), "little") & ((1 << 63) - 1)
    return x or 1
