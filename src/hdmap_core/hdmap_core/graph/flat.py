"""The flat view of a map graph: every live node and edge of all segment graphs in global indices (Sec. VI).

``FlatGraph`` holds the complete map's hierarchical graph as flat arrays: the topology graph (one
node per used sampling step) and the road-feature graph (one node per aggregated maximum), with
cross references (the feature nodes of topology node ``t`` are ``t_start[t]:t_start[t + 1]``).
``flatten`` builds it from the segment graphs, their alive masks and the links between them; the
linking, loose-end, clean-up and export functions of this package read it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from hdmap_core.graph.segment_graph import SegmentGraph, stable_uid

__all__ = ["FlatGraph", "Link", "flatten", "link_key", "remap", "map_edges", "subset_nodes", "dedupe_uids"]

#: A link between two segment graphs: (graph key, local index) -> (graph key, local index).
Link = tuple[str, int, str, int]


@dataclass
class FlatGraph:
    """All alive nodes and edges of a MapGraph in global indices (graphs in key order).

    Topology arrays (``t_*``) have T rows, feature-node arrays (``n_*``) N rows; positions [m] in
    the map frame, headings [rad]. ``topo_edges`` (E_t, 2) and ``edges`` (E, 2) index them;
    ``leftover`` (E,) marks feature edges that join a split or merge (Sec. V leftover assignment).
    """

    keys: list[str]
    tmap: dict[str, np.ndarray]  # per graph: local topo index -> global or -1
    nmap: dict[str, np.ndarray]  # per graph: local feature node index -> global or -1
    t_graph: np.ndarray
    t_local: np.ndarray
    t_uid: np.ndarray
    t_xy: np.ndarray
    t_heading: np.ndarray
    t_width: np.ndarray
    t_start: np.ndarray
    n_graph: np.ndarray
    n_local: np.ndarray
    n_uid: np.ndarray
    n_xy: np.ndarray
    n_type: np.ndarray
    n_count: np.ndarray
    n_std: np.ndarray
    topo_edges: np.ndarray
    edges: np.ndarray
    leftover: np.ndarray

    @property
    def n_topo(self) -> int:
        return len(self.t_uid)

    @property
    def n_nodes(self) -> int:
        return len(self.n_uid)

    def node_topo(self) -> np.ndarray:
        """(N,) the topology node of each feature node."""
        return np.repeat(np.arange(self.n_topo), np.diff(self.t_start))


def remap(mask: np.ndarray, offset: int) -> np.ndarray:
    """(M,) global index of each masked-in local index (``offset`` upward), -1 for the rest."""
    out = np.full(len(mask), -1, dtype=np.int64)
    out[mask] = offset + np.arange(int(mask.sum()))
    return out


def map_edges(e: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges (E, 2) renumbered by ``m`` (local -> global or -1): the (E', 2) edges with both ends
    kept, and the (E,) bool mask of those kept."""
    if len(e) == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=bool)
    g = m[e]
    ok = (g >= 0).all(axis=1)
    return g[ok], ok


def link_key(flat: FlatGraph, a: int, b: int, *, topo: bool) -> Link:
    """The stored form of a link between global nodes a -> b (topology nodes with ``topo``, else
    feature nodes): (graph key, local index) of each end."""
    if topo:
        return (flat.keys[flat.t_graph[a]], int(flat.t_local[a]), flat.keys[flat.t_graph[b]], int(flat.t_local[b]))
    return (flat.keys[flat.n_graph[a]], int(flat.n_local[a]), flat.keys[flat.n_graph[b]], int(flat.n_local[b]))


