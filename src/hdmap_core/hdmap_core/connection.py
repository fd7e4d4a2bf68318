"""Connection of distribution maxima along one pivot drive (Sec. V of Immel et al. 2023).

The aggregated maxima of consecutive sampling steps are joined by a rectangular linear assignment
(``scipy.optimize.linear_sum_assignment``, Karp 1980); nodes left over at splits and merges are
joined to their nearest neighbour on the other side (the paper's modified assignment). Steps whose
mean connection angle is implausible are rejected, road borders never connect to another type, and
steps without a result are bridged when the gap to the next valid step is short.

The result is a :class:`SegmentGraph`: the hierarchical graph of one segment (Sec. VI), a topology
graph with one node per used step (road midpoint, heading, width) and a road-feature graph whose
nodes are the maxima and whose edges are the connections. Each topology node refers to its feature
nodes and each feature node to its topology node. Polylines are the maximal chains of the feature
graph that no closing rule cuts (:func:`feature_chains`):

- RULE 1: an edge joining two different types closes the polyline (a new one opens).
- RULE 2: an edge made by the leftover (modified) assignment closes it; splits and merges follow.
- RULE 3: a gap longer than ``max_gap_m`` closes it (no edge is made across the gap).
- RULE 4: a step already processed through another pivot (``StepResult.processed_before``)
  closes it (no edge, the topology chain breaks); stitching (Sec. VI) joins it to the other pivot.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.model import FeatureType
from hdmap_core.steps import Segment, StepResult, left_normal

__all__ = [
    "ConnectionConfig",
    "ConnectionStats",
    "SegmentGraph",
    "connect_segment",
    "feature_chains",
    "stable_uid",
    "tile_of",
]

_BORDER = int(FeatureType.ROAD_BORDER)
_BIG = 1.0e9
_GATE = 1.0e4  # cost added to a pair beyond the edge limits: taken only when nothing else is left
_MASK63 = np.uint64((1 << 63) - 1)


@dataclass(frozen=True)
class ConnectionConfig:
    """Parameters of the connection stage (the paper gives none of these numbers).

    Attributes:
        max_gap_m: steps without a result are bridged when the pivot travelled at most this far
            between two valid steps; a longer gap closes every polyline (RULE 3) [m].
        max_mean_angle_deg: a step whose assigned connections have a mean angle (to the heading)
            above this is rejected as an implausible optimisation result and bridged [deg].
        robust_angle: judge a step by the median connection angle instead of the mean, so that
            one feature leaving the cut while another enters does not reject a good step.
        max_edge_angle_deg: a single connection steeper than this is not made; 90 disables [deg].
        edge_slack_m: lateral slack added to the edge angle limit (noise of the maxima) [m].
        leftover_max_m: a leftover node is joined to its nearest neighbour only when that is at
            most this far across the cut; ``inf`` joins every leftover, as in the paper [m].
        bridge_features: keep a polyline whose feature is missing in a step open for ``max_gap_m``
            so that it continues when the feature reappears (per-feature gap bridging; the paper
            bridges whole steps only).
        min_separation_m: two lane markings (or two road borders) of one step closer than this
            are one feature seen twice (typically a misclassified cluster the overlap filter
            kept); only the one with more drives is used. 0 disables (the paper) [m].
        tile_size_m: edge of the square tiles that key topology nodes by place [m].
    """

    max_gap_m: float = 20.0
    max_mean_angle_deg: float = 15.0
    robust_angle: bool = True
    max_edge_angle_deg: float = 35.0
    edge_slack_m: float = 0.3
    leftover_max_m: float = 2.0
    bridge_features: bool = True
    min_separation_m: float = 1.0
    tile_size_m: float = 256.0

    def __post_init__(self) -> None:
        if not self.max_gap_m >= 0:
            raise ConfigError(f"max_gap_m must be >= 0, got {self.max_gap_m}")
        for name in ("max_mean_angle_deg", "max_edge_angle_deg"):
            v = getattr(self, name)
            if not 0 < v <= 90:
                raise ConfigError(f"{name} must be in (0, 90], got {v}")
        if not self.edge_slack_m >= 0:
            raise ConfigError(f"edge_slack_m must be >= 0, got {self.edge_slack_m}")
        if not self.min_separation_m >= 0:
            raise ConfigError(f"min_separation_m must be >= 0, got {self.min_separation_m}")
        if not self.leftover_max_m >= 0:
            raise ConfigError(f"leftover_max_m must be >= 0, got {self.leftover_max_m}")
        if not (self.tile_size_m > 0 and math.isfinite(self.tile_size_m)):
            raise ConfigError(f"tile_size_m must be > 0, got {self.tile_size_m}")

    @classmethod
    def paper(cls) -> ConnectionConfig:
        """The paper's variant: every leftover joined, no per-edge limit, whole-step bridging only."""
        return cls(
            max_edge_angle_deg=90.0,
            leftover_max_m=math.inf,
            bridge_features=False,
            robust_angle=False,
            min_separation_m=0.0,
        )


