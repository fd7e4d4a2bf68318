"""Topology link precision for the evaluator: does the ground truth's lane graph support each link
of the map's topology graph?

The road-level check (``evaluate_roads``) asks whether the map's topology *reaches* every branch
at a ground-truth split or merge; a map that linked everything to everything would pass it. This
check is its counterpart: for every map topology edge A -> B (``TopologyNode.successors``) it asks
whether a vehicle can drive from A to B on the ground truth's lanes, see ``docs/evaluation.md``
"Topology link precision":

1. a map node is *on* the ground-truth lanes (any lane: ramps and junction lanes too) whose
   centerline crosses its cross-section (a lane point within ``NODE_ALONG_M`` of it along its heading,
   within ``width / 2 + node_margin_m`` across, running within the feature angle of its heading);
   at each such lane its station is that of the crossing point nearest the cross-section;
2. an edge is *evaluable* when both its nodes are on ground-truth lanes and at least one of them
   lies in the evaluated area (inside a cut running its way): a link from the highway onto a ramp
   whose lanes have no cuts of their own is judged, a link between two city streets is not. The
   others are *unevaluable* (counted and listed apart, not false);
3. an evaluable edge is *supported* when from a lane under A at A's station, or a lane reached
   from one by lane changes there (``left`` / ``right`` neighbours: a node is a carriageway
   midpoint, not a lane), some lane under B at B's station is reached along ground-truth
   successors with a path of at most
   ``path_factor * |AB| + path_slack_m`` (on one lane: B's station minus A's, B up to ``back_m``
   behind A counting as 0; else the rest of A's lane, whole lanes between, B's station on its
   lane); else it is *false*;
4. an edge is *long* when |AB| > ``long_m``: consecutive steps of one pivot are 2 m apart, the
   longer edges are the stitcher's links and bridged gaps, where wrong links would be.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from hdmap_core.evaluation.roads import NODE_ALONG_M, TopologyArrays, densify_path
from hdmap_core.geometry import unit_tangents
from hdmap_core.groundtruth import GTLane

__all__ = ["LinkCheckConfig", "TopologyLink", "LinkPrecision", "check_topology_links"]

#: Weight of the lane graph's end -> start links (a zero weight would drop the edge) [m].
_JOINT_M = 1e-6


@dataclass(frozen=True)
class LinkCheckConfig:
    """The settings of the link check (from ``EvalConfig``; units in the names).

    Attributes:
        node_margin_m: a node's cross-section reaches this far beyond its half width [m].
        cos_min: cosine of the largest angle between a lane and a node's heading.
        path_factor: the longest ground-truth lane path for an edge is ``path_factor`` times the
            edge's length ...
        path_slack_m: ... plus this [m].
        back_m: on one lane, B up to this far behind A (along the lane) still counts [m].
        long_m: edges longer than this are "long" (the stitcher's links) [m].
    """

    node_margin_m: float
    cos_min: float
    path_factor: float
    path_slack_m: float
    back_m: float
    long_m: float


@dataclass(frozen=True)
class TopologyLink:
    """One map topology edge (from -> to) and its verdict against the ground-truth lane graph.

    Attributes:
        from_id, to_id: the map topology node ids.
        x, y: position of the from node [m]; to_x, to_y: of the to node [m].
        length_m: |AB| [m].
        lane_path_m: shortest ground-truth lane path found from a lane under A to one under B [m]
            (inf when none within the bound, NaN when unevaluable).
        verdict: "supported", "false" or "unevaluable".
        reason: why false / unevaluable ("" when supported).
    """

    from_id: int
    to_id: int
    x: float
    y: float
    to_x: float
    to_y: float
    length_m: float
    lane_path_m: float
    verdict: str
    reason: str = ""

    def to_dict(self) -> dict:
        out = dict(self.__dict__)
        out["lane_path_m"] = self.lane_path_m if np.isfinite(self.lane_path_m) else None
        return out


@dataclass(frozen=True)
class LinkPrecision:
    """The link check of one map.

    Attributes:
        n_links, n_evaluable, n_supported: all distinct topology edges, those with both nodes on
            ground-truth lanes, and of these the supported ones.
        n_long, n_long_evaluable, n_long_supported: the same for edges longer than ``long_m``.
        false_links: every false edge (any length), longest first.
        unevaluable_long: the unevaluable long edges, longest first.
        lane_path_m: (E,) per edge (in ``TopologyArrays`` edge order) the shortest ground-truth
            lane path found [m] (inf: none within the bound; NaN: unevaluable).
    """

    n_links: int
    n_evaluable: int
    n_supported: int
    n_long: int
    n_long_evaluable: int
    n_long_supported: int
    false_links: tuple[TopologyLink, ...]
    unevaluable_long: tuple[TopologyLink, ...]
    lane_path_m: np.ndarray

    @property
    def precision(self) -> float:
        """Supported / evaluable edges (NaN when none is evaluable)."""
        return self.n_supported / self.n_evaluable if self.n_evaluable else float("nan")

    @property
    def long_precision(self) -> float:
        """Supported / evaluable long edges (NaN when none is evaluable)."""
        return self.n_long_supported / self.n_long_evaluable if self.n_long_evaluable else float("nan")


@dataclass(frozen=True)
class _LanePoints:
    """All lane centerlines resampled to <= 1 m: (M, 2) points, (M,) lane index, (M,) station
    along the lane [m], (M, 2) unit driving direction; (L,) lane lengths [m]."""

    xy: np.ndarray
    lane: np.ndarray
    station_m: np.ndarray
    direction: np.ndarray
    length_m: np.ndarray

    @staticmethod
    def build(lines: list[np.ndarray]) -> _LanePoints:
        xy, lane, st, dirs, length = [], [], [], [], []
        for k, line in enumerate(lines):
            p, arc = densify_path(np.asarray(line, dtype=float))
            d = unit_tangents(p)
            xy.append(p)
            lane.append(np.full(len(p), k, dtype=np.int64))
            st.append(arc)
            dirs.append(d)
            length.append(float(arc[-1]))
        if not xy:
            z = np.zeros((0, 2))
            return _LanePoints(z, np.zeros(0, np.int64), np.zeros(0), z, np.zeros(0))
        return _LanePoints(
            np.concatenate(xy), np.concatenate(lane), np.concatenate(st), np.concatenate(dirs), np.array(length)
        )


def _lanes_under(topo: TopologyArrays, nodes: np.ndarray, lp: _LanePoints, cos_min: float) -> tuple[np.ndarray, ...]:
    """(node, lane, station [m]) rows, sorted by node then lane, of the lanes crossing the
    cross-section of each of ``nodes`` running its way (RULE L1), at the crossing point nearest
    the cross-section."""
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(nodes) == 0 or len(lp.xy) == 0:
        return empty
    hits = cKDTree(lp.xy).query_ball_point(topo.xy[nodes], r=np.hypot(topo.half_m[nodes], NODE_ALONG_M))
    owner = np.repeat(nodes, [len(h) for h in hits])
    if len(owner) == 0:
        return empty
    q = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    d = lp.xy[q] - topo.xy[owner]
    t = topo.tangent[owner]
    along = np.abs((d * t).sum(axis=1))
    across = np.abs(d[:, 0] * t[:, 1] - d[:, 1] * t[:, 0])
    ok = (along <= NODE_ALONG_M) & (across <= topo.half_m[owner]) & ((lp.direction[q] * t).sum(axis=1) >= cos_min)
    node, lane, along, q = owner[ok], lp.lane[q[ok]], along[ok], q[ok]
    order = np.lexsort((along, lane, node))
    node, lane, q = node[order], lane[order], q[order]
    first = np.ones(len(node), dtype=bool)
    first[1:] = (node[1:] != node[:-1]) | (lane[1:] != lane[:-1])
    return node[first], lane[first], lp.station_m[q[first]]


def _with_lane_changes(
    node: np.ndarray,
    lane: np.ndarray,
    station: np.ndarray,
    lanes: Mapping[str, GTLane],
    index: Mapping[str, int],
    length_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(node, lane, station) rows plus, for each, the lanes a vehicle reaches from its lane by lane
    changes (``GTLane.left`` / ``right``, same direction, repeated) at the same share of the lane's
    length (RULE L3: a topology node is a carriageway midpoint, so a link may change lanes at its
    start); sorted by node then lane, one row per (node, lane)."""
    ids = list(index)
    side = [[index[x] for x in (lanes[lid].left, lanes[lid].right) if x is not None and x in index] for lid in ids]
    reach: list[list[int]] = []
    for k in range(len(ids)):
        seen, todo = {k}, [k]
        while todo:
            for m in side[todo.pop()]:
                if m not in seen:
                    seen.add(m)
                    todo.append(m)
        reach.append(sorted(seen))
    n_r = np.array([len(reach[k]) for k in lane.tolist()], dtype=np.int64)
    rep = np.repeat(np.arange(len(lane)), n_r)
    to = np.array([m for k in lane.tolist() for m in reach[k]], dtype=np.int64)
    share = station / np.maximum(length_m[lane], 1e-9)
    out_node, out_lane, out_s = node[rep], to, share[rep] * length_m[to]
    own = to == lane[rep]
    out_s[own] = station[rep[own]]
    order = np.lexsort((~own, out_lane, out_node))  # a lane's own row first where it is also a neighbour's
    out_node, out_lane, out_s = out_node[order], out_lane[order], out_s[order]
    first = np.ones(len(out_node), dtype=bool)
    first[1:] = (out_node[1:] != out_node[:-1]) | (out_lane[1:] != out_lane[:-1])
    return out_node[first], out_lane[first], out_s[first]


def _lane_graph(lanes: Mapping[str, GTLane], index: Mapping[str, int], length_m: np.ndarray) -> csr_matrix:
    """Lane graph with a start node (0..L-1) and an end node (L..2L-1) per lane: start -> end
    weighted with the lane's length, end -> start of each successor ~0 [m]."""
    n = len(index)
    src = list(range(n))
    dst = [n + k for k in range(n)]
    w = list(np.maximum(length_m, _JOINT_M))
    for lid, k in index.items():
        for s in lanes[lid].successors:
            if s in index:
                src.append(n + k)
                dst.append(index[s])
                w.append(_JOINT_M)
    return csr_matrix((w, (src, dst)), shape=(2 * n, 2 * n))


def check_topology_links(
    lanes: Mapping[str, GTLane], topo: TopologyArrays, in_area: np.ndarray, cfg: LinkCheckConfig
) -> LinkPrecision:
    """Judge every edge of the map's topology graph against the ground-truth lane graph.

    Args:
        lanes: the ground truth's lanes (all of them: paths may run through junction lanes).
        topo: the map's topology graph (``TopologyArrays.build`` with ``cfg.node_margin_m``).
        in_area: (N,) bool, the node lies in the evaluated area (inside a cut running its way).

    Returns:
        The counts, the false links and the unevaluable long ones (RULES L1-L4).
        cfg: the settings.
    """
    index = {lid: k for k, lid in enumerate(lanes)}
    lp = _LanePoints.build([lanes[lid].centerline for lid in index])
    n_nodes, src, dst = len(topo.xy), topo.src, topo.dst
    length = np.linalg.norm(topo.xy[dst] - topo.xy[src], axis=1) if len(src) else np.zeros(0)
    row_node, row_lane, row_s = _lanes_under(topo, np.arange(n_nodes), lp, cfg.cos_min)
    start = np.searchsorted(row_node, np.arange(n_nodes))
    count = np.searchsorted(row_node, np.arange(n_nodes), side="right") - start
    a_node, a_lane, a_s = _with_lane_changes(row_node, row_lane, row_s, lanes, index, lp.length_m)
    a_start = np.searchsorted(a_node, np.arange(n_nodes))
    a_count = np.searchsorted(a_node, np.arange(n_nodes), side="right") - a_start
    # RULE L2: an edge is evaluable when both its nodes are on ground-truth lanes and one of them
    # lies in the evaluated area.
    on = count > 0
    evaluable = on[src] & on[dst] & (in_area[src] | in_area[dst]) if len(src) else np.zeros(0, dtype=bool)
    bound = cfg.path_factor * length + cfg.path_slack_m
    best = np.full(len(src), np.nan)
    ev = np.flatnonzero(evaluable)
    if len(ev):
        # Every (lane under A, lane under B) pair of every evaluable edge, edge by edge.
        na, nb = a_count[src[ev]], count[dst[ev]]
        reps = na * nb
        first = np.concatenate([[0], np.cumsum(reps)[:-1]])
        k = np.arange(int(reps.sum())) - np.repeat(first, reps)
        ra = np.repeat(a_start[src[ev]], reps) + k // np.repeat(nb, reps)
        rb = np.repeat(start[dst[ev]], reps) + k % np.repeat(nb, reps)
        la, lb, sa, sb = a_lane[ra], row_lane[rb], a_s[ra], row_s[rb]
        # RULE L3: the shortest lane path from A's station on a lane under A to B's on a lane under B.
        ahead = sb - sa
        same = np.where((la == lb) & (ahead >= -cfg.back_m), np.maximum(ahead, 0.0), np.inf)
        sources, inv = np.unique(la, return_inverse=True)
        n_l = len(index)
        dist = dijkstra(
            _lane_graph(lanes, index, lp.length_m), directed=True, indices=n_l + sources, limit=float(bound[ev].max())
        )
        between = dist[inv, lb]
        other = (lp.length_m[la] - sa) + between + sb
        path = np.minimum(same, other)
        best[ev] = np.minimum.reduceat(path, first)
    supported = evaluable & (np.nan_to_num(best, nan=np.inf) <= bound)
    long_ = length > cfg.long_m

    def why(e: int) -> str:
        off = [
            f"{end} node on no ground-truth lane running its way"
            for end, n in (("from", src[e]), ("to", dst[e]))
            if not on[n]
        ]
        return "; ".join(off) or "both nodes outside the evaluated area"

    def link(e: int, verdict: str, reason: str) -> TopologyLink:
        a, b = int(src[e]), int(dst[e])
        return TopologyLink(
            from_id=int(topo.ids[a]),
            to_id=int(topo.ids[b]),
            x=float(topo.xy[a, 0]),
            y=float(topo.xy[a, 1]),
            to_x=float(topo.xy[b, 0]),
            to_y=float(topo.xy[b, 1]),
            length_m=float(length[e]),
            lane_path_m=float(best[e]),
            verdict=verdict,
            reason=reason,
        )

    false_e = np.flatnonzero(evaluable & ~supported)
    false_links = tuple(
        link(
            int(e),
            "false",
            f"no ground-truth lane path within {bound[e]:.1f} m"
            + (f" (shortest {best[e]:.1f} m)" if np.isfinite(best[e]) else ""),
        )
        for e in false_e[np.argsort(-length[false_e], kind="stable")]
    )
    unev = np.flatnonzero(~evaluable & long_)
    unevaluable_long = tuple(
        link(int(e), "unevaluable", why(int(e))) for e in unev[np.argsort(-length[unev], kind="stable")]
    )
    return LinkPrecision(
        n_links=int(len(src)),
        n_evaluable=int(evaluable.sum()),
        n_supported=int(supported.sum()),
        n_long=int(long_.sum()),
        n_long_evaluable=int((evaluable & long_).sum()),
        n_long_supported=int((supported & long_).sum()),
        false_links=false_links,
        unevaluable_long=unevaluable_long,
        lane_path_m=best,
    )
