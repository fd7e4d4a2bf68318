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
graphs. Beyond the paper (rules of :class:`StitchConfig`, all off in the ``paper`` preset):
component ends that duplicate a place already in the map are trimmed, spurs and bubbles pruned,
dangling ends running on another segment's line deduplicated, loose ends that continue each other
joined (gaps filled on a Hermite curve), and, at export (``hdmap_core.graph.export``), type flicker
smoothed, gore splits placed at the lane line's end and isolated specks dropped.

The steps are functions with plain data in and out, one module each: ``flat.py`` (the flat view
of all graphs), ``trim.py`` (overlap trimming), ``linking.py`` (steps 1-4 and the late links;
partners in ``links.py``, the pivots' tracks in ``tracks.py``), ``loose_ends.py``, ``cleanup.py``,
``type_runs.py``, ``gores.py`` and ``export.py`` (the export), ``from_hdmap.py`` (a map read back).
:class:`MapGraph` keeps the state (segment graphs, alive masks, links) and applies their results.

Feature ids are the stable uid of a polyline's first feature node (hash of pivot id, step index and
slot), so the same input gives the same ids and adding an unrelated segment changes none.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from hdmap_core.errors import HdmapError
from hdmap_core.graph.cleanup import spur_free
from hdmap_core.graph.export import ExportPlan, export_planned, export_with_plan
from hdmap_core.graph.flat import FlatGraph, Link, dedupe_uids, flatten, link_key
from hdmap_core.graph.from_hdmap import graph_from_hdmap
from hdmap_core.graph.linking import link_segments
from hdmap_core.graph.loose_ends import dedupe_loose_ends, join_loose_ends
from hdmap_core.graph.segment_graph import SegmentGraph
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.graph.trim import trim_overlaps
from hdmap_core.model import HDMap
from hdmap_core.pipeline.evidence import refuted_edges

__all__ = ["MapGraph", "IntegrateReport", "StitchState", "stitch", "to_hdmap"]


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


@dataclass(frozen=True)
class StitchState:
    """What the stitch decided for some segment graphs (``MapGraph.state``): which of their
    topology nodes stay (``alive``, per key (T_k,) bool), which of their feature nodes were
    dropped (``node_dead``, per key (N_k,) bool, keys without drops absent) and the links that
    start at one of their nodes (to a node of any graph)."""

    alive: dict[str, np.ndarray]
    node_dead: dict[str, np.ndarray]
    topo_links: frozenset[Link]
    feature_links: frozenset[Link]
    branch_links: frozenset[Link]