@dataclass
class ConnectionStats:
    """Counts of what the connection stage did with the steps of one segment."""

    steps: int = 0
    used: int = 0
    invalid: int = 0
    processed_before: int = 0
    rejected_angle: int = 0
    gaps_bridged: int = 0
    gaps_closed: int = 0
    splits: int = 0
    merges: int = 0
    suppressed: int = 0


@dataclass(frozen=True)
class SegmentGraph:
    """The hierarchical graph of one segment (or of a whole map, see ``stitching``).

    Feature nodes are stored grouped by topology node, in step order: the feature nodes of topology
    node ``t`` are ``topo_start[t]:topo_start[t + 1]``.

    Attributes:
        key: stable name of the segment, ``"<pivot_id>@<first step index>"``.
        pivot_id: drive id of the pivot.
        topo_uid: (T,) uint64 stable id of each topology node (< 2**63).
        topo_step: (T,) int step index of each topology node.
        topo_xy: (T, 2) road midpoint [m].
        topo_heading: (T,) ENU yaw [rad].
        topo_width: (T,) ego-road width [m].
        topo_edges: (Et, 2) int, topology edges (from, to), local indices.
        topo_start: (T + 1,) int offsets into the feature nodes.
        node_uid: (N,) uint64 stable id of each feature node (< 2**63); a polyline is named by
            the uid of its first node.
        node_xy: (N, 2) world point of each maximum [m].
        node_type: (N,) int FeatureType code.
        node_count: (N,) int drives supporting the maximum.
        node_std: (N,) float 1-sigma lateral uncertainty [m].
        edges: (E, 2) int feature-graph edges (from, to), in driving direction.
        edge_leftover: (E,) bool, edge made by the leftover assignment (RULE 2).
        drive_ids: drives that took part in any used step.
        stats: what happened to the steps.
    """

    key: str
    pivot_id: str
    topo_uid: np.ndarray
    topo_step: np.ndarray
    topo_xy: np.ndarray
    topo_heading: np.ndarray
    topo_width: np.ndarray
    topo_edges: np.ndarray
    topo_start: np.ndarray
    node_uid: np.ndarray
    node_xy: np.ndarray
    node_type: np.ndarray
    node_count: np.ndarray
    node_std: np.ndarray
    edges: np.ndarray
    edge_leftover: np.ndarray
    drive_ids: tuple[str, ...] = ()
    stats: ConnectionStats = field(default_factory=ConnectionStats, compare=False)
    tile_size_m: float = 256.0

    @property
    def n_topo(self) -> int:
        return len(self.topo_uid)

    @property
    def n_nodes(self) -> int:
        return len(self.node_uid)

    @property
    def node_topo(self) -> np.ndarray:
        """(N,) int: the topology node of each feature node (the cross reference)."""
        return np.repeat(np.arange(self.n_topo), np.diff(self.topo_start))

    @property
    def topo_tile(self) -> np.ndarray:
        """(T, 2) int tile key (ix, iy) of each topology node."""
        return tile_of(self.topo_xy, tile_size_m=self.tile_size_m)

    def features_of(self, t: int) -> np.ndarray:
        """Feature node indices of topology node ``t``."""
        return np.arange(self.topo_start[t], self.topo_start[t + 1])

    def polylines(self) -> list[np.ndarray]:
        """The polylines of this segment: node index chains in driving direction."""
        return feature_chains(self.n_nodes, self.edges, self.edge_leftover, self.node_type, self.node_uid)

    def components(self) -> list[np.ndarray]:
        """Connected components of the topology graph, each as topology node indices in order."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        if self.n_topo == 0:
            return []
        e = self.topo_edges
        adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(self.n_topo, self.n_topo))
        _, labels = connected_components(adj, directed=True, connection="weak")
        order = np.argsort(labels, kind="stable")
        splits = np.flatnonzero(np.diff(labels[order])) + 1
        return [np.sort(c) for c in np.split(order, splits)]


# --- ids and places ----------------------------------------------------------------------------


def _splitmix64(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.uint64)
    with np.errstate(over="ignore"):
        x = x + np.uint64(0x9E3779B97F4A7C15)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def stable_uid(name: str, a: np.ndarray, b: np.ndarray | int = 0) -> np.ndarray:
    """Stable 63-bit ids from a name and two integer keys (e.g. pivot id, step index, slot).

    The same inputs give the same ids on every run and machine (no Python ``hash``).

    Returns:
        uint64 array of the broadcast shape of ``a`` and ``b``, every value in [1, 2**63).
    """
    h0 = np.uint64(int.from_bytes(hashlib.blake2b(name.encode(), digest_size=8).digest(), "little"))
    a = np.asarray(a, dtype=np.int64).astype(np.uint64)
    b = np.asarray(b, dtype=np.int64).astype(np.uint64)
    with np.errstate(over="ignore"):
        x = _splitmix64(h0 ^ _splitmix64(a * np.uint64(0x100000001B3) + b))
    x = x & _MASK63
    return np.where(x == 0, np.uint64(1), x)


def tile_of(xy: np.ndarray, *, tile_size_m: float = 256.0) -> np.ndarray:
    """(N, 2) points [m] -> (N, 2) int tile keys ``(floor(x / size), floor(y / size))``."""
    return np.floor(np.asarray(xy, dtype=float).reshape(-1, 2) / tile_size_m).astype(np.int64)


# --- polylines from the feature graph ------------------------------------------------------------


def chain_links(
    n_nodes: int, edges: np.ndarray, leftover: np.ndarray, node_type: np.ndarray
) -> np.ndarray:
    """(E,) bool: which edges continue a polyline (the others close one and open the next)."""
    if len(edges) == 0:
        return np.zeros(0, dtype=bool)
    out_deg = np.bincount(edges[:, 0], minlength=n_nodes)
    in_deg = np.bincount(edges[:, 1], minlength=n_nodes)
    u, v = edges[:, 0], edges[:, 1]
    return (
        (out_deg[u] == 1)  # a split (two successors) closes the polyline
        & (in_deg[v] == 1)  # a merge (two predecessors) closes the polyline
        # RULE 1: the edge joins two different types
        & (node_type[u] == node_type[v])
        # RULE 2: the edge was made by the leftover (modified) assignment
        & ~np.asarray(leftover, dtype=bool)
    )
    # RULE 3 and RULE 4 make no edge at all (see connect_segment), so nothing continues there.


def feature_chains(
    n_nodes: int,
    edges: np.ndarray,
    leftover: np.ndarray,
    node_type: np.ndarray,
    node_uid: np.ndarray,
) -> list[np.ndarray]:
    """Split a feature graph into polylines (maximal chains of continuing edges).

    Args:
        n_nodes: number of nodes N.
        edges: (E, 2) int (from, to).
        leftover: (E,) bool, leftover edges (RULE 2).
        node_type: (N,) int type codes.
        node_uid: (N,) uint64 node ids; a closed ring is opened at its smallest id so the result
            does not depend on node order.

    Returns:
        Chains of node indices in driving direction, ordered by the uid of their first node.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    link = chain_links(n_nodes, edges, leftover, node_type)
    nxt = np.full(n_nodes, -1, dtype=np.int64)
    has_prev = np.zeros(n_nodes, dtype=bool)
    nxt[edges[link, 0]] = edges[link, 1]
    has_prev[edges[link, 1]] = True
    seen = np.zeros(n_nodes, dtype=bool)
    nxt_l = nxt.tolist()
    chains: list[np.ndarray] = []

    def walk(start: int) -> None:
        out = [start]
        seen[start] = True
        j = nxt_l[start]
        while j >= 0 and not seen[j]:
            out.append(j)
            seen[j] = True
            j = nxt_l[j]
        chains.append(np.asarray(out, dtype=np.int64))

    for s in np.flatnonzero(~has_prev).tolist():
        walk(s)
    rest = np.flatnonzero(~seen)
    if len(rest):  # rings (a closed loop road): open each at its smallest uid
        for s in rest[np.argsort(node_uid[rest], kind="stable")].tolist():
            if not seen[s]:
                walk(s)
    chains.sort(key=lambda c: int(node_uid[c[0]]))
    return chains


