"""Road-level splits and merges for the evaluator: does the map's topology graph branch where the
ground truth's roads do?

The feature-level check (``evaluate_topology``) needs ground-truth features that meet; where the
markings stop before a junction (the CARLA maps) it has nothing to check. This one takes the
branch points from the ground truth's *lane graph* and checks the map's *topology graph*
(``HDMap.topology``, road midpoints per step with successors), see ``docs/evaluation.md``
"Road-level splits and merges":

1. a lane with two or more successors (predecessors) is a candidate split (merge) at its end (start);
2. each successor's lanes are followed (all successor paths) for ``follow_m``; two successors are
   on different roads when their paths part by more than ``apart_m`` (each from the other, at one
   distance from the point: a lane added beside the others stays 3.5 m from them);
3. candidates of one kind closer than ``cluster_m`` are one road point; its branches are the
   successor paths grouped by "not parted";
4. a map topology node is on a branch when the branch's lane path crosses the node's cross-section
   (``width / 2 + margin_m`` to each side, running its way) and no other branch's path does;
5. the point is found when the map's topology connects, along successors within ``path_m``, a node
   on the single side to a node on every branch that has nodes (a merge: every branch to the
   single side).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.cluster.hierarchy import DisjointSet
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from hdmap_core.geometry import unit_tangents
from hdmap_core.groundtruth import GTLane
from hdmap_core.model import TopologyNode

__all__ = [
    "DEFAULT_NODE_WIDTH_M",
    "NODE_ALONG_M",
    "RoadBranchPoint",
    "RoadCheckConfig",
    "check_road_points",
    "densify_path",
    "road_branch_points",
]

#: Lane paths are resampled to at most this spacing [m] (the node crossing test needs dense points).
_SPACING_M = 1.0
#: A path point counts at a node when it is at most this far from the node's cross-section along the road [m].
NODE_ALONG_M = 1.0
#: Paths are compared per bin of this length of distance from the point [m].
_BIN_M = 2.0
#: Width assumed for a topology node whose width is not a finite number > 0 [m].
DEFAULT_NODE_WIDTH_M = 3.5


@dataclass(frozen=True)
class RoadCheckConfig:
    """The settings of the road-level check (from ``EvalConfig``; units in the names).

    Attributes:
        follow_m: length of lane path followed from the point on each side [m].
        apart_m: successor paths parting by more than this are different roads [m].
        cluster_m: candidates of one kind closer than this are one road point [m].
        node_margin_m: a node's cross-section reaches this far beyond its half width [m].
        path_m: longest path along topology successors between the two sides [m].
        cos_min: cosine of the largest angle between a path and a node's heading (and between
            candidates of one road point).
    """

    follow_m: float
    apart_m: float
    cluster_m: float
    node_margin_m: float
    path_m: float
    cos_min: float


@dataclass(frozen=True)
class RoadBranchPoint:
    """A ground-truth road split or merge (from the lane graph) and whether the map's topology has it.

    Attributes:
        kind: "split" or "merge".
        x, y: position [m] (mean of its lane branch points); heading_rad: ENU yaw there.
        gt_lanes: the ground-truth lanes with several successors (split) / predecessors (merge).
        branch_lanes: per branch (road of the multi side), its first lanes.
        single_nodes: map topology nodes on the single side (the incoming road of a split).
        branch_nodes: per branch, map topology nodes on it (where it is told apart from the others).
        branch_connected: per branch, whether a single-side node is connected to one of its nodes.
        evaluable: the single side and at least two branches have map nodes.
        found: evaluable and every branch with nodes connected.
        reason: why not found / not evaluable ("" when found).
    """

    kind: str
    x: float
    y: float
    heading_rad: float
    gt_lanes: tuple[str, ...]
    branch_lanes: tuple[tuple[str, ...], ...]
    single_nodes: int
    branch_nodes: tuple[int, ...]
    branch_connected: tuple[bool, ...]
    evaluable: bool
    found: bool
    reason: str = ""

    def to_dict(self) -> dict:
        out = dict(self.__dict__)
        out["gt_lanes"] = list(self.gt_lanes)
        out["branch_lanes"] = [list(b) for b in self.branch_lanes]
        out["branch_nodes"] = list(self.branch_nodes)
        out["branch_connected"] = list(self.branch_connected)
        return out


@dataclass(frozen=True)
class _Path:
    """Lane paths followed from a point: (M, 2) points, (M,) distance from the point along the
    path [m], (M, 2) unit driving direction."""

    xy: np.ndarray
    dist: np.ndarray
    direction: np.ndarray

    @staticmethod
    def concat(paths: Sequence[_Path]) -> _Path:
        return _Path(*(np.concatenate([getattr(p, k) for p in paths]) for k in ("xy", "dist", "direction")))


@dataclass(frozen=True)
class _Candidate:
    kind: str
    lane: str
    xy: np.ndarray
    heading: float
    single: _Path
    branches: tuple[tuple[str, _Path], ...]  # (first lane, its paths) per successor / predecessor


@dataclass(frozen=True)
class RoadPoint:
    """A road split or merge of the ground truth before it is checked against a map."""

    kind: str
    xy: np.ndarray
    heading: float
    lanes: tuple[str, ...]
    single: _Path
    branches: tuple[tuple[tuple[str, ...], _Path], ...]  # (first lanes, their paths) per road


def densify_path(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) points at most ``_SPACING_M`` apart on the polyline ``points`` and their (M,) arc."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    if arc[-1] <= 0:
        return points[:1], arc[:1]
    s = np.linspace(0.0, arc[-1], int(np.ceil(arc[-1] / _SPACING_M)) + 1)
    return np.stack([np.interp(s, arc, points[:, 0]), np.interp(s, arc, points[:, 1])], axis=1), s


def follow_lanes(lanes: Mapping[str, GTLane], start: str, *, forward: bool, follow_m: float) -> _Path:
    """All lane paths from the start (forward) or end (backward) of lane ``start``, along successors
    (predecessors), up to ``follow_m`` from there; each lane taken once (the first time reached)."""
    parts: list[_Path] = []
    todo, seen = [(start, 0.0)], set()
    while todo:
        lid, d0 = todo.pop()
        if lid in seen or lid not in lanes:
            continue
        seen.add(lid)
        line = lanes[lid].centerline if forward else lanes[lid].centerline[::-1]
        xy, arc = densify_path(np.asarray(line, dtype=float))
        direction = unit_tangents(xy)
        if not forward:
            direction = -direction
        keep = d0 + arc <= follow_m
        parts.append(_Path(xy[keep], d0 + arc[keep], direction[keep]))
        if d0 + arc[-1] < follow_m:
            nxt = lanes[lid].successors if forward else lanes[lid].predecessors
            todo += [(n, d0 + float(arc[-1])) for n in nxt]
    return _Path.concat(parts) if parts else _Path(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)))


def _away_m(a: _Path, b: _Path) -> float:
    """How far the paths ``a`` get from ``b``: over bins of distance from the point (up to where
    both reach), the largest of the bins' smallest distance from an ``a`` point to any ``b`` point."""
    if len(a.dist) == 0 or len(b.dist) == 0:
        return 0.0
    d = cKDTree(b.xy).query(a.xy)[0]
    keep = a.dist <= min(a.dist.max(), b.dist.max())
    bins = (a.dist[keep] // _BIN_M).astype(np.int64)
    lowest = np.full(int(bins.max()) + 1, np.inf)
    np.minimum.at(lowest, bins, d[keep])
    return float(lowest[np.isfinite(lowest)].max())


def parting_m(a: _Path, b: _Path) -> float:
    """How far two branches part: the smaller of ``_away_m`` both ways (a lane added beside another
    stays at the lane width both ways; a ramp gets far from the main road, and it from the ramp)."""
    return min(_away_m(a, b), _away_m(b, a))


def _candidates(lanes: Mapping[str, GTLane], *, highway_only: bool, cfg: RoadCheckConfig) -> list[_Candidate]:
    """Lane-level branch points (RULE R1) whose branches part into different roads (RULE R2)."""
    out = []
    for lid, lane in lanes.items():
        if highway_only and not lane.highway:
            continue
        for kind, others, forward in (("split", lane.successors, True), ("merge", lane.predecessors, False)):
            others = tuple(o for o in others if o in lanes)
            # RULE R1: a lane with >= 2 successors (predecessors) is a candidate split (merge).
            if len(others) < 2:
                continue
            paths = [follow_lanes(lanes, o, forward=forward, follow_m=cfg.follow_m) for o in others]
            # RULE R2: it is a road split (merge) when two of its branches part by more than apart_m.
            if max(parting_m(paths[i], paths[j]) for i in range(len(paths)) for j in range(i)) <= cfg.apart_m:
                continue
            line = np.asarray(lane.centerline, dtype=float)
            xy, d = (line[-1], line[-1] - line[-2]) if forward else (line[0], line[1] - line[0])
            single = follow_lanes(lanes, lid, forward=not forward, follow_m=cfg.follow_m)
            out.append(_Candidate(kind, lid, xy, float(np.arctan2(d[1], d[0])), single, tuple(zip(others, paths))))
    return out


def road_branch_points(lanes: Mapping[str, GTLane], *, highway_only: bool, cfg: RoadCheckConfig) -> list[RoadPoint]:
    """The ground truth's road splits and merges (RULES R1-R3), in lane order."""
    cands = _candidates(lanes, highway_only=highway_only, cfg=cfg)
    ds = DisjointSet(range(len(cands)))
    for i in range(len(cands)):
        for j in range(i):
            a, b = cands[i], cands[j]
            # RULE R3: candidates of one kind, heading the same way, closer than cluster_m are one point.
            same_way = np.cos(a.heading - b.heading) >= cfg.cos_min
            if a.kind == b.kind and same_way and np.linalg.norm(a.xy - b.xy) <= cfg.cluster_m:
                ds.merge(i, j)
    return [_road_point([cands[k] for k in sorted(g)], cfg) for g in sorted(ds.subsets(), key=min)]


def _road_point(members: list[_Candidate], cfg: RoadCheckConfig) -> RoadPoint:
    """One road point from its candidates: branches grouped by not parting (RULE R3)."""
    flat = [b for c in members for b in c.branches]
    ds = DisjointSet(range(len(flat)))
    for i in range(len(flat)):
        for j in range(i):
            if parting_m(flat[i][1], flat[j][1]) <= cfg.apart_m:
                ds.merge(i, j)
    groups = sorted((sorted(g) for g in ds.subsets()), key=min)
    branches = tuple((tuple(sorted({flat[k][0] for k in g})), _Path.concat([flat[k][1] for k in g])) for g in groups)
    return RoadPoint(
        kind=members[0].kind,
        xy=np.mean([c.xy for c in members], axis=0),
        heading=members[0].heading,
        lanes=tuple(c.lane for c in members),
        single=_Path.concat([c.single for c in members]),
        branches=branches,
    )


# ------------------------------------------------------------------------------ the map's side


@dataclass(frozen=True)
class TopologyArrays:
    """The map's topology graph as arrays: (N, 2) positions, (N, 2) unit headings, (N,) half
    widths of the cross-sections (with the margin) [m], the successor graph (N x N sparse,
    weight = distance between the linked nodes [m]), (N,) node ids, and the (E,) edges
    ``src -> dst`` (node indices, each distinct linked pair once)."""

    xy: np.ndarray
    tangent: np.ndarray
    half_m: np.ndarray
    graph: csr_matrix
    tree: cKDTree | None
    ids: np.ndarray
    src: np.ndarray
    dst: np.ndarray

    @staticmethod
    def build(nodes: Sequence[TopologyNode], margin_m: float) -> TopologyArrays:
        xy = np.array([np.asarray(n.position, dtype=float)[:2] for n in nodes]).reshape(-1, 2)
        yaw = np.array([float(n.heading) for n in nodes])
        width = np.array([float(n.width) for n in nodes])
        width = np.where(np.isfinite(width) & (width > 0), width, DEFAULT_NODE_WIDTH_M)
        index = {int(n.id): i for i, n in enumerate(nodes)}
        pairs = sorted({(i, index[int(s)]) for i, n in enumerate(nodes) for s in n.successors if int(s) in index})
        src, dst = (np.array(p, dtype=np.int64) for p in zip(*pairs)) if pairs else (np.zeros(0, np.int64),) * 2
        # Zero weights would drop an edge from the sparse graph: coincident nodes are 1 mm apart.
        w = np.maximum(np.linalg.norm(xy[dst] - xy[src], axis=1), 1e-3)
        graph = csr_matrix((w, (src, dst)), shape=(len(nodes), len(nodes)))
        ok = np.all(np.isfinite(xy), axis=1)
        xy = np.where(ok[:, None], xy, 1e12)
        return TopologyArrays(
            xy,
            np.stack([np.cos(yaw), np.sin(yaw)], axis=1),
            width / 2 + margin_m,
            graph,
            cKDTree(xy) if len(xy) else None,
            np.array([int(n.id) for n in nodes], dtype=np.int64),
            src,
            dst,
        )


def _crossed(topo: TopologyArrays, cand: np.ndarray, path: _Path, cos_min: float) -> np.ndarray:
    """(C,) bool: the path crosses the cross-section of each candidate node (RULE R4): a path point
    within ``NODE_ALONG_M`` of it along the node's heading, within its half width across, running its way."""
    out = np.zeros(len(cand), dtype=bool)
    if len(cand) == 0 or len(path.dist) == 0:
        return out
    hits = cKDTree(path.xy).query_ball_point(topo.xy[cand], r=np.hypot(topo.half_m[cand], NODE_ALONG_M))
    owner = np.repeat(np.arange(len(cand)), [len(h) for h in hits])
    if len(owner) == 0:
        return out
    q = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    d = path.xy[q] - topo.xy[cand[owner]]
    t = topo.tangent[cand[owner]]
    along = np.abs((d * t).sum(axis=1))
    across = np.abs(d[:, 0] * t[:, 1] - d[:, 1] * t[:, 0])
    ok = (
        (along <= NODE_ALONG_M)
        & (across <= topo.half_m[cand[owner]])
        & ((path.direction[q] * t).sum(axis=1) >= cos_min)
    )
    out[owner[ok]] = True
    return out


def _reached(
    topo: TopologyArrays, sources: np.ndarray, targets: list[np.ndarray], path_m: float, *, reverse: bool
) -> list[bool]:
    """Per target set: is one of its nodes reached from a source along successors (predecessors
    when ``reverse``) within ``path_m``? (RULE R5)"""
    if len(sources) == 0:
        return [False] * len(targets)
    graph = topo.graph.T.tocsr() if reverse else topo.graph
    dist = dijkstra(graph, directed=True, indices=sources, min_only=True, limit=path_m)
    return [bool(len(t)) and bool(np.isfinite(dist[t]).any()) for t in targets]


def check_road_points(points: Sequence[RoadPoint], topo: TopologyArrays, cfg: RoadCheckConfig) -> list[RoadBranchPoint]:
    """Decide for each ground-truth road point whether the map's topology graph connects it."""
    return [_check_one(p, topo, cfg) for p in points]


def _check_one(p: RoadPoint, topo: TopologyArrays, cfg: RoadCheckConfig) -> RoadBranchPoint:
    if topo.tree is None:
        cand = np.zeros(0, dtype=np.int64)
    else:
        reach = cfg.follow_m + float(topo.half_m.max()) + NODE_ALONG_M
        cand = np.asarray(sorted(topo.tree.query_ball_point(p.xy, r=reach)), dtype=np.int64)
    single = cand[_crossed(topo, cand, p.single, cfg.cos_min)]
    on = np.array([_crossed(topo, cand, path, cfg.cos_min) for _, path in p.branches]).reshape(len(p.branches), -1)
    # RULE R4: a node is on a branch when that branch's path crosses it and no other branch's does.
    alone = on & (on.sum(axis=0) == 1)
    targets = [cand[row] for row in alone]
    connected = _reached(topo, single, targets, cfg.path_m, reverse=p.kind == "merge")
    n_nodes = tuple(int(len(t)) for t in targets)
    common: dict[str, Any] = dict(
        kind=p.kind,
        x=float(p.xy[0]),
        y=float(p.xy[1]),
        heading_rad=p.heading,
        gt_lanes=p.lanes,
        branch_lanes=tuple(b for b, _ in p.branches),
        single_nodes=int(len(single)),
        branch_nodes=n_nodes,
        branch_connected=tuple(connected),
    )
    side = "incoming" if p.kind == "split" else "outgoing"
    mapped = sum(n > 0 for n in n_nodes)
    # RULE R6: evaluable when the single side and at least two branches have nodes.
    if len(single) == 0 or mapped < 2:
        why = (
            f"no topology node on the {side} road"
            if len(single) == 0
            else f"topology nodes on {mapped} of {len(n_nodes)} branches"
        )
        return RoadBranchPoint(**common, evaluable=False, found=False, reason=f"not evaluable: {why}")
    missing = sum(n > 0 and not c for n, c in zip(n_nodes, connected))
    if missing:
        return RoadBranchPoint(
            **common,
            evaluable=True,
            found=False,
            reason=f"{missing} branch(es) not connected to the {side} road within {cfg.path_m:g} m",
        )
    return RoadBranchPoint(**common, evaluable=True, found=True)


def topology_from_lanes(
    lanes: Mapping[str, GTLane], *, step_m: float = 2.0, width_m: float = DEFAULT_NODE_WIDTH_M
) -> tuple[TopologyNode, ...]:
    """A lane-level topology graph of a ground truth (for the ground truth used as a map).

    One node every ``step_m`` along each lane centerline (at ``step_m / 2``, ``3 step_m / 2``, ...;
    a lane shorter than ``step_m`` gets one node in its middle), ``width_m`` wide, linked to the
    next node of its lane and from a lane's last node to the first node of each successor lane.
    Ids are 1, 2, ... in lane order.
    """
    firsts: dict[str, int] = {}
    rows: list[tuple[str, np.ndarray, float]] = []  # (lane, position, heading) per node
    for lid, lane in lanes.items():
        xy, arc = densify_path(np.asarray(lane.centerline, dtype=float))
        if arc[-1] <= 0:
            continue
        s = np.arange(step_m / 2, arc[-1], step_m) if arc[-1] >= step_m else np.array([arc[-1] / 2])
        pos = np.stack([np.interp(s, arc, xy[:, 0]), np.interp(s, arc, xy[:, 1])], axis=1)
        ahead = np.stack([np.interp(np.minimum(s + 0.5, arc[-1]), arc, xy[:, k]) for k in (0, 1)], axis=1)
        behind = np.stack([np.interp(np.maximum(s - 0.5, 0.0), arc, xy[:, k]) for k in (0, 1)], axis=1)
        yaw = np.arctan2(ahead[:, 1] - behind[:, 1], ahead[:, 0] - behind[:, 0])
        firsts[lid] = len(rows) + 1
        rows += [(lid, pos[i], float(yaw[i])) for i in range(len(s))]
    nodes = []
    for i, (lid, pos, yaw) in enumerate(rows):
        last = i + 1 == len(rows) or rows[i + 1][0] != lid
        succ = tuple(firsts[s] for s in lanes[lid].successors if s in firsts) if last else (i + 2,)
        nodes.append(TopologyNode(id=i + 1, position=pos, heading=yaw, width=float(width_m), successors=succ))
    return tuple(nodes)
