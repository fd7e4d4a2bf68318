"""The hierarchical graph of one segment (Sec. VI of Immel et al. 2023): the data model that the
connection stage (``connection.py``) builds and the stitching stage (``stitching.py``) joins.

A topology graph with one node per used step (road midpoint, heading, width) and a road-feature
graph whose nodes are the maxima and whose edges are the connections; each topology node refers to
its feature nodes and each feature node to its topology node. Also the stable ids of nodes, the
spatial tiles that key map state by place, and the polylines of a feature graph: its maximal
chains that no closing rule cuts (:func:`feature_chains`):

- RULE 1: an edge joining two different types closes the polyline (a new one opens).
- RULE 2: an edge made by the leftover (modified) assignment closes it; splits and merges follow.
- RULE 3: a gap longer than ``max_gap_m`` closes it (no edge is made across the gap).
- RULE 4: a step already processed through another pivot (``StepResult.processed_before``)
  closes it (no edge, the topology chain breaks); stitching (Sec. VI) joins it to the other pivot.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

__all__ = ["ConnectionStats", "SegmentGraph", "stable_uid", "tile_of", "chain_links", "feature_chains"]

_MASK63 = np.uint64((1 << 63) - 1)


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
    malformed: int = 0
    problems: list[str] = field(default_factory=list)


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
        track_step: (S,) int, every step of the pivot with a finite pose, used or not (rejected
            steps and the ends of runs processed before included), increasing: the path the
            pivot drove, which the stitcher's track links follow (empty: not known).
        track_s: (S,) the steps' travelled distances of the pivot (``StepResult.s_m``) [m]; the
            order of the pivot's track over all its graphs (empty: not known, step order).
        track_xy: (S, 2) the steps' cut-line midpoints [m].
        track_heading: (S,) the steps' ENU yaw [rad].
        track_pose: (S, 2) the pivot's own position at each track step (``StepResult.pose``)
            [m]; empty when a step has none (stored before poses were kept).
        track_judged: (S,) bool, the step carries a negative-evidence profile (``StepResult.empty_m``).
        track_empty_start: (S + 1,) offsets into ``track_empty``.
        track_empty: (M, 2) the steps' empty intervals [lo, hi] along their cuts, from the
            midpoint [m] (``hdmap_core.pipeline.evidence``).
        pivot_drive: the drive the pivot is, when ``pivot_id`` is a per-tile name of it (live:
            ``"<drive>#<ix>,<iy>"``, ``incremental.connect_tile``); '' = ``pivot_id``. The graphs
            of one pivot drive hold pieces of one track, ordered by ``track_s``.
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
    track_step: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), compare=False)
    track_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), compare=False)
    track_heading: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False)
    track_pose: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), compare=False)
    track_judged: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool), compare=False)
    track_empty_start: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64), compare=False)
    track_empty: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), compare=False)
    track_s: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False)
    pivot_drive: str = field(default="", compare=False)

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


def stable_uid(name: str, a: np.ndarray | int, b: np.ndarray | int = 0) -> np.ndarray:
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
    n_nodes: int, edges: np.ndarray, leftover: np.ndarray, node_type: np.ndarray, *, through: bool = False
) -> np.ndarray:
    """(E,) bool: which edges continue a polyline (the others close one and open the next).

    Args:
        through: at a split (merge) whose node has exactly one continuing candidate out of
            (into) it -- an edge of its own type not made by the leftover assignment, or, when
            there is none, its one leftover edge of its own type -- that edge still continues
            the polyline (when it is the other node's candidate too): the line runs through the
            junction and only the branch (a leftover or type-changing edge) starts (ends)
            there, on the through line's interior. False (the segment's own polylines, the
            paper): a split or merge closes every polyline meeting there.
    """
    if len(edges) == 0:
        return np.zeros(0, dtype=bool)
    u, v = edges[:, 0], edges[:, 1]
    # RULE 1: an edge joining two different types closes the polyline;
    # RULE 2: an edge made by the leftover (modified) assignment closes it
    same = node_type[u] == node_type[v]
    lo = np.asarray(leftover, dtype=bool)
    cand = same & ~lo
    if through:
        # each node continues in its one regular edge of its type, or, when it has none, in its
        # one leftover edge of its type (an entry's solid line merging where the dashed line
        # changes to solid: the solid tip's leftover edge is the line's only continuation)
        def chosen(ends: np.ndarray) -> np.ndarray:
            n_reg = np.bincount(ends[cand], minlength=n_nodes)
            n_lo = np.bincount(ends[same & lo], minlength=n_nodes)
            return (cand & (n_reg[ends] == 1)) | (same & lo & (n_reg[ends] == 0) & (n_lo[ends] == 1))

        return chosen(u) & chosen(v)
    else:
        out_deg = np.bincount(u, minlength=n_nodes)
        in_deg = np.bincount(v, minlength=n_nodes)
    # a split (two successors) and a merge (two predecessors) close the polyline
    return cand & (out_deg[u] == 1) & (in_deg[v] == 1)
    # RULE 3 and RULE 4 make no edge at all (see connect_segment), so nothing continues there.


def feature_chains(
    n_nodes: int,
    edges: np.ndarray,
    leftover: np.ndarray,
    node_type: np.ndarray,
    node_uid: np.ndarray,
    *,
    through: bool = False,
) -> list[np.ndarray]:
    """Split a feature graph into polylines (maximal chains of continuing edges).

    Args:
        n_nodes: number of nodes N.
        edges: (E, 2) int (from, to).
        leftover: (E,) bool, leftover edges (RULE 2).
        node_type: (N,) int type codes.
        node_uid: (N,) uint64 node ids; a closed ring is opened at its smallest id so the result
            does not depend on node order.
        through: see ``chain_links``.

    Returns:
        Chains of node indices in driving direction, ordered by the uid of their first node.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    link = chain_links(n_nodes, edges, leftover, node_type, through=through)
    nxt = np.full(n_nodes, -1, dtype=np.int64)
    has_prev = np.zeros(n_nodes, dtype=bool)
    nxt[edges[link, 0]] = edges[link, 1]
    has_prev[edges[link, 1]] = True
    # list ranking by pointer doubling: each node's distance to the end of its chain and that end
    dist = (nxt >= 0).astype(np.int64)
    ptr = nxt.copy()
    end = np.where(nxt >= 0, nxt, np.arange(n_nodes))
    for _ in range(max(1, int(n_nodes).bit_length() + 1)):
        live = ptr >= 0
        if not live.any():
            break
        p = ptr[live]
        dist[live] += dist[p]
        end[live] = end[p]
        ptr[live] = ptr[p]
    on_chain = ptr < 0  # nodes still pointing on are on a ring
    chains: list[np.ndarray] = []
    idx = np.flatnonzero(on_chain)
    if len(idx):
        order = idx[np.lexsort((-dist[idx], end[idx]))]
        cut = np.flatnonzero(np.diff(end[order])) + 1
        chains = np.split(order, cut)
    rest = np.flatnonzero(~on_chain)
    if len(rest):  # rings (a closed loop road): open each at its smallest uid
        seen = np.zeros(n_nodes, dtype=bool)
        nxt_l = nxt.tolist()
        for s0 in rest[np.argsort(node_uid[rest], kind="stable")].tolist():
            if seen[s0]:
                continue
            out = [s0]
            seen[s0] = True
            j = nxt_l[s0]
            while j >= 0 and not seen[j]:
                out.append(j)
                seen[j] = True
                j = nxt_l[j]
            chains.append(np.asarray(out, dtype=np.int64))
    chains.sort(key=lambda c: int(node_uid[c[0]]))
    return chains