# --- the connection of one segment ----------------------------------------------------------------


def _check_step(st: StepResult) -> None:
    k = np.shape(st.lateral_m)
    for name in ("types", "counts", "std_m"):
        if np.shape(getattr(st, name)) != k:
            raise HdmapError(
                f"step {st.index} of pivot {st.pivot_id!r}: {name} has shape {np.shape(getattr(st, name))}, "
                f"lateral_m has {k}"
            )
    if np.shape(st.midpoint) != (2,) or not np.all(np.isfinite(st.midpoint)) or not math.isfinite(st.heading):
        raise HdmapError(f"step {st.index} of pivot {st.pivot_id!r}: midpoint/heading missing or not finite")


def _separate(lat: np.ndarray, types: np.ndarray, counts: np.ndarray, min_sep_m: float) -> np.ndarray | None:
    """Indices of the maxima to keep when markings (or borders) of one step lie closer than
    ``min_sep_m``: the better supported one wins. None: keep all (the common case, no copy)."""
    if min_sep_m <= 0 or len(lat) < 2:
        return None
    border = types == _BORDER
    close = False
    for cls in (border, ~border):
        v = np.sort(lat[cls])
        if len(v) > 1 and np.diff(v).min() < min_sep_m:
            close = True
    if not close:
        return None
    order = np.lexsort((np.abs(lat), -counts))  # most drives first, then nearest the midpoint
    kept: list[int] = []
    for i in order.tolist():
        if all(border[i] != border[j] or abs(lat[i] - lat[j]) >= min_sep_m for j in kept):
            kept.append(i)
    return np.sort(np.asarray(kept, dtype=np.int64))