def flatten(
    graphs: Mapping[str, SegmentGraph],
    alive: Mapping[str, np.ndarray],
    *,
    node_dead: Mapping[str, np.ndarray],
    topo_links: Iterable[Link] = (),
    feature_links: Iterable[Link] = (),
    branch_links: Iterable[Link] = (),
) -> FlatGraph:
    """The flat view of segment graphs (in key order) and the links between them.

    Args:
        graphs: segment graphs by key.
        alive: per key, (T_k,) bool: topology nodes still in the map (not trimmed).
        node_dead: per key (may lack keys), (N_k,) bool: feature nodes dropped as duplicates.
        topo_links, feature_links: links stitched between graphs.
        branch_links: split/merge feature links across graphs (stored as leftover edges).
    """
    keys = sorted(graphs)
    tmap: dict[str, np.ndarray] = {}
    nmap: dict[str, np.ndarray] = {}
    t_attrs = ("topo_uid", "topo_xy", "topo_heading", "topo_width")
    n_attrs = ("node_uid", "node_xy", "node_type", "node_count", "node_std")
    parts: dict[str, list] = {n: [] for n in ("tg", "tl", "tn", "ng", "nl", "te", "ne", "lo") + t_attrs + n_attrs}
    t_off = n_off = 0
    for gi, k in enumerate(keys):
        g, t_alive = graphs[k], alive[k]
        n_alive = np.repeat(t_alive, np.diff(g.topo_start))
        if k in node_dead:
            n_alive &= ~node_dead[k]
        tmap[k] = remap(t_alive, t_off)
        nmap[k] = remap(n_alive, n_off)
        tl = np.flatnonzero(t_alive)
        nl = np.flatnonzero(n_alive)
        parts["tg"].append(np.full(len(tl), gi))
        parts["tl"].append(tl)
        per_topo = np.diff(g.topo_start)
        if k in node_dead:
            per_topo = np.bincount(np.repeat(np.arange(g.n_topo), per_topo)[n_alive], minlength=g.n_topo)
        parts["tn"].append(per_topo[t_alive])
        parts["ng"].append(np.full(len(nl), gi))
        parts["nl"].append(nl)
        for a in t_attrs:
            parts[a].append(getattr(g, a)[tl])
        for a in n_attrs:
            parts[a].append(getattr(g, a)[nl])
        te, _ = map_edges(g.topo_edges, tmap[k])
        ne, ok = map_edges(g.edges, nmap[k])
        parts["te"].append(te)
        parts["ne"].append(ne)
        parts["lo"].append(g.edge_leftover[ok] if len(ok) else np.zeros(0, dtype=bool))
        t_off += len(tl)
        n_off += len(nl)

    def links(src: Iterable[Link], maps: dict[str, np.ndarray]) -> np.ndarray:
        out = []
        for ka, ia, kb, ib in sorted(src):
            a, b = maps[ka][ia], maps[kb][ib]
            if a >= 0 and b >= 0:
                out.append((a, b))
        return np.asarray(out, dtype=np.int64).reshape(-1, 2)

    def cat(name: str, empty: np.ndarray, dtype=None) -> np.ndarray:
        out = np.concatenate(parts[name]) if parts[name] else empty
        return out.astype(dtype) if dtype is not None else out

    i0 = np.zeros(0, dtype=np.int64)
    f0 = np.zeros(0)
    e0 = np.zeros((0, 2), dtype=np.int64)
    fl = links(feature_links, nmap)
    bl = links(branch_links, nmap)
    return FlatGraph(
        keys=keys,
        tmap=tmap,
        nmap=nmap,
        t_graph=cat("tg", i0),
        t_local=cat("tl", i0),
        t_uid=cat("topo_uid", i0, np.uint64),
        t_xy=cat("topo_xy", np.zeros((0, 2)), float).reshape(-1, 2),
        t_heading=cat("topo_heading", f0, float),
        t_width=cat("topo_width", f0, float),
        t_start=np.concatenate([[0], np.cumsum(cat("tn", i0))]).astype(np.int64),
        n_graph=cat("ng", i0),
        n_local=cat("nl", i0),
        n_uid=cat("node_uid", i0, np.uint64),
        n_xy=cat("node_xy", np.zeros((0, 2)), float).reshape(-1, 2),
        n_type=cat("node_type", i0, np.int64),
        n_count=cat("node_count", i0, np.int64),
        n_std=cat("node_std", f0, float),
        topo_edges=np.concatenate([cat("te", e0).reshape(-1, 2), links(topo_links, tmap)]).astype(np.int64),
        edges=np.concatenate([cat("ne", e0).reshape(-1, 2), fl, bl]).astype(np.int64),
        leftover=np.concatenate(
            [cat("lo", np.zeros(0, dtype=bool)), np.zeros(len(fl), dtype=bool), np.ones(len(bl), dtype=bool)]
        ),
    )


def subset_nodes(flat: FlatGraph, keep: np.ndarray) -> FlatGraph:
    """The flat graph restricted to the kept feature nodes ((N,) bool; topology unchanged)."""
    new_idx = np.full(len(keep), -1, dtype=np.int64)
    new_idx[keep] = np.arange(int(keep.sum()))
    e, ok = map_edges(flat.edges, new_idx)
    leftover = flat.leftover[ok] if len(ok) else flat.leftover
    if len(e):
        # a leftover edge whose sibling branch was pruned no longer joins a split or merge
        outdeg = np.bincount(e[:, 0], minlength=int(keep.sum()))
        indeg = np.bincount(e[:, 1], minlength=int(keep.sum()))
        leftover = leftover & ((outdeg[e[:, 0]] >= 2) | (indeg[e[:, 1]] >= 2))
    per_topo = np.bincount(flat.node_topo()[keep], minlength=flat.n_topo)
    return FlatGraph(
        keys=flat.keys,
        tmap=flat.tmap,
        nmap={k: np.where(v >= 0, new_idx[np.maximum(v, 0)], -1) for k, v in flat.nmap.items()},
        t_graph=flat.t_graph,
        t_local=flat.t_local,
        t_uid=flat.t_uid,
        t_xy=flat.t_xy,
        t_heading=flat.t_heading,
        t_width=flat.t_width,
        t_start=np.concatenate([[0], np.cumsum(per_topo)]).astype(np.int64),
        n_graph=flat.n_graph[keep],
        n_local=flat.n_local[keep],
        n_uid=flat.n_uid[keep],
        n_xy=flat.n_xy[keep],
        n_type=flat.n_type[keep],
        n_count=flat.n_count[keep],
        n_std=flat.n_std[keep],
        topo_edges=flat.topo_edges,
        edges=e,
        leftover=leftover,
    )


def dedupe_uids(flat: FlatGraph) -> np.ndarray:
    """(N,) feature node uids, made unique should two graphs carry the same pivot step (rehashed
    with the key)."""
    uid = flat.n_uid.copy()
    _, first, counts = np.unique(uid, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = np.flatnonzero(np.isin(uid, np.unique(uid)[counts > 1]))
        keep_first = set(first.tolist())
        for i in dup.tolist():
            if i not in keep_first:
                uid[i] = stable_uid(flat.keys[flat.n_graph[i]], int(flat.n_local[i]), 7)[()]
    return uid
