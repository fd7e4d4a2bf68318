"""Drive-path lanes: lanes along the ways the drives went where the map has no lane of their direction.

The connectors (:mod:`hdmap_core.lanes.connectors`) join the end of one lane to the start of
another. Where a lane has only one mapped line, or a road's lines were not mapped at all, there is
no lane to start from and the drives' way stays without a lane. Here the drives draw it.

RULE D1 (off the lanes): each trajectory is placed in the lanes as in RULE T1 (its own sideways
offset removed); its runs of points in no lane of their direction, or further than OFF_M from
that lane's centerline towards a side with no neighbour lane (a lane as wide as its mapped lines
allow does not cover the way; beside a neighbour it is a drive on the line), are the candidates;
a run ends where the drive crosses from a lane into its neighbour (a lane change). A drive that
lies in no lane for more than MAX_OFF_SHARE of its way is no evidence (its localisation is off by
about a lane: its offset estimate of RULE T1 put it in the wrong lanes).
RULE D2 (support): a candidate point is supported by the drives that have off-lane points within
SUPPORT_M of it heading the same way (~35 deg), and contradicted by the other drives that are on
a lane within AGAINST_M of it whose side towards it is a mapped line (one drive's localisation
error puts it beyond the line of the lane the others drive in); it needs at least ``min_drives``
drives for it (LINED_DRIVES within AGAINST_M of a lane's mapped line on the side towards it:
beside a mapped line one drive's error looks like a lane the line map missed) and more for it
than against it. The path is the mean of the supporting points,
smoothed over SMOOTH_M; a supported stretch of at least MIN_RUN_M is a drive-path lane. The
off-lane points within SUPPORT_M of it are then used up (no second lane along the same way);
runs are taken longest first.
RULE D3 (joins): a drive-path lane whose first point lies within JOIN_M of the end of a lane of
its direction (~45 deg) starts at that lane's end nodes (the difference fades out within _PIN_M),
and ends at the start nodes of a lane that starts within JOIN_M of its last point; otherwise its
sides start (end) at nodes of their own. Its sides are virtual (``FeatureType.UNKNOWN``); its
width is the joined lane's, else the median width of the map's lanes.

Ids are stable: hashes of the path's end points (0.1 m).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.lanes.connectors import (
    STEP_M,
    Placed,
    placed_trajectories,
    relinked,
    stable_id,
    trajectory_connectors,
    virtual_lane,
)
from hdmap_core.lanes.model import Boundary, Lane, LaneMap
from hdmap_core.model import FeatureType

__all__ = [
    "trajectory_lanes",
    "drive_path_lanes",
    "OFF_M",
    "MAX_OFF_SHARE",
    "MIN_RUN_M",
    "SUPPORT_M",
    "AGAINST_M",
    "JOIN_M",
    "SMOOTH_M",
    "MIN_DRIVES",
]

OFF_M = 1.0  # RULE D1: a point further from its lane's centerline is not on that lane
MAX_OFF_SHARE = 0.3  # RULE D1: a drive in no lane for more of its way is no evidence
MIN_RUN_M = 30.0  # RULE D2: shortest drive-path lane
SUPPORT_M = 1.5  # RULE D2: other drives' points this close support a point
AGAINST_M = 4.0  # RULE D2: drives on a lane this close to a point speak against it
LINED_DRIVES = 2  # RULE D2: drives needed within AGAINST_M of a lane's mapped line
SMOOTH_M = 5.0  # RULE D2: moving average of the mean path
JOIN_M = 4.0  # RULE D3: a lane end (start) this close to the path's first (last) point is joined
MIN_DRIVES = 1  # RULE D2: drives that must have gone the way (2: Town06 94.3 % instead of 95.2 %)
_ANGLE_COS = float(np.cos(0.6))  # RULE D2: heading agreement of supporting points
_JOIN_COS = float(np.cos(np.radians(45.0)))  # RULE D3: direction agreement of a joined lane
_PIN_M = 6.0  # RULE D3: the joined end's difference fades out within this way


def trajectory_lanes(lane_map: LaneMap, trajectories: Sequence[np.ndarray]) -> LaneMap:
    """``lane_map`` with everything the drives add: the connectors
    (:func:`hdmap_core.lanes.connectors.trajectory_connectors`), then the drive-path lanes. The
    trajectories are placed on the lanes once, and again only if connectors were added."""
    if not lane_map.lanes or not len(trajectories):
        return lane_map
    placed = placed_trajectories(lane_map, {ln.id: ln for ln in lane_map.lanes}, trajectories)
    joined = trajectory_connectors(lane_map, trajectories, placed=placed)
    return drive_path_lanes(joined, trajectories, placed=placed if joined is lane_map else None)


def drive_path_lanes(
    lane_map: LaneMap, trajectories: Sequence[np.ndarray], *, min_drives: int = MIN_DRIVES, placed: Placed | None = None
) -> LaneMap:
    """``lane_map`` with drive-path lanes (module docstring) where at least ``min_drives`` of the
    (N, 2) ``trajectories`` [m, map frame, time ordered] went at least MIN_RUN_M outside every lane
    of their direction. No trajectory or no such way: ``lane_map`` itself. ``placed``:
    :func:`hdmap_core.lanes.connectors.placed_trajectories` of these on ``lane_map``, if made."""
    if not lane_map.lanes or not len(trajectories):
        return lane_map
    lanes = {ln.id: ln for ln in lane_map.lanes}
    if placed is None:
        placed = placed_trajectories(lane_map, lanes, trajectories)
    paths = _paths(placed, lanes, max(1, min_drives))
    if not paths:
        return lane_map
    bounds = {b.id: b for b in lane_map.boundaries}
    nodes = dict(lane_map.nodes or {})
    width = float(np.median(np.concatenate([ln.width for ln in lane_map.lanes])))
    ends = _Ends(lane_map.lanes)
    new_lanes: list[Lane] = []
    for path in paths:
        made = _lane(path, ends, lanes, bounds, nodes, width)
        if made is None:
            continue
        lane, left, right = made
        if lane.id in lanes or any(x.id == lane.id for x in new_lanes):
            continue
        new_lanes.append(lane)
        bounds[left.id] = left
        bounds[right.id] = right
    if not new_lanes:
        return lane_map
    return LaneMap(
        relinked([*lane_map.lanes, *new_lanes], bounds),
        tuple(sorted(bounds.values(), key=lambda b: b.id)),
        nodes,
    )


def _paths(
    placed: list[tuple[np.ndarray, np.ndarray, np.ndarray]], lanes: dict[int, Lane], min_drives: int
) -> list[np.ndarray]:
    """RULES D1-D2: the mean paths (M, 2) of the supported off-lane stretches."""
    pts, yaw, drive, runs = [], [], [], []
    on_pts, on_yaw, on_drive, on_lines = [], [], [], []
    lined = {0: (False, False)} | {
        i: (ln.left_type != FeatureType.UNKNOWN, ln.right_type != FeatureType.UNKNOWN) for i, ln in lanes.items()
    }
    start = 0
    need = max(2, int(np.ceil(MIN_RUN_M / STEP_M)))
    lone = {0: (True, True)} | {i: (ln.left is None, ln.right is None) for i, ln in lanes.items()}
    for k, (p, ids, aside) in enumerate(placed):
        if np.mean(ids == 0) > MAX_OFF_SHARE:
            continue  # RULE D1: a drive that is mostly in no lane is lost, no evidence
        d = np.gradient(p, axis=0)
        # no lane, or off the lane's centerline towards a side without a neighbour lane (beside
        # a neighbour it is a drive between two lanes: a lane change or a drive on the line)
        free = np.array([lone[i][0 if a > 0 else 1] for i, a in zip(ids.tolist(), aside.tolist(), strict=True)])
        off = (ids == 0) | ((np.abs(aside) > OFF_M) & free.astype(bool).reshape(-1))
        pts.append(p[off])
        yaw.append(np.arctan2(d[off, 1], d[off, 0]))
        drive.append(np.full(int(off.sum()), k))
        on_pts.append(p[~off])
        on_yaw.append(np.arctan2(d[~off, 1], d[~off, 0]))
        on_drive.append(np.full(int((~off).sum()), k))
        on_lines.append(np.array([lined[i] for i in ids[~off].tolist()], dtype=bool).reshape(-1, 2))
        # runs of off-lane points, as indices into the concatenated off-lane points; a run ends
        # where the drive crosses from one lane into its neighbour (a lane change, not a way)
        change = np.zeros(len(ids), dtype=bool)
        change[1:] = (ids[1:] != ids[:-1]) & (ids[1:] != 0) & (ids[:-1] != 0) & (aside[1:] * aside[:-1] < 0)
        pos = np.cumsum(off) - 1  # index among this drive's off-lane points
        first = np.flatnonzero(off & (change | ~np.concatenate([[False], off[:-1]])))
        last = np.concatenate([first[1:], [len(ids)]])[: len(first)]
        for a, b in zip(first.tolist(), last.tolist(), strict=True):
            b = a + int(np.argmin(np.concatenate([off[a:b], [False]])))  # the run's end
            if b - a >= need:
                runs.append((start + int(pos[a]), start + int(pos[b - 1]) + 1))
        start += int(off.sum())
    if not runs:
        return []
    xy = np.concatenate(pts)
    hd = np.concatenate(yaw)
    dv = np.concatenate(drive)
    unit = np.stack([np.cos(hd), np.sin(hd)], axis=1)
    tree = cKDTree(xy)
    on_xy = np.concatenate(on_pts)
    on_unit = np.concatenate(on_yaw)
    on_unit = np.stack([np.cos(on_unit), np.sin(on_unit)], axis=1)
    on_dv = np.concatenate(on_drive)
    on_lined = np.concatenate(on_lines)
    on_tree = cKDTree(on_xy) if len(on_xy) else None
    beside = _lined_sides(lanes.values())
    used = np.zeros(len(xy), dtype=bool)
    out: list[np.ndarray] = []
    for a, b in sorted(runs, key=lambda r: (r[0] - r[1], r[0])):
        idx = np.arange(a, b)
        near = tree.query_ball_point(xy[idx], SUPPORT_M)
        against = on_tree.query_ball_point(xy[idx], AGAINST_M) if on_tree is not None else [[]] * len(idx)
        lined_near = beside(xy[idx], unit[idx])
        mean = np.zeros((len(idx), 2))
        ok = np.zeros(len(idx), dtype=bool)
        for j, (i, nb, no) in enumerate(zip(idx, near, against, strict=True)):
            if used[i]:
                continue
            nb = np.asarray(nb, dtype=np.int64)
            nb = nb[~used[nb] & (unit[nb] @ unit[i] >= _ANGLE_COS)]
            no = np.asarray(no, dtype=np.int64)
            no = no[on_unit[no] @ unit[i] >= _ANGLE_COS]
            rel = xy[i] - on_xy[no]
            left = on_unit[no, 0] * rel[:, 1] - on_unit[no, 1] * rel[:, 0] > 0
            no = no[np.where(left, on_lined[no, 0], on_lined[no, 1])]
            support = np.unique(dv[nb])
            least = max(min_drives, LINED_DRIVES) if lined_near[j] else min_drives
            if len(support) >= least and len(support) > len(np.setdiff1d(on_dv[no], support)):
                ok[j] = True
                mean[j] = xy[nb].mean(axis=0)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
        for s0, s1 in zip(edges[::2], edges[1::2], strict=True):
            if s1 - s0 < need:
                continue
            path = _smoothed(mean[s0:s1])
            out.append(path)
            # RULE D2: the off-lane points along this path are used up
            d = np.gradient(path, axis=0)
            d /= np.maximum(np.hypot(*d.T), 1e-9)[:, None]
            for j, nb in enumerate(tree.query_ball_point(path, SUPPORT_M)):
                nb = np.asarray(nb, dtype=np.int64)
                used[nb[unit[nb] @ d[j] >= _ANGLE_COS]] = True
    return out


def _lined_sides(lanes: Iterable[Lane]) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """RULE D2: a function telling, per point and unit heading, whether a lane of that direction
    has a mapped line (not virtual) on its side towards the point within AGAINST_M."""
    xy, dirs, lined = [], [], []
    for ln in lanes:
        c = ln.centerline
        if len(c) < 2:
            continue
        d = np.gradient(c, axis=0)
        xy.append(c)
        dirs.append(d / np.maximum(np.hypot(*d.T), 1e-9)[:, None])
        sides = [ln.left_type != FeatureType.UNKNOWN, ln.right_type != FeatureType.UNKNOWN]
        lined.append(np.tile(sides, (len(c), 1)))
    if not xy:
        return lambda p, u: np.zeros(len(p), dtype=bool)
    at, to, has = np.concatenate(xy), np.concatenate(dirs), np.concatenate(lined).astype(bool)
    tree = cKDTree(at)

    def near(p: np.ndarray, u: np.ndarray) -> np.ndarray:
        out = np.zeros(len(p), dtype=bool)
        for j, nb in enumerate(tree.query_ball_point(p, AGAINST_M)):
            nb = np.asarray(nb, dtype=np.int64)
            nb = nb[to[nb] @ u[j] >= _ANGLE_COS]
            rel = p[j] - at[nb]
            left = to[nb, 0] * rel[:, 1] - to[nb, 1] * rel[:, 0] > 0
            out[j] = bool(np.any(np.where(left, has[nb, 0], has[nb, 1])))
        return out

    return near


def _smoothed(path: np.ndarray) -> np.ndarray:
    """Moving average over SMOOTH_M (the ends keep their points)."""
    k = int(round(SMOOTH_M / STEP_M)) // 2
    if k < 1 or len(path) < 2 * k + 1:
        return path
    kernel = np.ones(2 * k + 1) / (2 * k + 1)
    out = path.copy()
    for c in range(2):
        out[k:-k, c] = np.convolve(path[:, c], kernel, mode="valid")
    return out


class _Ends:
    """Lane ends and starts, found by position and checked for direction."""

    def __init__(self, lanes: Sequence[Lane]) -> None:
        usable = [ln for ln in lanes if len(ln.centerline) >= 2]
        self.ids = [ln.id for ln in usable]
        self.last = np.array([ln.centerline[-1] for ln in usable]).reshape(-1, 2)
        self.first = np.array([ln.centerline[0] for ln in usable]).reshape(-1, 2)
        self.tree_last = cKDTree(self.last) if usable else None
        self.tree_first = cKDTree(self.first) if usable else None

    def near(self, at: np.ndarray, direction: np.ndarray, lanes: dict[int, Lane], *, end: bool) -> int | None:
        tree = self.tree_last if end else self.tree_first
        if tree is None:
            return None
        best: tuple[float, int | None] = (JOIN_M, None)
        for k in tree.query_ball_point(at, JOIN_M):
            ln = lanes[self.ids[k]]
            if _direction(ln.centerline, first=not end) @ direction < _JOIN_COS:
                continue
            dist = float(np.hypot(*((self.last if end else self.first)[k] - at)))
            if dist <= best[0]:
                best = (dist, ln.id)
        return best[1]


def _lane(
    path: np.ndarray,
    ends: _Ends,
    lanes: dict[int, Lane],
    bounds: dict[int, Boundary],
    nodes: dict[int, np.ndarray],
    width: float,
) -> tuple[Lane, Boundary, Boundary] | None:
    """RULE D3: the drive-path lane along ``path`` with its two virtual sides; None if degenerate."""
    if len(path) < 3:
        return None
    d = np.gradient(path, axis=0)
    d /= np.maximum(np.hypot(*d.T), 1e-9)[:, None]
    p = ends.near(path[0], d[0], lanes, end=True)
    q = ends.near(path[-1], d[-1], lanes, end=False)
    if p is not None and p == q:
        q = None
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(path, axis=0).T))])
    length = float(s[-1])
    t = (s / max(length, 1e-9))[:, None]
    reach = min(_PIN_M / max(length, 1e-9), 0.5)
    w0 = np.clip(1.0 - t / reach, 0.0, 1.0) if p is not None else np.zeros_like(t)
    w1 = np.clip(1.0 - (1.0 - t) / reach, 0.0, 1.0) if q is not None else np.zeros_like(t)
    key = [int(round(v * 10.0)) & ((1 << 64) - 1) for v in (*path[0], *path[-1])]
    lane_id = stable_id("drive_path", *key)
    h0 = lanes[p].width[-1] / 2.0 if p is not None else width / 2.0
    h1 = lanes[q].width[0] / 2.0 if q is not None else width / 2.0
    half = (1.0 - t[:, 0]) * h0 + t[:, 0] * h1
    center = path.copy()
    if p is not None:
        center = center + w0 * (lanes[p].centerline[-1] - center[0])
    if q is not None:
        center = center + w1 * (lanes[q].centerline[0] - center[-1])
    d = np.gradient(center, axis=0)
    d /= np.maximum(np.hypot(*d.T), 1e-9)[:, None]
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1)
    sides = []
    for sign, pick in ((1.0, 0), (-1.0, 1)):
        pts = center + sign * half[:, None] * normal
        if p is not None:
            a = bounds[(lanes[p].left_boundary, lanes[p].right_boundary)[pick]]
            pts = pts + w0 * (a.points[-1] - pts[0])
            n0 = a.end_node
        else:
            n0 = stable_id("drive_path_node", lane_id, pick, 0)
            nodes[n0] = pts[0].copy()
        if q is not None:
            b = bounds[(lanes[q].left_boundary, lanes[q].right_boundary)[pick]]
            pts = pts + w1 * (b.points[0] - pts[-1])
            n1 = b.start_node
        else:
            n1 = stable_id("drive_path_node", lane_id, pick, 1)
            nodes[n1] = pts[-1].copy()
        sides.append(Boundary(stable_id("drive_path_side", lane_id, pick), 0, FeatureType.UNKNOWN, pts, n0, n1))
    left, right = sides
    return virtual_lane(lane_id, left, right)


def _direction(line: np.ndarray, *, first: bool) -> np.ndarray:
    """Unit direction of a polyline over its first (last) few points."""
    k = min(len(line) - 1, 5)
    v = line[k] - line[0] if first else line[-1] - line[len(line) - 1 - k]
    return v / max(float(np.hypot(*v)), 1e-9)