@dataclass
class _Assignment:
    regular: list[tuple[int, int]]
    leftover: list[tuple[int, int]]
    mean_angle_deg: float


def _assign(
    tip_xy: np.ndarray,
    tip_type: np.ndarray,
    tip_fresh: np.ndarray,
    new_xy: np.ndarray,
    new_type: np.ndarray,
    heading: float,
    config: ConnectionConfig,
) -> _Assignment:
    """Modified rectangular assignment between open polyline ends (tips) and a step's maxima.

    The cost is the point distance across the cut of the new step (for consecutive steps it ranks
    pairs as the Euclidean distance does, and it stays comparable across bridged gaps).
    """
    d = new_xy[None, :, :] - tip_xy[:, None, :]
    u = np.array([math.cos(heading), math.sin(heading)])
    along = d @ u
    lat = np.abs(d @ left_normal(heading))
    # never connect a road border to another type
    forbidden = (tip_type[:, None] == _BORDER) != (new_type[None, :] == _BORDER)
    tan_max = math.tan(math.radians(min(config.max_edge_angle_deg, 89.999)))
    plausible = (along > 0.0) & (lat <= config.edge_slack_m + np.maximum(along, 0.0) * tan_max)
    ok = plausible & ~forbidden

    n, m = lat.shape
    rows = cols = np.zeros(0, dtype=np.int64)
    if config.max_edge_angle_deg < 90.0:
        cost = np.where(forbidden, _BIG, np.where(plausible, lat, _GATE + lat))
    else:  # the paper's variant: plain point distances
        cost = np.where(forbidden, _BIG, lat)
    if n and m:
        if n == m and bool(tip_fresh.all()):
            # In 1-D the sorted pairing is the exact optimum of the assignment for |a - b| costs.
            lt = tip_xy @ left_normal(heading)
            ln = new_xy @ left_normal(heading)
            rows, cols = np.argsort(lt, kind="stable"), np.argsort(ln, kind="stable")
            if not ok[rows, cols].all():
                rows, cols = linear_sum_assignment(cost)
        else:
            rows, cols = linear_sum_assignment(cost)
    # the plausibility of the step is judged on the assignment as solved (before edge limits)
    allowed = ~forbidden[rows, cols]
    angles = np.degrees(np.arctan2(lat[rows, cols], np.abs(along[rows, cols]) + 1e-9))[allowed]
    if len(angles) == 0:
        mean_angle = 0.0
    else:
        mean_angle = float(np.median(angles) if config.robust_angle else angles.mean())
    keep = ok[rows, cols]
    rows, cols = rows[keep], cols[keep]

    # the paper's modification: leftovers join their nearest neighbour on the other side
    leftover: list[tuple[int, int]] = []
    near = ok & (lat <= config.leftover_max_m)
    matched_new = np.zeros(m, dtype=bool)
    matched_new[cols] = True
    matched_tip = np.zeros(n, dtype=bool)
    matched_tip[rows] = True
    fresh_near = near & tip_fresh[:, None]
    for j in np.flatnonzero(~matched_new):  # split: a new node without a partner
        cand = np.flatnonzero(fresh_near[:, j])
        if len(cand):
            leftover.append((int(cand[np.argmin(lat[cand, j])]), int(j)))
    for i in np.flatnonzero(~matched_tip & tip_fresh):  # merge: an old node without a partner
        cand = np.flatnonzero(near[i, :])
        if len(cand):
            leftover.append((int(i), int(cand[np.argmin(lat[i, cand])])))
    regular = list(zip(rows.tolist(), cols.tolist()))
    return _Assignment(regular=regular, leftover=leftover, mean_angle_deg=mean_angle)