class MapGraph:
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
        # the decisions of the last export (``to_hdmap(keep_plan=True)``), kept by ``with_geometry``
        # (``to_hdmap_planned``); None after any change of the graph's structure
        self.export_plan: ExportPlan | None = None
        self._plan_refuted = 0  # the fills refuted in that export
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

    def state(self, keys: Iterable[str]) -> StitchState:
        """The stitch's decisions for the graphs ``keys``: their masks and the links from their
        nodes (a link belongs to the graph of its first node, so states of disjoint key sets
        never hold the same link)."""
        own = set(keys) & set(self._graphs)

        def mine(links: set[Link]) -> frozenset[Link]:
            return frozenset(ln for ln in links if ln[0] in own)

        return StitchState(
            alive={k: self._alive[k].copy() for k in sorted(own)},
            node_dead={k: self._node_dead[k].copy() for k in sorted(own) if k in self._node_dead},
            topo_links=mine(self._topo_links),
            feature_links=mine(self._feature_links),
            branch_links=mine(self._branch_links),
        )

    @classmethod
    def from_states(
        cls, graphs: Iterable[SegmentGraph], states: Iterable[StitchState], *, config: StitchConfig = StitchConfig()
    ) -> MapGraph:
        """A map graph of ``graphs`` with the decisions of ``states`` (``state`` of disjoint key
        sets that cover every graph), as one ``integrate`` of them all leaves it: the join of
        graphs stitched in parts (``hdmap_core.tiled.stitch``). Links to a graph not given are
        dropped.

        Raises:
            HdmapError: a graph without a state, or two graphs with one key.
        """
        mg = cls(config=config)
        for g in graphs:
            if g.key in mg._graphs:
                raise HdmapError(f"two segment graphs with the key {g.key!r}")
            mg._graphs[g.key] = g
        for st in states:
            mg._alive.update(st.alive)
            mg._node_dead.update(st.node_dead)
            mg._topo_links |= st.topo_links
            mg._feature_links |= st.feature_links
            mg._branch_links |= st.branch_links
        missing = sorted(set(mg._graphs) - set(mg._alive))
        if missing:
            raise HdmapError(f"no stitch state for the segment graphs {missing[:3]}")
        mg._alive = {k: v for k, v in mg._alive.items() if k in mg._graphs}
        mg._node_dead = {k: v for k, v in mg._node_dead.items() if k in mg._graphs}
        for name in ("_topo_links", "_feature_links", "_branch_links"):
            links = getattr(mg, name)
            setattr(mg, name, {ln for ln in links if ln[0] in mg._graphs and ln[2] in mg._graphs})
        mg.version = 1
        mg.last_report = IntegrateReport(
            added=len(mg._graphs),
            topology_links=len(mg._topo_links),
            feature_links=len(mg._feature_links) + len(mg._branch_links),
        )
        return mg

    def with_geometry(self, graphs: Iterable[SegmentGraph]) -> MapGraph:
        """A copy in which ``graphs`` replace the graphs of their keys with every stitch decision
        kept (masks, drops, links): the same nodes and edges, moved (``live.restitch``: a fused
        drive). Not the stitch of the moved graphs (``integrate`` / ``rebuild`` decide again).

        Raises:
            HdmapError: a graph whose key is not in the map or whose nodes or edges differ.
        """
        new = self.copy()
        for g in graphs:
            old = self._graphs.get(g.key)
            if (
                old is None
                or not np.array_equal(old.node_uid, g.node_uid)
                or not np.array_equal(old.topo_uid, g.topo_uid)
                or not np.array_equal(old.edges, g.edges)
                or not np.array_equal(old.topo_edges, g.topo_edges)
            ):
                raise HdmapError(f"with_geometry: {g.key!r} is not a graph of the map with the same nodes and edges")
            new._graphs[g.key] = g
        new.export_plan = self.export_plan  # the same nodes and edges: the same export decisions
        new._plan_refuted = self._plan_refuted
        return new

    # -- updates --
    def remove(self, keys: Iterable[str]) -> int:
        """Drop segment graphs (and every link touching them); returns how many were present."""
        gone = {k for k in keys if k in self._graphs}
        if gone:
            self.export_plan = None
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
        self.export_plan = None  # the structure changes: the last export's decisions are not this graph's
        new = list(graphs)
        for g in new:
            if not isinstance(g, SegmentGraph):
                raise HdmapError(
                    f"integrate takes SegmentGraph objects (connection.connect_segment), got {type(g).__name__}"
                )
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
        cfg = self.config
        if cfg.trim_overlap and new:
            self._alive, rep.trimmed_nodes = trim_overlaps(
                self._flatten(), self._graphs, self._alive, new_keys=[g.key for g in new], config=cfg
            )
        self._link(rep)
        if cfg.spur_max_m > 0 or cfg.bubble_max_m > 0:
            # RULE spur / bubble, now: so that the ends they leave are deduplicated and joined
            flat = self._flatten()
            keep = spur_free(flat, dedupe_uids(flat), spur_max_m=cfg.spur_max_m, bubble_max_m=cfg.bubble_max_m)
            rep.pruned_nodes = self._drop_nodes(flat, ~keep)
        if cfg.dedupe_loose_ends:
            flat = self._flatten()
            rep.deduplicated_nodes = self._drop_nodes(flat, dedupe_loose_ends(flat))
        if cfg.join_loose_ends:
            flat = self._flatten()
            joins = join_loose_ends(flat, config=cfg)
            self._feature_links.update(link_key(flat, a, b, topo=False) for a, b in joins.links)
            self._branch_links.update(link_key(flat, a, b, topo=False) for a, b in joins.branch_links)
            if joins.dropped.any():
                self._drop_nodes(flat, joins.dropped)
            rep.loose_ends_joined = len(joins.links)
            rep.branches_joined = len(joins.branch_links)
        self.version += 1
        self.last_report = rep
        return rep

    # -- internals --
    def _flatten(self) -> FlatGraph:
        return flatten(
            self._graphs,
            self._alive,
            node_dead=self._node_dead,
            topo_links=self._topo_links,
            feature_links=self._feature_links,
            branch_links=self._branch_links,
        )

    def _link(self, rep: IntegrateReport) -> None:
        """Link the component ends of the map (Sec. VI, 1-4; ``linking.link_segments``) and book them."""
        flat = self._flatten()
        links = link_segments(flat, self._graphs, config=self.config)
        self._topo_links.update(link_key(flat, a, b, topo=True) for a, b in links.topo)
        self._feature_links.update(link_key(flat, x, y, topo=False) for x, y in links.features)
        rep.topology_links = len(links.topo)
        rep.feature_links = len(links.features)
        rep.track_links, rep.path_links, rep.bridge_links = links.track_links, links.path_links, links.bridge_links

    def _drop_nodes(self, flat: FlatGraph, drop: np.ndarray) -> int:
        """Mark the feature nodes of ``flat`` where ``drop`` ((N,) bool) is set as dead; returns how many."""
        dead = np.flatnonzero(drop)
        for j in dead.tolist():
            k = flat.keys[flat.n_graph[j]]
            if k not in self._node_dead:
                self._node_dead[k] = np.zeros(self._graphs[k].n_nodes, dtype=bool)
            self._node_dead[k][flat.n_local[j]] = True
        return len(dead)

    # -- export --
    def to_hdmap(
        self,
        *,
        version: int | None = None,
        stamp_ns: int = 0,
        drive_ids: Sequence[str] | None = None,
        keep_plan: bool = False,
    ) -> HDMap:
        """The complete map as an ``HDMap``: every field of MapFeature / TopologyNode filled.
        ``keep_plan``: keep the export's decisions as ``export_plan`` (:meth:`to_hdmap_planned`)."""
        flat = self._flatten()
        if drive_ids is None:
            drive_ids = sorted({d for g in self._graphs.values() for d in g.drive_ids})
        refuted = 0
        protect = None
        if self.config.fill_evidence is not None and len(flat.edges):
            drop = _refuted_fills(flat, [self._graphs[k] for k in flat.keys])
            refuted = int(drop.sum())
            # the pieces a refuted fill leaves are drive-supported: no speck rule for them
            protect = np.zeros(flat.n_nodes, dtype=bool)
            protect[flat.edges[drop].reshape(-1)] = True
            flat = dataclasses.replace(flat, edges=flat.edges[~drop], leftover=flat.leftover[~drop])
        features, topology, plan = export_with_plan(flat, config=self.config, protect=protect)
        if keep_plan:
            self.export_plan = plan
            self._plan_refuted = refuted
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

    def to_hdmap_planned(self, *, drive_ids: Sequence[str] | None = None) -> HDMap:
        """The map as ``to_hdmap`` gives it, with the decisions of the export ``export_plan`` holds
        (an export of this graph before ``with_geometry`` moved its nodes: ``live.restitch``):
        the same polylines of the same nodes at their new positions, the fills refuted then
        dropped again, the gore rules run again.

        Raises:
            HdmapError: no export plan, or one of another graph.
        """
        if self.export_plan is None:
            raise HdmapError("to_hdmap_planned: no export plan (to_hdmap(keep_plan=True) first)")
        features, topology = export_planned(self._flatten(), self.export_plan)
        if drive_ids is None:
            drive_ids = sorted({d for g in self._graphs.values() for d in g.drive_ids})
        return HDMap(
            features=features,
            topology=topology,
            drive_ids=tuple(drive_ids),
            version=self.version,
            extra={
                "segments": len(self._graphs),
                "topology_links": len(self._topo_links),
                "feature_links": len(self._feature_links) + len(self._branch_links),
                "last_integrate": dict(self.last_report.__dict__),
                "fills_refuted": self._plan_refuted,
            },
        )


def _refuted_fills(flat: FlatGraph, graphs: Sequence[SegmentGraph]) -> np.ndarray:
    """(E,) bool: feature edges of ``flat`` through stretches the drives saw empty
    (``StitchConfig.fill_evidence``, ``evidence.refuted_edges``), from every segment's judged
    steps."""
    xy, hd, starts, iv = [], [], [], []
    off = 0
    for g in graphs:
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
        flat.n_xy,
        flat.edges,
        np.concatenate(xy),
        np.concatenate(hd),
        np.concatenate([np.zeros(1, np.int64), *starts]).astype(np.int64),
        np.concatenate(iv),
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
