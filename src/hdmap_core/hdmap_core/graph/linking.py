"""Links between the segments of the map: component ends joined to their partners (Sec. VI, steps 1-4).

``link_segments`` takes the flat view of the map and returns the links to add, in global node
indices: every start (no predecessor) and end (no successor) of a component of the topology graph
looks up its nearest valid partner (``links.partner``), the topology nodes are linked and the
features they refer to joined by the unmodified rectangular assignment, same type only. Beyond the
paper (each switchable in ``StitchConfig``): links inside a component (RULE within component),
along the pivot's track (RULE track), along the chain's own arc (RULE path) and across a track's
bridge over a junction (RULE track bridge), all topology only.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from networkx.utils import UnionFind
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from hdmap_core.geometry import heading_frame
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.links import (
    PATH_STEP_M,
    Adjacency,
    closes_cycle,
    heading_rate,
    partner,
    path_partner,
    reached_within,
)
from hdmap_core.graph.segment_graph import SegmentGraph
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.graph.tracks import pivot_tracks, track_bridges, track_partner
from hdmap_core.model import FeatureType

__all__ = ["SegmentLinks", "link_segments"]

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: features are joined across a link only when at most this far apart across the cut [m].
_FEATURE_MAX_M = 2.0
#: a join is skipped when the feature already continues within this distance of the new partner
#: (it would duplicate a polyline) [m].
_DUPLICATE_M = 0.25
#: the chain's heading rate is taken over this much of it (chord from the node to the first
#: chain node at least this far; shorter chains: straight) [m].
_PATH_CURVATURE_M = 20.0

_BIG = 1.0e9
_GATE = 1.0e4
_BORDER_CODE = int(FeatureType.ROAD_BORDER)


@dataclass
class SegmentLinks:
    """The links ``link_segments`` found, in global indices of its ``FlatGraph``.

    ``topo``: topology links (a, b); ``features``: feature links (x, y); the counts split
    ``topo`` by the rule that made it.
    """

    topo: list[tuple[int, int]] = field(default_factory=list)
    features: list[tuple[int, int]] = field(default_factory=list)
    track_links: int = 0
    path_links: int = 0
    bridge_links: int = 0


def link_segments(flat: FlatGraph, graphs: Mapping[str, SegmentGraph], *, config: StitchConfig) -> SegmentLinks:
    """Link dangling component starts/ends to their nearest valid neighbour (Sec. VI, 1-4).

    Args:
        flat: the map's flat view (not modified).
        graphs: its segment graphs by key (for the pivots' tracks).
        config: stitching parameters.
    """
    if flat.n_topo < 2:
        return SegmentLinks()
    return _Linker(flat, graphs, config).run()


class _Linker:
    """The working state of one ``link_segments`` call: the map's adjacency with the links made
    so far, node degrees and the components they join (union-find over the weak components)."""

    def __init__(self, flat: FlatGraph, graphs: Mapping[str, SegmentGraph], cfg: StitchConfig) -> None:
        self.flat, self.graphs, self.cfg = flat, graphs, cfg
        nt = flat.n_topo
        te = flat.topo_edges
        adj = coo_matrix((np.ones(len(te)), (te[:, 0], te[:, 1])), shape=(nt, nt))
        _, self.labels = connected_components(adj, directed=True, connection="weak")
        self.uf = UnionFind()
        self.indeg = np.bincount(te[:, 1], minlength=nt) if len(te) else np.zeros(nt, dtype=np.int64)
        self.outdeg = np.bincount(te[:, 0], minlength=nt) if len(te) else np.zeros(nt, dtype=np.int64)
        self.tree = cKDTree(flat.t_xy)
        self.existing = Adjacency(te[:, 0], te[:, 1], nt)
        self.out = SegmentLinks()

    def component(self, i: int) -> int:
        return self.uf[int(self.labels[i])]

    def run(self) -> SegmentLinks:
        flat, cfg = self.flat, self.cfg
        out_adj = Adjacency(flat.edges[:, 0], flat.edges[:, 1], flat.n_nodes)
        in_adj = Adjacency(flat.edges[:, 1], flat.edges[:, 0], flat.n_nodes)
        # 1. components' start (no predecessor) and end (no successor) nodes, in a fixed order
        ends = [(int(i), True) for i in np.flatnonzero(self.outdeg == 0)]
        starts = [(int(i), False) for i in np.flatnonzero(self.indeg == 0)]
        todo = sorted(ends + starts, key=lambda x: (int(flat.t_uid[x[0]]), x[1]))
        for i, is_end in todo:
            if (is_end and self.outdeg[i]) or (not is_end and self.indeg[i]):
                continue
            # 2.-3. the nearest valid neighbour in another component
            best = partner(flat, self.tree, i, is_end, cfg, lambda j: self.component(j) != self.component(i))
            join = True
            if best < 0 and cfg.link_within_component:
                # RULE within component: a start (end) with no partner in another component may
                # link inside its own component (topology only) unless the link closes a short cycle.
                best = partner(
                    flat, self.tree, i, is_end, cfg, lambda j: j != i and not closes_cycle(self.existing, i, j, is_end)
                )
                join = False
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            # 4. link the topology nodes and join their features
            if not self.add_topo_link(a, b):
                continue
            if join:
                self.join_features(a, b, out_adj, in_adj)
        if cfg.track_search_m > 0:
            self.track_links(todo)
        if cfg.path_search_m > 0:
            self.path_links(todo)
        if cfg.track_bridge_m > 0:
            self.bridge_links()
        return self.out

    def add_topo_link(self, a: int, b: int) -> bool:
        """Link topology node a -> b (and book it); False when the link exists already."""
        if b in self.existing.get(a):
            return False
        self.existing.add(a, b)
        self.outdeg[a] += 1
        self.indeg[b] += 1
        self.uf.union(int(self.labels[a]), int(self.labels[b]))
        self.out.topo.append((a, b))
        return True

    def allowed(self, i: int, is_end: bool) -> Callable[[int], bool]:
        """Partners a late (track or arc) link of start/end i may take: another component, or
        with ``link_within_component`` its own without closing a short cycle."""
        within = self.cfg.link_within_component

        def allowed(j: int) -> bool:
            if self.component(j) != self.component(i):
                return True
            return within and not closes_cycle(self.existing, i, j, is_end)

        return allowed

    def reach(self) -> float:
        """Search radius of a late link's point queries: one step along, the widest half road across [m]."""
        flat = self.flat
        return math.hypot(PATH_STEP_M, float(np.nanmax(np.where(flat.t_width > 0, flat.t_width, 3.5))) / 2.0)

    def join_features(self, a: int, b: int, out_adj: Adjacency, in_adj: Adjacency) -> None:
        """Unmodified rectangular assignment between the features of linked topology nodes a -> b,
        same type only."""
        flat, cfg = self.flat, self.cfg
        xa = np.arange(flat.t_start[a], flat.t_start[a + 1])
        yb = np.arange(flat.t_start[b], flat.t_start[b + 1])
        if len(xa) == 0 or len(yb) == 0:
            return
        _, n = heading_frame(float(flat.t_heading[b]))
        lat = np.abs((flat.n_xy[yb][None, :, :] - flat.n_xy[xa][:, None, :]) @ n)
        ta, tb = flat.n_type[xa][:, None], flat.n_type[yb][None, :]
        if cfg.same_type_only:
            forbidden = ta != tb
        else:  # markings of either type may meet (flicker); a border only meets a border
            forbidden = (ta == _BORDER_CODE) != (tb == _BORDER_CODE)
        cost = np.where(forbidden, _BIG, np.where(lat <= _FEATURE_MAX_M, lat, _GATE + lat))
        cost = cost + np.where(ta != tb, cfg.type_mismatch_cost_m, 0.0)
        rows, cols = linear_sum_assignment(cost)
        for r, c in zip(rows.tolist(), cols.tolist()):
            if forbidden[r, c] or lat[r, c] > _FEATURE_MAX_M:
                continue
            x, y = int(xa[r]), int(yb[c])
            # the feature already continues next to y (or y is already reached next to x): skip
            if any(abs(float((flat.n_xy[z] - flat.n_xy[y]) @ n)) <= _DUPLICATE_M for z in out_adj.get(x)):
                continue
            if any(abs(float((flat.n_xy[w] - flat.n_xy[x]) @ n)) <= _DUPLICATE_M for w in in_adj.get(y)):
                continue
            out_adj.add(x, y)
            in_adj.add(y, x)
            self.out.features.append((x, y))

    def track_links(self, todo: list[tuple[int, bool]]) -> None:
        """RULE track: a start (end) still without a partner follows the path its pivot drove
        backward (forward) for ``track_search_m`` and links, topology only, to the first node
        that path enters (``tracks.track_partner``): a drive went there from the end."""
        flat, cfg, existing = self.flat, self.cfg, self.existing
        reach = self.reach()
        te = flat.topo_edges
        pred = Adjacency(te[:, 1], te[:, 0], flat.n_topo)
        for a, b in existing.added():
            pred.add(b, a)
        tracks, rows = pivot_tracks([self.graphs[k] for k in flat.keys], use_pose=cfg.track_pose)
        for i, is_end in todo:
            linked = bool(self.outdeg[i]) if is_end else bool(self.indeg[i])
            if linked and not cfg.track_linked_ends:
                continue
            g = self.graphs[flat.keys[flat.t_graph[i]]]
            track = tracks.get(g.pivot_drive or g.pivot_id)
            if track is None or len(track[0]) < 2:
                continue
            step = int(g.topo_step[flat.t_local[i]])
            r = int(np.searchsorted(g.track_step, step))
            if r >= len(g.track_step) or int(g.track_step[r]) != step:
                continue
            if linked:
                allowed = self._rejoin_allowed(i, is_end, pred)
            else:
                allowed = self.allowed(i, is_end)
            best = track_partner(flat, self.tree, i, is_end, track, int(rows[g.key][r]), cfg, reach, allowed)
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            if self.add_topo_link(a, b):
                pred.add(b, a)
                self.out.track_links += 1

    def _rejoin_allowed(self, i: int, is_end: bool, pred: Adjacency) -> Callable[[int], bool]:
        """RULE linked end: a linked end still follows its pivot: a node its track enters that the
        map does not reach from it within 2 track searches + 30 m gets a link too."""
        flat, cfg = self.flat, self.cfg
        walk, back = (self.existing, pred) if is_end else (pred, self.existing)
        far = 2.0 * cfg.track_search_m + 30.0
        near = reached_within(flat, walk, i, far)
        behind = reached_within(flat, back, i, far) if cfg.track_rejoin_both else set()
        existing = self.existing

        def allowed(j: int) -> bool:
            if j in near or closes_cycle(existing, i, j, is_end):
                return False
            if cfg.track_rejoin_m <= 0:
                return True
            # RULE rejoin: nor a node whose road runs on (back) into what the map reaches from the
            # end (start) within track_rejoin_m: the link would only add a side step
            # between two roads that join anyway
            if near & reached_within(flat, walk, j, cfg.track_rejoin_m):
                return False
            # RULE rejoin both: ... nor one whose road came from (runs on into) what reaches the end
            # (what the start reaches): the side step across a split (merge) behind it
            return not (behind and behind & reached_within(flat, back, j, cfg.track_rejoin_m))

        return allowed

    def bridge_links(self) -> None:
        """RULE track bridge: where a pivot's track leaves the map's node A, runs through steps that
        no node covers (failed steps at a junction, the road on both sides mapped by other pivots)
        and enters node B within ``track_bridge_m``, A is linked to B (topology only) unless the
        map reaches B from A within 2 * ``track_bridge_m`` + 30 m already or the link closes a
        short cycle: the pivot drove from A to B (``tracks.track_bridges``). Unlike the track search it
        needs no component start/end: the pivot's own chain may not exist there at all."""
        flat, cfg, existing = self.flat, self.cfg, self.existing
        reach = self.reach()
        limit = 2.0 * cfg.track_bridge_m + 30.0
        reached: dict[int, set[int]] = {}

        def near(a: int) -> set[int]:
            if a not in reached:
                reached[a] = reached_within(flat, existing, a, limit)
            return reached[a]

        tracks, _ = pivot_tracks([self.graphs[k] for k in flat.keys], use_pose=cfg.track_pose)
        for pid in sorted(tracks):
            xy, heading = tracks[pid]
            if len(xy) < 3:
                continue
            bridges = track_bridges(
                flat,
                self.tree,
                np.asarray(xy, dtype=float),
                np.asarray(heading, dtype=float),
                cfg,
                reach,
                lambda a, j: j in near(a),
            )
            for a, b in bridges:
                if b in near(a):
                    continue
                if closes_cycle(existing, a, b, True):
                    continue
                if self.add_topo_link(a, b):
                    self.out.bridge_links += 1
                    reached.clear()  # the map reaches more now

    def path_links(self, todo: list[tuple[int, bool]]) -> None:
        """RULE path: a start (end) still without a partner follows its chain's own arc backward
        (forward) for ``path_search_m`` and links, topology only, to the first node it enters
        (``links.path_partner``). Run after every start/end had its ordinary turn, so it takes no
        partner away from another's ordinary (feature-joining) link."""
        flat, cfg = self.flat, self.cfg
        te = flat.topo_edges
        pred = Adjacency(te[:, 1], te[:, 0], flat.n_topo)
        succ = self.existing
        reach = self.reach()
        for i, is_end in todo:
            if (is_end and self.outdeg[i]) or (not is_end and self.indeg[i]):
                continue
            rate = heading_rate(flat, pred if is_end else succ, i, _PATH_CURVATURE_M)
            if not is_end:
                rate = -rate  # measured from a later node back to the start: flip to driving sense
            best = path_partner(flat, self.tree, i, is_end, rate, cfg, reach, self.allowed(i, is_end))
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            if self.add_topo_link(a, b):
                self.out.path_links += 1
