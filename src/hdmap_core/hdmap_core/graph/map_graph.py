"""Inter-segment connection: segments stitched into the complete hierarchical map (Sec. VI).

Immel et al. 2023 keep the map as a hierarchical graph: a topology graph with one node per sampling
step (road midpoint, heading, width) and a road-feature graph of polylines, each referring to the
other. Every segment (one pivot drive, :class:`~hdmap_core.graph.segment_graph.SegmentGraph`) carries such a
graph; :class:`MapGraph` holds the complete one and inserts segments as the paper describes:

1. the segment's topology graph is split into connected components (breaks come from RULE 3/4);
2. the start and end node of each component look up their nearest neighbours in the complete
   topology graph with a kd-tree (``scipy.spatial.cKDTree``);
3. a neighbour is accepted by a distance, heading and connection-angle check;
4. the topology nodes are linked, and the feature nodes they refer to are joined by the
   unmodified rectangular assignment, same type only.

The same mechanism updates an existing map with newly mapped sections: ``MapGraph.integrate``
adds segment graphs and replaces the graphs of re-estimated segments (keyed by segment key, or
by place via ``keys_in_tiles``); ``rebuild`` makes the map a function of the set of segment
graphs. Beyond the paper (each switchable in :class:`StitchConfig`, all off in
``StitchConfig.paper()``): component ends that duplicate a place already in the map are trimmed,
spurs and bubbles pruned, dangling ends running on another segment's line deduplicated, loose ends
that continue each other joined (gaps filled on a Hermite curve), and, at export
(``hdmap_core.graph.flat``), type flicker smoothed, gore splits placed at the lane line's end and
isolated specks dropped.

Helpers: ``stitching_config.py`` (:class:`StitchConfig`), ``stitching_links.py`` (partners of
component ends, the arc search), ``stitching_ends.py`` (loose-end de-duplication and joins, a mixin
of :class:`MapGraph`), ``graph.py`` (the flat view of all graphs and the export).

Feature ids are the stable uid of a polyline's first feature node (hash of pivot id, step index and
slot), so the same input gives the same ids and adding an unrelated segment changes none.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from hdmap_core.errors import HdmapError
from hdmap_core.pipeline.evidence import refuted_edges
from hdmap_core.graph.flat import (
    FlatGraph,
    _dedupe_uids,
    _map_edges,
    _remap,
    _spur_free,
    _unit,
    export_map,
    graph_from_hdmap,
)
from hdmap_core.model import HDMap
from hdmap_core.graph.segment_graph import SegmentGraph
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.graph.loose_ends import LooseEnds
from hdmap_core.graph.links import (
    _PATH_STEP_M,
    _Adjacency,
    _closes_cycle,
    _heading_rate,
    _partner,
    _path_partner,
    _reached_within,
    _track_bridges,
    _track_partner,
    _UnionFind,
)

__all__ = ["StitchConfig", "MapGraph", "stitch", "to_hdmap", "graph_from_hdmap"]

_BIG = 1.0e9
_GATE = 1.0e4
_BORDER_CODE = 3  # FeatureType.ROAD_BORDER

Link = tuple[str, int, str, int]  # (graph key, local index) -> (graph key, local index)


# --- the complete map graph ---------------------------------------------------------------------------


@dataclass
class IntegrateReport:
    """What one ``MapGraph.integrate`` call did."""

    added: int = 0
    removed: int = 0
    trimmed_nodes: int = 0
    topology_links: int = 0
    feature_links: int = 0
    pruned_nodes: int = 0
    deduplicated_nodes: int = 0
    loose_ends_joined: int = 0
    branches_joined: int = 0
    path_links: int = 0
    track_links: int = 0
    bridge_links: int = 0


class MapGraph(LooseEnds):
    """The complete hierarchical map graph, built from segment graphs and kept up to date.

    State is keyed by segment key (``SegmentGraph.key``) and, through the topology nodes' tiles,
    by place; links between segments are stored by (segment key, local index), so replacing a
    segment drops exactly its own nodes and links.

    Args:
        graphs: segment graphs to integrate right away.
        config: stitching parameters.
    """

    def __init__(self, graphs: Iterable[SegmentGraph] = (), *, config: StitchConfig = StitchConfig()) -> None:
        self.config = config
        self._graphs: dict[str, SegmentGraph] = {}
        self._alive: dict[str, np.ndarray] = {}
        self._node_dead: dict[str, np.ndarray] = {}  # feature nodes dropped as duplicates
        self._topo_links: set[Link] = set()
        self._feature_links: set[Link] = set()
        self._branch_links: set[Link] = set()  # split/merge joins (leftover-like: a branch)
        self.version = 0
        self.last_report = IntegrateReport()
        graphs = list(graphs)
        if graphs:
            self.integrate(graphs)

    # -- queries --
    @property
    def keys(self) -> list[str]:
        return sorted(self._graphs)

    def graph(self, key: str) -> SegmentGraph:
        return self._graphs[key]

    def keys_in_tiles(self, tiles: Iterable[tuple[int, int]]) -> set[str]:
        """Keys of the segment graphs with a topology node in any of ``tiles`` ((ix, iy) keys)."""
        want = {(int(a), int(b)) for a, b in tiles}
        out = set()
        for key, g in self._graphs.items():
            if g.n_topo and want & set(map(tuple, g.topo_tile.tolist())):
                out.add(key)
        return out

    def copy(self) -> MapGraph:
        """An independent copy (segment graphs are immutable and shared)."""
        new = MapGraph(config=self.config)
        new._graphs = dict(self._graphs)
        new._alive = {k: v.copy() for k, v in self._alive.items()}
        new._node_dead = {k: v.copy() for k, v in self._node_dead.items()}
        new._topo_links = set(self._topo_links)
        new._feature_links = set(self._feature_links)
        new._branch_links = set(self._branch_links)
        new.version = self.version
        new.last_report = self.last_report
        return new

    @classmethod
    def from_hdmap(cls, hdmap: HDMap, *, config: StitchConfig = StitchConfig()) -> MapGraph:
        """A map graph holding an existing map (as one graph keyed ``"base"``), ids preserved."""
        mg = cls(config=config)
        g = graph_from_hdmap(hdmap)
        mg._graphs[g.key] = g
        mg._alive[g.key] = np.ones(g.n_topo, dtype=bool)
        mg.version = int(hdmap.version)
        return mg

    # -- updates --
    def remove(self, keys: Iterable[str]) -> int:
        """Drop segment graphs (and every link touching them); returns how many were present."""
        gone = {k for k in keys if k in self._graphs}
        for k in gone:
            del self._graphs[k]
            del self._alive[k]
            self._node_dead.pop(k, None)
        if gone:
            self._topo_links = {ln for ln in self._topo_links if ln[0] not in gone and ln[2] not in gone}
            self._feature_links = {ln for ln in self._feature_links if ln[0] not in gone and ln[2] not in gone}
            self._branch_links = {ln for ln in self._branch_links if ln[0] not in gone and ln[2] not in gone}
        return len(gone)

    def rebuild(self) -> IntegrateReport:
        """Forget every trim, dedupe and link and stitch all segment graphs afresh (in key order).

        After ``rebuild`` the map is a function of the set of segment graphs only, whatever the
        order in which they were integrated (``integrate`` trims and links only what changed).
        """
        graphs = [self._graphs[k] for k in self.keys]
        version = self.version
        self._graphs, self._alive, self._node_dead = {}, {}, {}
        self._topo_links, self._feature_links, self._branch_links = set(), set(), set()
        rep = self.integrate(graphs)
        self.version = version + 1
        return rep

    def integrate(self, graphs: Iterable[SegmentGraph], *, replace: Iterable[str] = ()) -> IntegrateReport:
        """Insert segment graphs into the map (Sec. VI); a graph whose key is present replaces it.

        Args:
            graphs: new or re-estimated segment graphs (not modified).
            replace: keys of further graphs to drop first (e.g. ``keys_in_tiles`` of re-mapped
                tiles, or segments of another pivot that re-estimated the place).

        Returns:
            What was done. Also bumps ``version``.
        """
        new = list(graphs)
        for g in new:
            if not isinstance(g, SegmentGraph):
                raise HdmapError(f"integrate takes SegmentGraph objects (connection.connect_segment), got {type(g).__name__}")
        new.sort(key=lambda g: g.key)
        keys = [g.key for g in new]
        if len(set(keys)) != len(keys):
            raise HdmapError(f"integrate got two segment graphs with the same key: {sorted(keys)}")
        rep = IntegrateReport()
        rep.removed = self.remove(set(replace) | set(keys))
        for g in new:
            self._graphs[g.key] = g
            self._alive[g.key] = np.ones(g.n_topo, dtype=bool)
        rep.added = len(new)
        if self.config.trim_overlap and new:
            rep.trimmed_nodes = self._trim([g.key for g in new])
        self._stitch(rep)
        if self.config.spur_max_m > 0 or self.config.bubble_max_m > 0:
            # prune spurs and bubbles now, so that the ends they leave are deduplicated and joined
            rep.pruned_nodes = self._kill(self._flat(), lambda fl: _spur_free(
                fl, _dedupe_uids(fl), self.config.spur_max_m, self.config.bubble_max_m))
        if self.config.dedupe_loose_ends:
            rep.deduplicated_nodes = self._dedupe_loose_ends()
        if self.config.join_loose_ends:
            self._join_loose_ends(rep)
        self.version += 1
        self.last_report = rep
        return rep

    # -- internals --
    def _flat(self) -> FlatGraph:
        keys = self.keys
        tmap: dict[str, np.ndarray] = {}
        nmap: dict[str, np.ndarray] = {}
        t_attrs = ("topo_uid", "topo_xy", "topo_heading", "topo_width")
        n_attrs = ("node_uid", "node_xy", "node_type", "node_count", "node_std")
        parts: dict[str, list] = {n: [] for n in ("tg", "tl", "tn", "ng", "nl", "te", "ne", "lo") + t_attrs + n_attrs}
        t_off = n_off = 0
        for gi, k in enumerate(keys):
            g, alive = self._graphs[k], self._alive[k]
            n_alive = np.repeat(alive, np.diff(g.topo_start))
            if k in self._node_dead:
                n_alive &= ~self._node_dead[k]
            tmap[k] = _remap(alive, t_off)
            nmap[k] = _remap(n_alive, n_off)
            tl = np.flatnonzero(alive)
            nl = np.flatnonzero(n_alive)
            parts["tg"].append(np.full(len(tl), gi))
            parts["tl"].append(tl)
            per_topo = np.diff(g.topo_start)
            if k in self._node_dead:
                per_topo = np.bincount(np.repeat(np.arange(g.n_topo), per_topo)[n_alive], minlength=g.n_topo)
            parts["tn"].append(per_topo[alive])
            parts["ng"].append(np.full(len(nl), gi))
            parts["nl"].append(nl)
            for a in t_attrs:
                parts[a].append(getattr(g, a)[tl])
            for a in n_attrs:
                parts[a].append(getattr(g, a)[nl])
            te, _ = _map_edges(g.topo_edges, tmap[k])
            ne, ok = _map_edges(g.edges, nmap[k])
            parts["te"].append(te)
            parts["ne"].append(ne)
            parts["lo"].append(g.edge_leftover[ok] if len(ok) else np.zeros(0, dtype=bool))
            t_off += len(tl)
            n_off += len(nl)

        def links(src: set[Link], maps: dict[str, np.ndarray]) -> np.ndarray:
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
        fl = links(self._feature_links, nmap)
        bl = links(self._branch_links, nmap)
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
            topo_edges=np.concatenate([cat("te", e0).reshape(-1, 2), links(self._topo_links, tmap)]).astype(np.int64),
            edges=np.concatenate([cat("ne", e0).reshape(-1, 2), fl, bl]).astype(np.int64),
            leftover=np.concatenate([cat("lo", np.zeros(0, dtype=bool)), np.zeros(len(fl), dtype=bool),
                                     np.ones(len(bl), dtype=bool)]),
        )

    def _trim(self, new_keys: Sequence[str]) -> int:
        """Kill component end nodes of new graphs that lie on a place another graph already maps.

        With ``trim_keep_longer`` a node is not killed for overlapping a shorter piece (fewer
        topology nodes in its component) of another graph; that graph is walked after the new
        ones instead, so its shorter piece gives way (RULE: the longer estimate of a place stays).
        """
        cfg = self.config
        flat = self._flat()
        if flat.n_topo == 0:
            return 0
        tree = cKDTree(flat.t_xy)
        cos_max = math.cos(math.radians(cfg.max_heading_diff_deg))
        comps: dict[str, list[np.ndarray]] = {}
        sizes: dict[str, np.ndarray] = {}
        spared: set[str] = set()

        def components(key: str) -> list[np.ndarray]:
            if key not in comps:
                comps[key] = self._graphs[key].components()
            return comps[key]

        def size_of(key: str) -> np.ndarray:
            if key not in sizes:
                out = np.zeros(self._graphs[key].n_topo, dtype=np.int64)
                for comp in components(key):
                    out[comp] = len(comp)
                sizes[key] = out
            return sizes[key]

        graph_index = {k: i for i, k in enumerate(flat.keys)}
        pending: set[str] = set()  # the new graphs not walked yet

        def overlaps(k: str, t: int, lookahead: bool, skip: int = -1) -> bool:
            """Does node t of graph k lie on a place of another graph (not ``skip``) that it must
            give way to?"""
            g = self._graphs[k]
            gi = graph_index[k]
            own = size_of(k)[t]
            u, n = _unit(float(g.topo_heading[t]))
            fl = g.node_xy[g.topo_start[t] : g.topo_start[t + 1]] @ n
            ft = g.node_type[g.topo_start[t] : g.topo_start[t + 1]]
            radius = max(cfg.overlap_radius_m, cfg.overlap_search_m)
            for j in tree.query_ball_point(g.topo_xy[t], radius):
                if flat.t_graph[j] in (gi, skip):
                    continue
                kj = flat.keys[flat.t_graph[j]]
                if not self._alive[kj][flat.t_local[j]]:
                    continue
                if math.cos(g.topo_heading[t] - flat.t_heading[j]) < cos_max:
                    continue
                d = flat.t_xy[j] - g.topo_xy[t]
                if math.hypot(*d) <= cfg.overlap_radius_m:
                    same = True  # the same road midpoint
                elif abs(float(d @ u)) > cfg.overlap_along_m or len(fl) == 0:
                    continue
                else:
                    # the same features: most of this step's maxima have a twin of the same type
                    other = slice(flat.t_start[j], flat.t_start[j + 1])
                    gl, gt = flat.n_xy[other] @ n, flat.n_type[other]
                    twin = (np.abs(fl[:, None] - gl[None, :]) <= cfg.overlap_feature_m) & (ft[:, None] == gt[None, :])
                    same = int(twin.any(axis=1).sum()) >= max(min(2, len(fl)), cfg.overlap_share * len(fl))
                if not same:
                    continue
                if cfg.trim_keep_longer and size_of(kj)[flat.t_local[j]] < own:
                    if lookahead:
                        spared.add(kj)
                    continue
                if (lookahead and cfg.trim_lookahead and kj in pending
                        and overlaps(kj, int(flat.t_local[j]), False, skip=gi)):
                    continue  # RULE: not for a place whose own walk will trim it (for a third)
                return True
            return False

        def walk(k: str) -> int:
            alive = self._alive[k]
            killed = 0
            for comp in components(k):
                order = comp.tolist()
                for walk_order in (order, order[::-1]):
                    for t in walk_order:
                        if not alive[t] or not overlaps(k, t, True):
                            break
                        alive[t] = False
                        killed += 1
            pending.discard(k)
            return killed

        pending.update(new_keys)
        killed = sum(walk(k) for k in new_keys)
        killed += sum(walk(k) for k in sorted(spared - set(new_keys)))
        return killed

    def _stitch(self, rep: IntegrateReport) -> None:
        """Link dangling component starts/ends to their nearest valid neighbour (Sec. VI, 1-4)."""
        cfg = self.config
        flat = self._flat()
        nt = flat.n_topo
        if nt < 2:
            return
        te = flat.topo_edges
        adj = coo_matrix((np.ones(len(te)), (te[:, 0], te[:, 1])), shape=(nt, nt))
        _, labels = connected_components(adj, directed=True, connection="weak")
        uf = _UnionFind(labels)
        indeg = np.bincount(te[:, 1], minlength=nt) if len(te) else np.zeros(nt, dtype=np.int64)
        outdeg = np.bincount(te[:, 0], minlength=nt) if len(te) else np.zeros(nt, dtype=np.int64)
        tree = cKDTree(flat.t_xy)
        out_adj = _Adjacency(flat.edges[:, 0], flat.edges[:, 1], flat.n_nodes)
        in_adj = _Adjacency(flat.edges[:, 1], flat.edges[:, 0], flat.n_nodes)
        existing = _Adjacency(te[:, 0], te[:, 1], nt)
        # 1. components' start (no predecessor) and end (no successor) nodes, in a fixed order
        ends = [(int(i), True) for i in np.flatnonzero(outdeg == 0)]
        starts = [(int(i), False) for i in np.flatnonzero(indeg == 0)]
        todo = sorted(ends + starts, key=lambda x: (int(flat.t_uid[x[0]]), x[1]))
        for i, is_end in todo:
            if (is_end and outdeg[i]) or (not is_end and indeg[i]):
                continue
            best = _partner(flat, tree, i, is_end, cfg, lambda j: uf.find(j) != uf.find(i))
            join = True
            if best < 0 and cfg.link_within_component:
                # RULE: a start (end) with no partner in another component may link inside its own
                # component (topology only) unless the link closes a short cycle.
                best = _partner(
                    flat, tree, i, is_end, cfg, lambda j: j != i and not _closes_cycle(existing, i, j, is_end)
                )
                join = False
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            # 4. link the topology nodes and join their features
            if not self._add_topo_link(flat, a, b, existing, outdeg, indeg, uf, rep):
                continue
            if join:
                rep.feature_links += self._join_features(flat, a, b, out_adj, in_adj)
        if cfg.track_search_m > 0:
            self._track_links(flat, tree, todo, existing, indeg, outdeg, uf, rep)
        if cfg.path_search_m > 0:
            self._path_links(flat, tree, todo, existing, indeg, outdeg, uf, rep)
        if cfg.track_bridge_m > 0:
            self._bridge_links(flat, tree, existing, indeg, outdeg, uf, rep)

    def _allowed(self, existing: _Adjacency, uf: _UnionFind, i: int, is_end: bool) -> Callable[[int], bool]:
        """Partners a late (track or arc) link of start/end i may take: another component, or
        with ``link_within_component`` its own without closing a short cycle."""
        within = self.config.link_within_component

        def allowed(j: int) -> bool:
            if uf.find(j) != uf.find(i):
                return True
            return within and not _closes_cycle(existing, i, j, is_end)

        return allowed

    @staticmethod
    def _reach(flat: FlatGraph) -> float:
        """Search radius of a late link's point queries: one step along, the widest half road across [m]."""
        return math.hypot(_PATH_STEP_M, float(np.nanmax(np.where(flat.t_width > 0, flat.t_width, 3.5))) / 2.0)

    def _track_links(
        self, flat: FlatGraph, tree: cKDTree, todo: list[tuple[int, bool]], existing: _Adjacency,
        indeg: np.ndarray, outdeg: np.ndarray, uf: _UnionFind, rep: IntegrateReport,
    ) -> None:
        """RULE: a start (end) still without a partner follows the path its pivot drove
        backward (forward) for ``track_search_m`` and links, topology only, to the first node
        that path enters (``_track_partner``): a drive went there from the end."""
        cfg = self.config
        reach = self._reach(flat)
        te = flat.topo_edges
        pred = _Adjacency(te[:, 1], te[:, 0], flat.n_topo)
        for a, b in existing.added():
            pred.add(b, a)
        tracks, rows = self._pivot_tracks()
        for i, is_end in todo:
            linked = bool(outdeg[i]) if is_end else bool(indeg[i])
            if linked and not cfg.track_linked_ends:
                continue
            g = self._graphs[flat.keys[flat.t_graph[i]]]
            track = tracks.get(g.pivot_drive or g.pivot_id)
            if track is None or len(track[0]) < 2:
                continue
            step = int(g.topo_step[flat.t_local[i]])
            r = int(np.searchsorted(g.track_step, step))
            if r >= len(g.track_step) or int(g.track_step[r]) != step:
                continue
            if linked:
                # RULE: a linked end still follows its pivot: a node its track enters that the map
                # does not reach from it within 2 track searches + 30 m gets a link too
                walk, back = (existing, pred) if is_end else (pred, existing)
                far = 2.0 * cfg.track_search_m + 30.0
                near = _reached_within(flat, walk, i, far)
                behind = _reached_within(flat, back, i, far) if cfg.track_rejoin_both else set()

                def allowed(
                    j: int, i: int = i, is_end: bool = is_end, near: set[int] = near, walk: _Adjacency = walk,
                    behind: set[int] = behind, back: _Adjacency = back,
                ) -> bool:
                    if j in near or _closes_cycle(existing, i, j, is_end):
                        return False
                    if cfg.track_rejoin_m <= 0:
                        return True
                    # RULE: nor a node whose road runs on (back) into what the map reaches from the
                    # end (start) within track_rejoin_m: the link would only add a side step
                    # between two roads that join anyway
                    if near & _reached_within(flat, walk, j, cfg.track_rejoin_m):
                        return False
                    # RULE: ... nor one whose road came from (runs on into) what reaches the end
                    # (what the start reaches): the side step across a split (merge) behind it
                    return not (behind and behind & _reached_within(flat, back, j, cfg.track_rejoin_m))
            else:
                allowed = self._allowed(existing, uf, i, is_end)
            best = _track_partner(flat, tree, i, is_end, track, int(rows[g.key][r]), cfg, reach, allowed)
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            if self._add_topo_link(flat, a, b, existing, outdeg, indeg, uf, rep):
                pred.add(b, a)
                rep.track_links += 1

    def _bridge_links(
        self, flat: FlatGraph, tree: cKDTree, existing: _Adjacency, indeg: np.ndarray, outdeg: np.ndarray,
        uf: _UnionFind, rep: IntegrateReport,
    ) -> None:
        """RULE track bridge: where a pivot's track leaves the map's node A, runs through steps that
        no node covers (failed steps at a junction, the road on both sides mapped by other pivots)
        and enters node B within ``track_bridge_m``, A is linked to B (topology only) unless the
        map reaches B from A within 2 * ``track_bridge_m`` + 30 m already or the link closes a
        short cycle: the pivot drove from A to B (``_track_bridges``). Unlike the track search it
        needs no component start/end: the pivot's own chain may not exist there at all."""
        cfg = self.config
        reach = self._reach(flat)
        limit = 2.0 * cfg.track_bridge_m + 30.0
        reached: dict[int, set[int]] = {}

        def near(a: int) -> set[int]:
            if a not in reached:
                reached[a] = _reached_within(flat, existing, a, limit)
            return reached[a]

        tracks, _ = self._pivot_tracks()
        for pid in sorted(tracks):
            xy, heading = tracks[pid]
            if len(xy) < 3:
                continue
            bridges = _track_bridges(
                flat, tree, np.asarray(xy, dtype=float), np.asarray(heading, dtype=float), cfg, reach,
                lambda a, j: j in near(a),
            )
            for a, b in bridges:
                if b in near(a):
                    continue
                if _closes_cycle(existing, a, b, True):
                    continue
                if self._add_topo_link(flat, a, b, existing, outdeg, indeg, uf, rep):
                    rep.bridge_links += 1
                    reached.clear()  # the map reaches more now

    def _pivot_tracks(self) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
        """Per pivot drive, its track over all its segment graphs (xy, heading; in order of
        travelled distance, each step once), and per graph the row of each of its track steps
        in that track. Live, one pivot's steps come in one graph per tile: the graphs' pivot ids
        are per tile (``SegmentGraph.pivot_drive`` names the drive) and their step indices count
        from each tile's clip of the drive, so the pieces are ordered by ``track_s`` (the
        travelled distance on the whole drive); graphs without it are ordered by step. The xy
        are the pivot's positions (``track_pose``) with ``StitchConfig.track_pose`` when every
        piece has them, else its steps' cut midpoints (``track_xy``)."""
        parts: dict[str, list[SegmentGraph]] = {}
        for k in self.keys:
            g = self._graphs[k]
            if len(g.track_step):
                parts.setdefault(g.pivot_drive or g.pivot_id, []).append(g)
        tracks, rows = {}, {}
        for pid, gs in parts.items():
            # RULE track_pose: the pivot's own positions where every piece has them
            pose = self.config.track_pose and all(len(g.track_pose) == len(g.track_step) for g in gs)
            attr = "track_pose" if pose else "track_xy"
            if len(gs) == 1:
                g = gs[0]
                tracks[pid] = (getattr(g, attr), g.track_heading)
                rows[g.key] = np.arange(len(g.track_step))
                continue
            by_s = all(len(g.track_s) == len(g.track_step) for g in gs)
            order = [np.asarray(g.track_s if by_s else g.track_step, dtype=float) for g in gs]
            _, first, inverse = np.unique(np.concatenate(order), return_index=True, return_inverse=True)
            tracks[pid] = (np.concatenate([getattr(g, attr) for g in gs])[first],
                           np.concatenate([g.track_heading for g in gs])[first])
            at = np.cumsum([0] + [len(o) for o in order])
            for g, a, b in zip(gs, at[:-1], at[1:]):
                rows[g.key] = inverse[a:b]
        return tracks, rows

    def _path_links(
        self, flat: FlatGraph, tree: cKDTree, todo: list[tuple[int, bool]], existing: _Adjacency,
        indeg: np.ndarray, outdeg: np.ndarray, uf: _UnionFind, rep: IntegrateReport,
    ) -> None:
        """RULE: a start (end) still without a partner follows its chain's own arc backward
        (forward) for ``path_search_m`` and links, topology only, to the first node it enters
        (``_path_partner``). Run after every start/end had its ordinary turn, so it takes no
        partner away from another's ordinary (feature-joining) link."""
        cfg = self.config
        te = flat.topo_edges
        pred = _Adjacency(te[:, 1], te[:, 0], flat.n_topo)
        succ = existing
        reach = self._reach(flat)
        for i, is_end in todo:
            if (is_end and outdeg[i]) or (not is_end and indeg[i]):
                continue
            rate = _heading_rate(flat, pred if is_end else succ, i, cfg.path_curvature_m)
            if not is_end:
                rate = -rate  # measured from a later node back to the start: flip to driving sense
            best = _path_partner(flat, tree, i, is_end, rate, cfg, reach, self._allowed(existing, uf, i, is_end))
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            if self._add_topo_link(flat, a, b, existing, outdeg, indeg, uf, rep):
                rep.path_links += 1

    def _add_topo_link(
        self, flat: FlatGraph, a: int, b: int, existing: _Adjacency, outdeg: np.ndarray, indeg: np.ndarray,
        uf: _UnionFind, rep: IntegrateReport,
    ) -> bool:
        """Link topology node a -> b (and book it); False when the link exists already."""
        if b in existing.get(a):
            return False
        existing.add(a, b)
        outdeg[a] += 1
        indeg[b] += 1
        uf.union(a, b)
        self._topo_links.add(self._link(flat, a, b, topo=True))
        rep.topology_links += 1
        return True

    @staticmethod
    def _link(flat: FlatGraph, a: int, b: int, *, topo: bool) -> Link:
        if topo:
            return (flat.keys[flat.t_graph[a]], int(flat.t_local[a]), flat.keys[flat.t_graph[b]], int(flat.t_local[b]))
        return (flat.keys[flat.n_graph[a]], int(flat.n_local[a]), flat.keys[flat.n_graph[b]], int(flat.n_local[b]))

    def _join_features(self, flat: FlatGraph, a: int, b: int, out_adj: _Adjacency, in_adj: _Adjacency) -> int:
        """Unmodified rectangular assignment between the features of linked topology nodes a -> b,
        same type only."""
        cfg = self.config
        xa = np.arange(flat.t_start[a], flat.t_start[a + 1])
        yb = np.arange(flat.t_start[b], flat.t_start[b + 1])
        if len(xa) == 0 or len(yb) == 0:
            return 0
        _, n = _unit(float(flat.t_heading[b]))
        lat = np.abs((flat.n_xy[yb][None, :, :] - flat.n_xy[xa][:, None, :]) @ n)
        ta, tb = flat.n_type[xa][:, None], flat.n_type[yb][None, :]
        if cfg.same_type_only:
            forbidden = ta != tb
        else:  # markings of either type may meet (flicker); a border only meets a border
            forbidden = (ta == _BORDER_CODE) != (tb == _BORDER_CODE)
        cost = np.where(forbidden, _BIG, np.where(lat <= cfg.feature_max_m, lat, _GATE + lat))
        cost = cost + np.where(ta != tb, cfg.type_mismatch_cost_m, 0.0)
        rows, cols = linear_sum_assignment(cost)
        made = 0
        for r, c in zip(rows.tolist(), cols.tolist()):
            if forbidden[r, c] or lat[r, c] > cfg.feature_max_m:
                continue
            x, y = int(xa[r]), int(yb[c])
            # the feature already continues next to y (or y is already reached next to x): skip
            if any(abs(float((flat.n_xy[z] - flat.n_xy[y]) @ n)) <= cfg.duplicate_m for z in out_adj.get(x)):
                continue
            if any(abs(float((flat.n_xy[w] - flat.n_xy[x]) @ n)) <= cfg.duplicate_m for w in in_adj.get(y)):
                continue
            out_adj.add(x, y)
            in_adj.add(y, x)
            self._feature_links.add(self._link(flat, x, y, topo=False))
            made += 1
        return made

    def _kill(self, flat: FlatGraph, keep_fn) -> int:
        """Mark the feature nodes that ``keep_fn(flat)`` (an (N,) keep-mask) drops as dead."""
        keep = keep_fn(flat)
        dead = np.flatnonzero(~keep)
        for j in dead.tolist():
            k = flat.keys[flat.n_graph[j]]
            if k not in self._node_dead:
                self._node_dead[k] = np.zeros(self._graphs[k].n_nodes, dtype=bool)
            self._node_dead[k][flat.n_local[j]] = True
        return len(dead)

    def _refuted(self, flat: FlatGraph) -> np.ndarray:
        """(E,) bool: feature edges of ``flat`` through stretches the drives saw empty
        (``StitchConfig.fill_evidence``, ``evidence.refuted_edges``), from every segment's judged
        steps."""
        xy, hd, starts, iv = [], [], [], []
        off = 0
        for k in self.keys:
            g = self._graphs[k]
            j = np.flatnonzero(g.track_judged) if len(g.track_judged) == len(g.track_step) else np.zeros(0, np.int64)
            if len(j) == 0:
                continue
            xy.append(g.track_xy[j])
            hd.append(g.track_heading[j])
            lo, hi = g.track_empty_start[j], g.track_empty_start[j + 1]
            n = hi - lo
            rows = np.repeat(lo, n) + (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
            iv.append(g.track_empty[rows].reshape(-1, 2))
            starts.append(off + np.cumsum(n))
            off += int(n.sum())
        if not xy:
            return np.zeros(len(flat.edges), dtype=bool)
        return refuted_edges(
            flat.n_xy, flat.edges, np.concatenate(xy), np.concatenate(hd),
            np.concatenate([[0]] + starts).astype(np.int64), np.concatenate(iv), config=self.config.fill_evidence,
        )

    # -- export --
    def to_hdmap(
        self, *, version: int | None = None, stamp_ns: int = 0, drive_ids: Sequence[str] | None = None
    ) -> HDMap:
        """The complete map as an ``HDMap``: every field of MapFeature / TopologyNode filled."""
        flat = self._flat()
        if drive_ids is None:
            drive_ids = sorted({d for g in self._graphs.values() for d in g.drive_ids})
        refuted = 0
        protect = None
        if self.config.fill_evidence is not None and len(flat.edges):
            drop = self._refuted(flat)
            refuted = int(drop.sum())
            # the pieces a refuted fill leaves are drive-supported: no speck rule for them
            protect = np.zeros(flat.n_nodes, dtype=bool)
            protect[flat.edges[drop].reshape(-1)] = True
            flat.edges, flat.leftover = flat.edges[~drop], flat.leftover[~drop]
        features, topology = export_map(flat, self.config, protect=protect)
        return HDMap(
            features=features,
            topology=topology,
            drive_ids=tuple(drive_ids),
            version=self.version if version is None else int(version),
            stamp_ns=int(stamp_ns),
            extra={
                "segments": len(self._graphs),
                "topology_links": len(self._topo_links),
                "feature_links": len(self._feature_links) + len(self._branch_links),
                "last_integrate": dict(self.last_report.__dict__),
                "fills_refuted": refuted,
            },
        )


# --- public functions -----------------------------------------------------------------------------------


def stitch(
    graphs: Iterable[SegmentGraph],
    *,
    config: StitchConfig = StitchConfig(),
    base: HDMap | None = None,
    version: int | None = None,
    stamp_ns: int = 0,
) -> HDMap:
    """Stitch segment graphs into the complete map (Sec. VI), optionally into an existing map.

    Args:
        graphs: segment graphs from ``connection.connect_segment`` (not modified).
        config: stitching parameters.
        base: an existing map to update with the new sections; its feature and topology ids are
            kept where its features persist.
        version: map version; default: the base's version + 1, else 1.
        stamp_ns: header stamp of the map [ns].

    Returns:
        The complete hierarchical map.
    """
    mg = MapGraph.from_hdmap(base, config=config) if base is not None else MapGraph(config=config)
    mg.integrate(graphs)
    drive_ids = None
    if base is not None:
        drive_ids = sorted(set(base.drive_ids) | {d for k in mg.keys for d in mg.graph(k).drive_ids})
    return mg.to_hdmap(version=version, stamp_ns=stamp_ns, drive_ids=drive_ids)


def to_hdmap(
    graph: MapGraph | SegmentGraph,
    *,
    drive_ids: Sequence[str] | None = None,
    version: int = 0,
    stamp_ns: int = 0,
    config: StitchConfig = StitchConfig(),
) -> HDMap:
    """Export a map graph (or a single segment graph) as an ``HDMap``."""
    if isinstance(graph, SegmentGraph):
        mg = MapGraph(config=config)
        mg._graphs[graph.key] = graph
        mg._alive[graph.key] = np.ones(graph.n_topo, dtype=bool)
        graph = mg
    return graph.to_hdmap(version=version, stamp_ns=stamp_ns, drive_ids=drive_ids)
