"""Splits and merges for the evaluator: are the ground truth's splits and merges connected in the map?

Ground-truth branch points come from the features alone (the ground truth has no feature links):
features of one class (lane lines = solid and dashed together, or road borders) meeting at a point
within ``JOIN_TOL_M``. At a point, a feature that ends there comes in, one that starts there goes
out, one that passes through does both; features running against the point's direction (more than
``max_feature_angle_deg``) are ignored. A point with at least one incoming and two outgoing
branches is a split, with two incoming and at least one outgoing a merge (``docs/evaluation.md``).

Each branch is sampled on the evaluator's cuts where it is at least ``separation_m`` away from the
other branches on its side (so that a map line near one branch cannot belong to another), over
``window_m``; the map features matched to those ground-truth points within the recall radius stand
for the branch. The point is found when, for every branch on its multi side, a map feature of the
single side reaches a map feature of that branch through successor links (or geometric joints,
see ``map_feature_graph``) whose joints lie within ``reach_m + window_m`` of the point.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
from scipy.cluster.hierarchy import DisjointSet
from scipy.spatial import cKDTree

from hdmap_core.evaluation.cuts import CutPoints, Cuts
from hdmap_core.groundtruth import GTFeature
from hdmap_core.model import FeatureType, MapFeature

__all__ = [
    "BranchPoint",
    "JOIN_TOL_M",
    "ground_truth_branch_points",
    "map_feature_graph",
    "check_branch_points",
    "on_cuts",
    "inside_cuts",
]

#: Feature ends closer than this are one point (the shared maps' joints are <= 0.002 m apart).
JOIN_TOL_M = 0.05


@dataclass(frozen=True)
class BranchPoint:
    """A ground-truth split or merge and whether the map has it connected.

    Attributes:
        kind: "split" or "merge".
        x, y: position [m]; heading_rad: ENU yaw of the driving direction there.
        gt_features: ids of the ground-truth features meeting there.
        n_in, n_out: incoming / outgoing branches.
        evaluable: the single side and at least two branches of the multi side have sample points.
        found: evaluable and connected in the map.
        reason: why not found / not evaluable ("" when found).
    """

    kind: str
    x: float
    y: float
    heading_rad: float
    gt_features: tuple[int, ...]
    n_in: int
    n_out: int
    evaluable: bool
    found: bool
    reason: str = ""

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class _Branch:
    feature: int  # index into the ground-truth feature list
    arc_m: float  # arc length of the point along the feature
    side: int  # -1: the part before the point (incoming), +1: after it (outgoing)


@dataclass(frozen=True)
class _Node:
    kind: str
    xy: np.ndarray
    heading: float
    branches: tuple[_Branch, ...]


def _class_of(t: FeatureType) -> int:
    return 1 if t == FeatureType.ROAD_BORDER else 0


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-12, n, 1.0)


def _arc(points: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def _locate(points: np.ndarray, arc: np.ndarray, q: np.ndarray) -> tuple[float, np.ndarray]:
    """Arc length of the point of ``points`` nearest to ``q`` and the unit direction there."""
    a, b = points[:-1], points[1:]
    d = b - a
    L2 = np.maximum((d * d).sum(axis=1), 1e-18)
    u = np.clip(((q - a) * d).sum(axis=1) / L2, 0.0, 1.0)
    dist = np.linalg.norm(a + u[:, None] * d - q, axis=1)
    j = int(np.argmin(dist))
    return float(arc[j] + u[j] * (arc[j + 1] - arc[j])), _unit(d[j])


def ground_truth_branch_points(features: Sequence[GTFeature], *, cos_min: float) -> list[_Node]:
    """Splits and merges of the ground-truth features (see the module docstring).

    Args:
        features: ground-truth features with (N >= 2, 2) finite points in driving direction.
        cos_min: cosine of the largest angle between a branch and the point's direction.

    Returns:
        The branch points in a deterministic order (by position of their first feature end).
    """
    feats = [f for f in features if len(f.points) >= 2]
    if not feats:
        return []
    pts = [np.asarray(f.points, dtype=float) for f in feats]
    arcs = [_arc(p) for p in pts]
    cls = np.array([_class_of(f.type) for f in feats])
    n = len(feats)
    ends = np.concatenate([np.array([p[0] for p in pts]), np.array([p[-1] for p in pts])])  # starts, then ends
    ds = DisjointSet(range(2 * n))
    for i, j in cKDTree(ends).query_pairs(JOIN_TOL_M):
        if cls[i % n] == cls[j % n]:
            ds.merge(i, j)
    tree = shapely.STRtree([shapely.LineString(p) for p in pts])
    nodes: list[_Node] = []
    for group in sorted((sorted(g) for g in ds.subsets()), key=lambda g: g[0]):
        first = group[0]
        f0 = first % n
        q = ends[first]
        ref = _unit(pts[f0][1] - pts[f0][0]) if first < n else _unit(pts[f0][-1] - pts[f0][-2])
        starts = {e for e in group if e < n}
        stops = {e - n for e in group if e >= n}
        branches: list[_Branch] = []
        for f in sorted(int(i) for i in tree.query(shapely.points(q), predicate="dwithin", distance=JOIN_TOL_M)):
            if cls[f] != cls[f0]:
                continue
            arc_q, direction = _locate(pts[f], arcs[f], q)
            if float(direction @ ref) < cos_min:
                continue
            if f in starts:
                branches.append(_Branch(f, 0.0, +1))
            if f in stops:
                branches.append(_Branch(f, float(arcs[f][-1]), -1))
            if f not in starts and f not in stops:
                branches += [_Branch(f, arc_q, -1), _Branch(f, arc_q, +1)]
        n_in = sum(b.side < 0 for b in branches)
        n_out = len(branches) - n_in
        heading = float(np.arctan2(ref[1], ref[0]))
        if n_in >= 1 and n_out >= 2:
            nodes.append(_Node("split", q, heading, tuple(branches)))
        if n_in >= 2 and n_out >= 1:
            nodes.append(_Node("merge", q, heading, tuple(branches)))
    return nodes


def on_cuts(nodes: list[_Node], cuts: Cuts, *, half_step_m: float, cos_min: float) -> list[_Node]:
    """The nodes inside the rectangle of a cut running their way (the evaluated carriageways)."""
    if not nodes:
        return []
    xy = np.array([nd.xy for nd in nodes])
    heading = np.array([nd.heading for nd in nodes])
    inside = inside_cuts(xy, heading, cuts, half_step_m=half_step_m, cos_min=cos_min)
    return [nd for nd, ok in zip(nodes, inside) if ok]


def inside_cuts(
    xy: np.ndarray, heading_rad: np.ndarray, cuts: Cuts, *, half_step_m: float, cos_min: float
) -> np.ndarray:
    """(N,) bool: the points (N, 2) [m] lie in the rectangle of a cut (``half_step_m`` along, within
    its extent across) whose direction is within ``arccos(cos_min)`` of their heading (N,) [rad]."""
    keep = np.zeros(len(xy), dtype=bool)
    if len(xy) == 0 or len(cuts) == 0:
        return keep
    heading = np.stack([np.cos(heading_rad), np.sin(heading_rad)], axis=1)
    tree = cKDTree(cuts.center)
    reach = half_step_m + float(np.max(np.maximum(-cuts.lo, cuts.hi)))
    # All (point, cut) pairs within reach at once (maps have thousands of topology nodes).
    hits = tree.query_ball_point(xy, r=reach)
    owner = np.repeat(np.arange(len(xy)), [len(h) for h in hits])
    if len(owner) == 0:
        return keep
    c = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    d = xy[owner] - cuts.center[c]
    along = np.abs((d * cuts.tangent[c]).sum(axis=1))
    across = (d * cuts.normal[c]).sum(axis=1)
    inside = (along <= half_step_m + 1e-6) & (across >= cuts.lo[c]) & (across <= cuts.hi[c])
    inside &= (cuts.tangent[c] * heading[owner]).sum(axis=1) >= cos_min
    keep[owner[inside]] = True
    return keep


def map_feature_graph(
    feats: Sequence[MapFeature], *, attach_m: float, cos_min: float
) -> list[list[tuple[int, np.ndarray]]]:
    """Directed connections between map features: successor links and geometric joints.

    X -> Y when Y is among X's successors or X among Y's predecessors (ids; unknown ids ignored),
    or when Y's first point lies within ``attach_m`` of the interior of X (Y starts on X: a split
    drawn as a through line and a branch starting on it, which links cannot express) or X's last
    point within ``attach_m`` of the interior of Y (a merge), the two running the same way there
    (cosine >= ``cos_min``). "Interior": farther than ``attach_m`` from both ends of the through
    feature; ends that merely touch count only when linked.

    Returns:
        per feature index, its (successor index, (2,) joint position [m]) pairs.
    """
    n = len(feats)
    edges: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
    if n == 0:
        return edges
    pts = [np.asarray(f.points, dtype=float) for f in feats]
    index = {int(f.id): i for i, f in enumerate(feats)}
    seen: set[tuple[int, int]] = set()

    def add(i: int, j: int, where: np.ndarray) -> None:
        if i != j and (i, j) not in seen:
            seen.add((i, j))
            edges[i].append((j, where))

    for i, f in enumerate(feats):
        for sid in f.successors:
            j = index.get(int(sid))
            if j is not None:
                add(i, j, pts[i][-1])
        for pid in f.predecessors:
            j = index.get(int(pid))
            if j is not None:
                add(j, i, pts[j][-1])
    tree = shapely.STRtree([shapely.LineString(p) for p in pts])
    firsts = np.array([p[0] for p in pts])
    lasts = np.array([p[-1] for p in pts])
    arcs = [_arc(p) for p in pts]

    def interior(q: np.ndarray, k: int) -> bool:
        return bool(min(np.linalg.norm(q - firsts[k]), np.linalg.norm(q - lasts[k])) > attach_m)

    for y, x in zip(*tree.query(shapely.points(firsts), predicate="dwithin", distance=attach_m)):
        if x == y or not interior(firsts[y], x):
            continue
        _, d = _locate(pts[x], arcs[x], firsts[y])
        if float(d @ _unit(pts[y][1] - pts[y][0])) >= cos_min:
            add(int(x), int(y), firsts[y])
    for x, y in zip(*tree.query(shapely.points(lasts), predicate="dwithin", distance=attach_m)):
        if x == y or not interior(lasts[x], y):
            continue
        _, d = _locate(pts[y], arcs[y], lasts[x])
        if float(d @ _unit(pts[x][-1] - pts[x][-2])) >= cos_min:
            add(int(x), int(y), lasts[x])
    return edges


def check_branch_points(
    nodes: list[_Node],
    gt_features: Sequence[GTFeature],
    gp: CutPoints,
    matched_gt: np.ndarray,
    matched_map: np.ndarray,
    graph: list[list[tuple[int, np.ndarray]]],
    *,
    separation_m: float,
    window_m: float,
    reach_m: float,
) -> list[BranchPoint]:
    """Decide for each ground-truth branch point whether the map has it connected.

    Args:
        nodes: from ``ground_truth_branch_points`` (already restricted to the evaluated area).
        gt_features: the ground-truth features the nodes' branch indices refer to.
        gp: the ground-truth points on the cuts (owner = index into ``gt_features``).
        matched_gt, matched_map: (Q,) pairs (ground-truth point index, map feature index) of map
            points within the recall radius of a same-type ground-truth point on their cut.
        graph: ``map_feature_graph`` of the map features (the matched map feature indices refer to it).
        separation_m: a branch is sampled only where it is this far from the other branches of its
            side on the same cut.
        window_m: length of each branch's sample, from where it is first separated [m].
        reach_m: the farthest from the point a sample may start [m].
    """
    forward_edges = graph
    backward_edges: list[list[tuple[int, np.ndarray]]] = [[] for _ in graph]
    for i, edges in enumerate(graph):
        for j, where in edges:
            backward_edges[j].append((i, where))
    arcs = [_arc(np.asarray(f.points, dtype=float)) for f in gt_features]
    if len(gp.owner):
        sizes = np.array([len(a) for a in arcs])
        first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        flat = np.concatenate(arcs)
        a_lo = flat[first[gp.owner] + gp.vertex]
        a_hi = flat[first[gp.owner] + np.minimum(gp.vertex + 1, sizes[gp.owner] - 1)]
        g_arc = a_lo + gp.u * (a_hi - a_lo)
    else:
        g_arc = np.zeros(0)
    by_owner: dict[int, np.ndarray] = {}
    order = np.argsort(gp.owner, kind="stable")
    bounds = np.searchsorted(gp.owner[order], np.arange(len(gt_features) + 1))
    for o in range(len(gt_features)):
        by_owner[o] = order[bounds[o] : bounds[o + 1]]
    pair_order = np.argsort(matched_gt, kind="stable")
    pg, pm = matched_gt[pair_order], matched_map[pair_order]

    def window(b: _Branch, others: list[_Branch]) -> np.ndarray:
        idx = by_owner.get(b.feature, np.zeros(0, dtype=np.int64))
        x = b.side * (g_arc[idx] - b.arc_m)
        idx, x = idx[(x > 0) & (x <= reach_m + window_m)], x[(x > 0) & (x <= reach_m + window_m)]
        ok = np.ones(len(idx), dtype=bool)
        for o in others:
            oidx = by_owner.get(o.feature, np.zeros(0, dtype=np.int64))
            ox = o.side * (g_arc[oidx] - o.arc_m)
            oidx = oidx[(ox > 0) & (ox <= reach_m + window_m + separation_m)]
            for k in np.flatnonzero(ok):
                same = gp.cut[oidx] == gp.cut[idx[k]]
                if same.any() and np.min(np.abs(gp.s[oidx[same]] - gp.s[idx[k]])) < separation_m:
                    ok[k] = False
        idx, x = idx[ok], x[ok]
        if len(x) == 0 or x.min() > reach_m:
            return np.zeros(0, dtype=np.int64)
        return idx[x <= x.min() + window_m]

    def mapped(points: np.ndarray) -> set[int]:
        lo = np.searchsorted(pg, points, side="left")
        hi = np.searchsorted(pg, points, side="right")
        return {int(m) for a, b in zip(lo, hi) for m in pm[a:b]}

    out = []
    for nd in nodes:
        radius = reach_m + window_m
        ins = [b for b in nd.branches if b.side < 0]
        outs = [b for b in nd.branches if b.side > 0]
        single, multi = (ins, outs) if nd.kind == "split" else (outs, ins)
        w_single = [window(b, []) for b in single]
        w_multi = [window(b, [o for o in multi if o is not b]) for b in multi]
        single_pts = np.concatenate(w_single) if w_single else np.zeros(0, dtype=np.int64)
        multi_ok = [w for w in w_multi if len(w)]
        ids = tuple(sorted({int(gt_features[b.feature].id) for b in nd.branches}))
        common: dict[str, Any] = dict(
            kind=nd.kind,
            x=float(nd.xy[0]),
            y=float(nd.xy[1]),
            heading_rad=nd.heading,
            gt_features=ids,
            n_in=len(ins),
            n_out=len(outs),
        )
        if len(single_pts) == 0 or len(multi_ok) < 2:
            why = "the single branch" if len(single_pts) == 0 else "fewer than 2 branches"
            out.append(
                BranchPoint(
                    **common,
                    evaluable=False,
                    found=False,
                    reason=f"not evaluable: {why} separated on cuts within {reach_m:g} m",
                )
            )
            continue
        m_single = mapped(single_pts)
        m_multi = [mapped(w) for w in multi_ok]
        if not m_single or not all(m_multi):
            n_missing = (not m_single) + sum(not m for m in m_multi)
            out.append(
                BranchPoint(
                    **common,
                    evaluable=True,
                    found=False,
                    reason=f"{n_missing} branch(es) not mapped within the recall radius",
                )
            )
            continue

        if nd.kind == "split":
            reached = _reach(m_single, forward_edges, nd.xy, radius)
        else:
            reached = _reach(m_single, backward_edges, nd.xy, radius)
        connected = [bool(reached & m) for m in m_multi]
        if all(connected):
            out.append(BranchPoint(**common, evaluable=True, found=True))
        else:
            out.append(
                BranchPoint(
                    **common,
                    evaluable=True,
                    found=False,
                    reason=f"{connected.count(False)} branch(es) not connected to the "
                    f"{'incoming' if nd.kind == 'split' else 'outgoing'} map feature",
                )
            )
    return out


def _reach(start: set[int], edges: list[list[tuple[int, np.ndarray]]], center: np.ndarray, radius: float) -> set[int]:
    """Map features reachable from ``start`` along ``edges`` whose joints lie within ``radius`` of ``center``."""
    seen = set(start)
    todo = deque(start)
    while todo:
        for j, where in edges[todo.popleft()]:
            if j not in seen and float(np.linalg.norm(where - center)) <= radius:
                seen.add(j)
                todo.append(j)
    return seen