class _Builder:
    """Accumulates the arrays of a SegmentGraph."""

    def __init__(self) -> None:
        self.topo: list[StepResult] = []
        self.topo_edges: list[tuple[int, int]] = []
        self.starts = [0]
        self.xy: list[np.ndarray] = []
        self.slots: list[np.ndarray] = []
        self.edges: list[tuple[int, int]] = []
        self.leftover: list[bool] = []
        self.n = 0

    def add_step(self, st: StepResult, xy: np.ndarray, slots: np.ndarray) -> np.ndarray:
        idx = np.arange(self.n, self.n + len(xy))
        self.topo.append(st)
        self.xy.append(xy)
        self.slots.append(slots)  # index into the step's own arrays: the stable slot
        self.n += len(xy)
        self.starts.append(self.n)
        return idx


def connect_segment(segment: Segment, *, config: ConnectionConfig = ConnectionConfig()) -> SegmentGraph:
    """Connect the aggregated maxima of one pivot drive into polylines (Sec. V).

    Args:
        segment: the pivot's steps (any order; sorted by ``index`` here; not modified).
        config: connection parameters.

    Returns:
        The segment's hierarchical graph. Steps that are invalid, processed before, or rejected
        by the angle check get no topology node.

    Raises:
        HdmapError: a step's arrays disagree in length, its midpoint/heading is not finite, or a
            step belongs to another pivot.
    """
    steps = sorted(segment.steps, key=lambda s: s.index)
    for st in steps:
        if st.pivot_id != segment.pivot_id:
            raise HdmapError(f"segment {segment.pivot_id!r} holds a step of pivot {st.pivot_id!r}")
        _check_step(st)
    stats = ConnectionStats(steps=len(steps))
    b = _Builder()
    tip_idx = np.zeros(0, dtype=np.int64)  # open polyline ends: node index ...
    tip_s = np.zeros(0)  # ... the pivot distance of their step, their point and type
    tip_xy = np.zeros((0, 2))
    tip_type = np.zeros(0, dtype=np.int64)
    last_topo: int | None = None
    last_s = 0.0
    skipped = False
    drive_ids: set[str] = set()

    for st in steps:
        if st.processed_before:
            # RULE 4: a section already processed by another pivot closes every polyline
            stats.processed_before += 1
            tip_idx, tip_s, tip_xy, tip_type, last_topo = tip_idx[:0], tip_s[:0], tip_xy[:0], tip_type[:0], None
            continue
        lat = np.asarray(st.lateral_m, dtype=float).reshape(-1)
        if not st.valid or len(lat) == 0 or not np.all(np.isfinite(lat)):
            stats.invalid += 1
            skipped = True
            continue
        types = np.asarray(st.types, dtype=np.int64).reshape(-1)
        sel = _separate(lat, types, np.asarray(st.counts).reshape(-1), config.min_separation_m)
        if sel is not None:
            st = replace(
                st,
                lateral_m=lat[sel],
                types=types[sel],
                counts=np.asarray(st.counts).reshape(-1)[sel],
                std_m=np.asarray(st.std_m, dtype=float).reshape(-1)[sel],
            )
            stats.suppressed += len(lat) - len(sel)
            types = types[sel]
        xy = st.points()
        gap = st.s_m - last_s
        new_edges: list[tuple[int, int, bool]] = []
        if last_topo is not None and gap > config.max_gap_m:
            # RULE 3: the gap to the last valid step exceeds the threshold: close everything
            stats.gaps_closed += 1
            tip_idx, tip_s, tip_xy, tip_type, last_topo = tip_idx[:0], tip_s[:0], tip_xy[:0], tip_type[:0], None
        if last_topo is not None:
            live = (st.s_m - tip_s) <= config.max_gap_m  # RULE 3 per polyline (bridged features)
            tip_idx, tip_s, tip_xy, tip_type = tip_idx[live], tip_s[live], tip_xy[live], tip_type[live]
            fresh = tip_s == last_s
            res = _assign(tip_xy, tip_type, fresh, xy, types, st.heading, config)
            if res.mean_angle_deg > config.max_mean_angle_deg:
                stats.rejected_angle += 1  # implausible optimisation result: treat as a gap
                skipped = True
                continue
            base = b.n
            new_edges = [(int(tip_idx[i]), base + j, False) for i, j in res.regular]
            new_edges += [(int(tip_idx[i]), base + j, True) for i, j in res.leftover]
            if skipped:
                stats.gaps_bridged += 1
        idx = b.add_step(st, xy, sel if sel is not None else np.arange(len(xy)))
        t = len(b.topo) - 1
        if last_topo is not None:
            b.topo_edges.append((last_topo, t))
        for u, v, lo in new_edges:
            b.edges.append((u, v))
            b.leftover.append(lo)
        matched = np.zeros(len(tip_idx), dtype=bool)
        if new_edges:
            used = {u for u, _, _ in new_edges}
            matched = np.isin(tip_idx, list(used))
        keep_old = ~matched if config.bridge_features else np.zeros(len(tip_idx), dtype=bool)
        tip_idx = np.concatenate([tip_idx[keep_old], idx])
        tip_s = np.concatenate([tip_s[keep_old], np.full(len(idx), st.s_m)])
        tip_xy = np.concatenate([tip_xy[keep_old], xy])
        tip_type = np.concatenate([tip_type[keep_old], types])
        last_topo, last_s, skipped = t, st.s_m, False
        stats.used += 1
        drive_ids.update(st.drive_ids)

    return _finish(segment, b, stats, drive_ids, config)


def _finish(
    segment: Segment, b: _Builder, stats: ConnectionStats, drive_ids: set[str], config: ConnectionConfig
) -> SegmentGraph:
    first = b.topo[0].index if b.topo else (segment.steps[0].index if segment.steps else 0)
    steps = np.array([t.index for t in b.topo], dtype=np.int64)
    starts = np.asarray(b.starts, dtype=np.int64)
    node_step = np.repeat(steps, np.diff(starts))
    slots = np.concatenate(b.slots) if b.slots else np.zeros(0, dtype=np.int64)
    edges = np.asarray(b.edges, dtype=np.int64).reshape(-1, 2)
    n = b.n
    if len(edges):
        out_deg = np.bincount(edges[:, 0], minlength=n)
        in_deg = np.bincount(edges[:, 1], minlength=n)
        stats.splits = int((out_deg >= 2).sum())
        stats.merges = int((in_deg >= 2).sum())

    def cat(name: str, dtype: type) -> np.ndarray:
        if not b.topo:
            return np.zeros(0, dtype=dtype)
        return np.concatenate([np.asarray(getattr(t, name), dtype=dtype).reshape(-1) for t in b.topo])

    return SegmentGraph(
        key=f"{segment.pivot_id}@{first}",
        pivot_id=segment.pivot_id,
        topo_uid=stable_uid("topo:" + segment.pivot_id, steps),
        topo_step=steps,
        topo_xy=np.array([np.asarray(t.midpoint, dtype=float) for t in b.topo]).reshape(-1, 2),
        topo_heading=np.array([float(t.heading) for t in b.topo]),
        topo_width=np.array([float(t.width_m) for t in b.topo]),
        topo_edges=np.asarray(b.topo_edges, dtype=np.int64).reshape(-1, 2),
        topo_start=starts,
        node_uid=stable_uid("feature:" + segment.pivot_id, node_step, slots),
        node_xy=np.concatenate(b.xy) if b.xy else np.zeros((0, 2)),
        node_type=cat("types", np.int64),
        node_count=cat("counts", np.int64),
        node_std=cat("std_m", float),
        edges=edges,
        edge_leftover=np.asarray(b.leftover, dtype=bool),
        drive_ids=tuple(sorted(drive_ids)),
        stats=stats,
        tile_size_m=config.tile_size_m,
    )
