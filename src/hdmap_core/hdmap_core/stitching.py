"""Inter-segment connection: segments stitched into the complete hierarchical map (Sec. VI).

Immel et al. 2023 keep the map as a hierarchical graph: a topology graph with one node per sampling
step (road midpoint, heading, width) and a road-feature graph of polylines, each referring to the
other. Every segment (one pivot drive, :class:`~hdmap_core.segment_graph.SegmentGraph`) carries such a
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
(``hdmap_core.graph``), type flicker smoothed, gore splits placed at the lane line's end and
isolated specks dropped.

Feature ids are the stable uid of a polyline's first feature node (hash of pivot id, step index and
slot), so the same input gives the same ids and adding an unrelated segment changes none.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from hdmap_core.segment_graph import SegmentGraph
from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.graph import (
    FlatGraph,
    _dedupe_uids,
    _map_edges,
    _remap,
    _spur_free,
    _unit,
    _wrap,
    export_map,
    graph_from_hdmap,
)
from hdmap_core.model import HDMap

__all__ = ["StitchConfig", "MapGraph", "stitch", "to_hdmap", "graph_from_hdmap"]

_BIG = 1.0e9
_GATE = 1.0e4
_TWIN_EDGE_REACH_M = 10.0  # half the longest gap the connection bridges by default (max_gap_m)
_BORDER_CODE = 3  # FeatureType.ROAD_BORDER

Link = tuple[str, int, str, int]  # (graph key, local index) -> (graph key, local index)


@dataclass(frozen=True)
class StitchConfig:
    """Parameters of the inter-segment connection (the paper gives no numbers).

    Attributes:
        max_distance_m: kd-tree search radius for a component end's neighbour [m].
        max_heading_diff_deg: the two topology nodes' headings differ at most this much [deg].
        max_connection_angle_deg: the link from one node to the other deviates at most this much
            from the driving direction (checked for links longer than ``angle_free_m``) [deg].
        angle_free_m: links shorter than this skip the connection-angle check [m].
        behind_tol_m: a predecessor may lie at most this far ahead of the start it links to
            (and a successor this far behind the end) [m].
        feature_max_m: features are joined across a link only when at most this far apart
            across the cut [m].
        same_type_only: join features of the same type only (the paper; default). False: a solid
            and a dashed marking may be joined too (at ``type_mismatch_cost_m`` extra cost), since
            their types flicker with misclassification; a road border still joins only a border.
            The polyline closes there (RULE 1) unless ``min_type_run_m`` relabels the short run.
            (Measured on one motorway_ramps run: no gain, so the paper's rule stays default.)
        type_mismatch_cost_m: assignment cost added to a solid-dashed pair [m].
        duplicate_m: a join is skipped when the feature already continues within this distance of
            the new partner (it would duplicate a polyline) [m].
        trim_overlap: drop component end nodes that lie on a place already in the map.
        trim_keep_longer: ... but only where the other graph's piece there is at least as long
            (in topology nodes) as the trimmed one; a shorter piece is trimmed instead (a pivot
            that sees only the last metres of a road must not cut a long pivot's end off and
            then be dropped as an isolated piece). False: every overlap trims the new graph.
        overlap_radius_m: a topology node this close to another graph's node with a similar
            heading is the same place [m] ...
        overlap_search_m: ... as is one up to this far away (midpoints of two pivots differ with
            their cut lines) at most ``overlap_along_m`` along the road, when at least
            ``overlap_share`` of its maxima (and 2) have a same-type twin within
            ``overlap_feature_m`` across the road [m].
        dedupe_loose_ends: drop dangling polyline ends/starts that run on top of another
            segment's polyline of the same class (``twin_lateral_m`` / ``twin_along_m``) [see
            ``MapGraph._dedupe_loose_ends``].
        twin_lateral_m: two feature nodes of different segments at most this far apart across
            the road ...
        twin_along_m: ... and this far along it (steps are 2 m apart) are one place [m].
        join_loose_ends: join polyline ends and starts of different segments that continue each
            other (same type, close across the cut) even where topology found no link.
        join_overlap_m: a loose start up to this far behind a loose end (the two overlap) is
            joined too, the end's overlapping nodes dropped [m].
        join_same_segment: also join loose ends of one segment (split there by a gap longer
            than the connection's ``max_gap_m``, RULE 3).
        join_radius_m: how far ahead of a loose end a loose start may begin [m].
        branch_lateral_m: a loose start (end) still unjoined then joins the nearest node of
            another segment's polyline of its type up to ``branch_radius_m`` behind (ahead) and
            this far across the road: a split (merge) across segments. 0 disables [m].
        branch_radius_m: see ``branch_lateral_m`` [m].
        branch_divergence_m: ... only when the branch moves away from the line: ~10 m on, its
            offset grew by at least this (a copy running beside the line is no branch) [m].
        branch_any_marking: a branch may join a lane marking of the other type (an exit's
            dashed line starts on the solid edge line; an entry's solid line ends on the dashed
            one); a road border joins only a border. False: same type only.
        join_lateral_m: how far across the road a loose start may lie from the end's arc [m] ...
        join_angle_deg: ... plus this angle's share of the distance [deg].
        join_line_heading_m: a loose end (start) is compared by its own polyline's direction,
            from the node at least this far back (on), instead of its topology node's heading (the
            pivot's, which leaves the lines where the pivot turns onto or off a ramp), when the
            two differ by more than ``join_line_heading_deg`` (a few metres of noisy nodes are a
            worse direction than the pivot's on an ordinary road). 0: the topology heading [m].
        join_line_heading_deg: see ``join_line_heading_m`` [deg].
        join_gap_check_m: a loose-end join longer than this is refused where drives passed
            through the gap but its neighbour lines were not mapped there either: some topology
            node (a pivot's step) lies in the middle half of the gap, within
            ``join_gap_lateral_m`` across the join and ``join_gap_heading_deg`` of its direction,
            while drive-supported feature nodes of that direction within ``join_gap_lateral_m``
            cover less than ``join_gap_coverage`` of the 2 m bins of the middle half. Every line of
            a road then ends at the same gap (a junction's mouth, where the steps failed): the
            straight fill across it is no drive's line. 0 disables (the paper) [m].
        join_gap_lateral_m: see ``join_gap_check_m`` [m].
        join_gap_heading_deg: see ``join_gap_check_m`` [deg].
        join_gap_coverage: see ``join_gap_check_m`` (share of bins, 0..1).
        join_line_cross_deg: a join longer than ``join_gap_check_m`` that passes only in its
            lines' direction (``join_line_heading_m``: where the pivot turned) is refused when a
            topology node in the middle half of the gap, within ``join_line_cross_lateral_m``
            across, heads more than this off the join: a pivot turning through a junction, whose
            lines all end at its mouth (carla_town06_30: three dashed lines filled straight
            across a junction, 30 false points each). 0 disables [deg].
        join_line_cross_lateral_m: see ``join_line_cross_deg`` [m].
        fill_spacing_m: a polyline edge longer than 1.5 x this (a bridged gap or join) is filled
            with points on a cubic Hermite curve through the end tangents, this far apart; the
            filled points carry drive_count 0 (no drive saw them). 0 disables [m].
        min_isolated_length_m: polylines without any link and shorter than this are dropped
            (single-step specks, false positives) [m].
        inner_border_max_m: a road border polyline without any link, seen by at most
            ``inner_border_max_drives`` drives, is dropped when at most of its drive-supported
            nodes lane markings of its direction lie within this distance on both sides: a
            border has the road on one side only, and one drive's marking reported as a border
            (1 % of marking stretches in the simulator) lies between two lane lines
            (carla_town04_30_s2: three such borders of 44-104 m, 115 false map points). 0
            disables (5 in the default pipeline preset) [m].
        inner_border_max_drives: see ``inner_border_max_m`` (max drive count over its nodes).
        sparse_type_run_m: a flicker run (between two runs of one other type) seen by at most
            ``sparse_drive_count`` drives (median) is relabelled when shorter than this (with
            1-3 drives one drive's misclassification sets the type for tens of metres). 0
            disables [m].
        sparse_drive_count: see ``sparse_type_run_m``.
        sparse_minority_only: ... and such a run of two or more drives only when the better
            supported run beside it has more drives (median): on the 30-drive CARLA fleets
            solid runs of 3 drives between dashed runs of 2-3 drives were real and relabelling
            them cost precision. False: any run of <= ``sparse_drive_count`` (True in the
            default pipeline preset).
        single_drive_run_m: a flicker run seen by one drive (median) is relabelled when shorter
            than this: one drive's type is no evidence against the type the line has before
            and after it, and a misclassified stretch is 20-200 m long (the simulator's blocks;
            on carla_town04_30_s1 two one-drive solid runs of 160-175 m between dashed runs
            held 171 of the 642 false map points); not when the run is longer than both runs
            beside it (one drive's solid 78 m, dashed 145 m, solid 77 m: the short runs are the
            likelier misclassification). 0 disables (250 in the default pipeline preset) [m].
        spur_max_m: a polyline shorter than this that hangs off a split without successor (or
            runs into a merge without predecessor) is a spur and is dropped. 0 disables [m].
        bubble_max_m: of two branches from one split node to one merge node (or a branch beside
            a direct edge between them) the one with fewer drives is dropped when shorter than
            this: lanes do not split and rejoin within it [m].
        gore_max_m: a common piece at most this long between a type change and a split into two
            polylines of its type (a gore's lines before they are resolved) is given to both
            branches, so the split sits where the lane line ends (merges alike). 0 disables [m].
        min_type_run_m: along a polyline, a run of one marking type (solid/dashed) shorter than
            this takes its neighbours' type instead of closing the polyline twice (RULE 1 on
            misclassification flicker). 0 disables (the paper) [m].
        merge_continuations: at export, a polyline whose only successor has it as its only
            predecessor, of the same type, is one polyline with it (what closed them, e.g. a
            leftover edge whose sibling branch was pruned or a one-point piece between them, is
            gone). False: the paper.
        link_within_component: a component start (end) that finds no partner in *another* weakly
            connected component may take one in its own (same geometric tests), as a topology link
            only (no feature join), unless that closes a cycle of fewer than ``_CYCLE_NODES``
            nodes. At a junction the main road's piece after a ramp is often joined to the map
            already through its other end, so its start stayed unlinked: the map's topology had
            no path from the incoming road to that branch (docs/evaluation.md, road-level splits
            and merges). On in the default preset only.
        path_search_m: a component start (end) still without a partner after every other
            component start/end had its turn follows its chain's own path backward (forward) up
            to this far: an arc from the node along its heading, turning at the chain's heading
            rate (over ``path_curvature_m`` of the chain). The first node whose cross-section
            (``topo_width`` / 2 across, one step along) the arc enters, with a heading within
            ``max_heading_diff_deg`` of the arc's there, in another component (or, with
            ``link_within_component``, in its own without closing a short cycle), is linked, as a
            topology link only (no feature join). A ramp's chain ends (an exit's starts) where
            its pivot's steps fail or reach a place mapped before, often still turning, 24-38 m
            from the gore: the main road within ``max_distance_m`` is 33-39 deg off the ramp's
            heading there, or the main road is beyond that radius (docs/graph.md). 0 disables
            (the paper; the plain default) [m].
        path_curvature_m: the chain's heading rate is taken over this much of it (chord from
            the node to the first chain node at least this far; shorter chains: straight) [m].
    """

    max_distance_m: float = 12.0
    max_heading_diff_deg: float = 30.0
    max_connection_angle_deg: float = 80.0
    angle_free_m: float = 3.0
    behind_tol_m: float = 1.0
    feature_max_m: float = 2.0
    same_type_only: bool = True
    type_mismatch_cost_m: float = 0.3
    duplicate_m: float = 0.25
    trim_overlap: bool = True
    trim_keep_longer: bool = True
    overlap_radius_m: float = 1.2
    overlap_search_m: float = 8.0
    overlap_along_m: float = 1.2
    overlap_feature_m: float = 0.5
    overlap_share: float = 0.6
    dedupe_loose_ends: bool = True
    twin_lateral_m: float = 0.5
    twin_along_m: float = 1.2
    join_loose_ends: bool = True
    join_same_segment: bool = True
    join_overlap_m: float = 8.0
    branch_lateral_m: float = 0.0
    branch_radius_m: float = 8.0
    branch_divergence_m: float = 0.3
    branch_any_marking: bool = True
    join_radius_m: float = 60.0
    join_lateral_m: float = 0.5
    join_angle_deg: float = 1.0
    join_line_heading_m: float = 4.0
    join_line_heading_deg: float = 10.0
    join_gap_check_m: float = 20.0
    join_gap_lateral_m: float = 12.0
    join_gap_heading_deg: float = 10.0
    join_gap_coverage: float = 0.8
    join_line_cross_deg: float = 0.0
    join_line_cross_lateral_m: float = 12.0
    fill_spacing_m: float = 2.0
    min_isolated_length_m: float = 20.0
    inner_border_max_m: float = 0.0
    inner_border_max_drives: int = 1
    min_type_run_m: float = 20.0
    sparse_type_run_m: float = 100.0
    sparse_drive_count: int = 5
    sparse_minority_only: bool = False
    single_drive_run_m: float = 0.0
    spur_max_m: float = 12.0
    bubble_max_m: float = 60.0
    gore_max_m: float = 100.0
    merge_continuations: bool = True
    link_within_component: bool = False
    path_search_m: float = 0.0
    path_curvature_m: float = 20.0
    through_lines: bool = True

    def __post_init__(self) -> None:
        for name in (
            "max_distance_m",
            "angle_free_m",
            "behind_tol_m",
            "feature_max_m",
            "type_mismatch_cost_m",
            "duplicate_m",
            "overlap_radius_m",
            "overlap_search_m",
            "overlap_along_m",
            "overlap_feature_m",
            "overlap_share",
            "join_radius_m",
            "join_overlap_m",
            "branch_lateral_m",
            "branch_radius_m",
            "branch_divergence_m",
            "twin_lateral_m",
            "twin_along_m",
            "join_lateral_m",
            "join_angle_deg",
            "join_line_heading_m",
            "join_line_heading_deg",
            "join_gap_check_m",
            "join_gap_lateral_m",
            "join_gap_heading_deg",
            "join_line_cross_deg",
            "join_line_cross_lateral_m",
            "fill_spacing_m",
            "min_isolated_length_m",
            "inner_border_max_m",
            "min_type_run_m",
            "sparse_type_run_m",
            "single_drive_run_m",
            "spur_max_m",
            "bubble_max_m",
            "gore_max_m",
            "path_search_m",
            "path_curvature_m",
        ):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be finite and >= 0, got {v}")
        for name in ("max_heading_diff_deg", "max_connection_angle_deg"):
            v = getattr(self, name)
            if not 0 < v <= 180:
                raise ConfigError(f"{name} must be in (0, 180], got {v}")
        if not 0.0 <= self.join_gap_coverage <= 1.0:
            raise ConfigError(f"join_gap_coverage must be in [0, 1], got {self.join_gap_coverage}")
        if self.inner_border_max_drives < 1:
            raise ConfigError(f"inner_border_max_drives must be >= 1, got {self.inner_border_max_drives}")

    @classmethod
    def paper(cls) -> StitchConfig:
        """The paper's variant: topology links and same-type unmodified assignment only."""
        return cls(
            same_type_only=True,
            trim_overlap=False,
            dedupe_loose_ends=False,
            join_loose_ends=False,
            min_isolated_length_m=0.0,
            inner_border_max_m=0.0,
            fill_spacing_m=0.0,
            join_line_heading_m=0.0,
            join_gap_check_m=0.0,
            join_line_cross_deg=0.0,
            min_type_run_m=0.0,
            sparse_type_run_m=0.0,
            sparse_minority_only=False,
            single_drive_run_m=0.0,
            spur_max_m=0.0,
            bubble_max_m=0.0,
            gore_max_m=0.0,
            merge_continuations=False,
            through_lines=False,
        )


class _GapCheck:
    """Whether a long loose-end join crosses a place drives passed with no line mapped beside it
    (``StitchConfig.join_gap_check_m``). Trees are built on first use."""

    LO, HI = 0.25, 0.75  # the middle half of the gap, along the join
    BIN_M = 2.0  # step spacing

    def __init__(self, flat: FlatGraph, node_heading: np.ndarray, cfg: StitchConfig) -> None:
        self._flat = flat
        self._node_heading = node_heading
        self._lat = cfg.join_gap_lateral_m
        self._cos = math.cos(math.radians(cfg.join_gap_heading_deg))
        self._cover = cfg.join_gap_coverage
        self._cross_cos = math.cos(math.radians(cfg.join_line_cross_deg)) if cfg.join_line_cross_deg > 0 else None
        self._cross_lat = cfg.join_line_cross_lateral_m
        self._ttree: cKDTree | None = None
        self._ntree: cKDTree | None = None
        self._nsup = np.zeros(0, dtype=np.int64)

    def _near(
        self, tree: cKDTree, xy: np.ndarray, p: np.ndarray, along: float, u: np.ndarray, n: np.ndarray, lat_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Points of ``tree`` in the middle half of the gap within ``lat_m`` across: (index, along)."""
        mid = p + 0.5 * (self.LO + self.HI) * along * u
        r = math.hypot(0.5 * (self.HI - self.LO) * along, lat_m)
        k = np.asarray(tree.query_ball_point(mid, r), dtype=np.int64)
        if len(k) == 0:
            return k, np.zeros(0)
        rel = xy[k] - p
        ra, rl = rel @ u, rel @ n
        ok = (ra > self.LO * along) & (ra < self.HI * along) & (np.abs(rl) < lat_m)
        return k[ok], ra[ok]

    def _trees(self) -> None:
        fl = self._flat
        if self._ttree is None:
            self._ttree = cKDTree(fl.t_xy) if len(fl.t_xy) else None
            self._nsup = np.flatnonzero(fl.n_count > 0)
            self._ntree = cKDTree(fl.n_xy[self._nsup]) if len(self._nsup) else None

    def crossed(self, p: np.ndarray, along: float, h: float, u: np.ndarray, n: np.ndarray) -> bool:
        """A topology node in the middle half of the join from ``p`` (``along`` m in direction
        ``h``), within ``join_line_cross_lateral_m`` across, heads more than
        ``join_line_cross_deg`` off it (False when the check is off)."""
        if self._cross_cos is None:
            return False
        self._trees()
        if self._ttree is None:
            return False
        fl = self._flat
        k, _ = self._near(self._ttree, fl.t_xy, p, along, u, n, self._cross_lat)
        return bool(np.any(np.cos(fl.t_heading[k] - h) < self._cross_cos))

    def unmapped(self, p: np.ndarray, along: float, h: float, u: np.ndarray, n: np.ndarray) -> bool:
        """A join from ``p`` ``along`` m in direction ``h`` (unit ``u``, normal ``n``) crosses a
        stretch drives passed (topology nodes in its middle half) whose lines beside it are missing
        too (drive-supported nodes cover < ``join_gap_coverage`` of its 2 m bins)."""
        fl = self._flat
        self._trees()
        if self._ttree is None:
            return False
        k, _ = self._near(self._ttree, fl.t_xy, p, along, u, n, self._lat)
        if not np.any(np.cos(fl.t_heading[k] - h) > self._cos):
            return False  # no drive went through the middle of the gap: nothing to hold against it
        if self._ntree is None:
            return True
        k, ra = self._near(self._ntree, fl.n_xy[self._nsup], p, along, u, n, self._lat)
        ra = ra[np.cos(self._node_heading[self._nsup[k]] - h) > self._cos]
        nb = max(1, int((self.HI - self.LO) * along / self.BIN_M))
        b = np.floor((ra / along - self.LO) / (self.HI - self.LO) * nb).astype(np.int64)
        return len(np.unique(b[(b >= 0) & (b < nb)])) < self._cover * nb


class _Adjacency:
    """Neighbour lookup over a fixed edge list (sorted, searched on demand) plus added edges."""

    def __init__(self, src: np.ndarray, dst: np.ndarray, n: int) -> None:
        order = np.argsort(src, kind="stable")
        self._dst = dst[order]
        self._ptr = np.searchsorted(src[order], np.arange(n + 1))
        self._extra: dict[int, list[int]] = {}

    def get(self, i: int) -> list[int]:
        out = self._dst[self._ptr[i] : self._ptr[i + 1]].tolist()
        return out + self._extra.get(i, [])

    def add(self, i: int, j: int) -> None:
        self._extra.setdefault(i, []).append(j)


def _line_heading(xy: np.ndarray, walk: np.ndarray, i: int, sign: float, min_m: float, hops: int = 6) -> float | None:
    """Heading of the polyline at its end (sign +1, ``walk`` = predecessor) or start (sign -1,
    ``walk`` = successor) node i, from the first node at least ``min_m`` along it (at most
    ``hops`` edges); None when the polyline is shorter."""
    k = i
    for _ in range(hops):
        k = int(walk[k])
        if k < 0:
            return None
        d = (xy[i] - xy[k]) * sign
        if math.hypot(d[0], d[1]) >= min_m:
            return math.atan2(d[1], d[0])
    return None


#: A within-component link is refused when it would close a cycle of fewer topology nodes (~1 km).
_CYCLE_NODES = 500


def _partner(
    flat: FlatGraph, tree: cKDTree, i: int, is_end: bool, cfg: StitchConfig, allowed: Callable[[int], bool]
) -> int:
    """The nearest topology node within ``max_distance_m`` that may continue the component end
    (start) node i (steps 2-3 of ``_stitch``: heading, behind/ahead, connection angle), among
    those ``allowed``; -1 if none."""
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    tan_c = math.tan(math.radians(min(cfg.max_connection_angle_deg, 89.999)))
    u, n = _unit(float(flat.t_heading[i]))
    best, best_d = -1, math.inf
    # 2. nearest neighbours in the complete topology graph (kd-tree)
    for j in tree.query_ball_point(flat.t_xy[i], cfg.max_distance_m):
        if math.cos(flat.t_heading[j] - flat.t_heading[i]) < cos_h or not allowed(j):
            continue
        d = flat.t_xy[j] - flat.t_xy[i] if is_end else flat.t_xy[i] - flat.t_xy[j]
        along, lat, dist = float(d @ u), abs(float(d @ n)), float(math.hypot(*d))
        # 3. distance and connection-angle check
        if along < -cfg.behind_tol_m:
            continue
        if dist > cfg.angle_free_m and lat > max(along, 0.0) * tan_c:
            continue
        if dist < best_d:
            best, best_d = int(j), dist
    return best


def _closes_cycle(successors: _Adjacency, i: int, j: int, is_end: bool) -> bool:
    """Would the link i -> j (``is_end``) or j -> i close a cycle of fewer than ``_CYCLE_NODES``
    nodes? (The link's head must not reach its tail already.)"""
    head, tail = (j, i) if is_end else (i, j)
    seen, todo = {head}, [head]
    while todo and len(seen) < _CYCLE_NODES:
        for k in successors.get(todo.pop()):
            if k == tail:
                return True
            if k not in seen:
                seen.add(k)
                todo.append(k)
    return False


#: Arc step of the path search (the step spacing) [m] and the shortest chord a heading rate is taken over [m].
_PATH_STEP_M = 2.0
_PATH_MIN_CHORD_M = 4.0


def _heading_rate(flat: FlatGraph, walk: _Adjacency, i: int, base_m: float) -> float:
    """Heading change per metre of the chain at its end (``walk`` = predecessors) or start
    (``walk`` = successors) node i: the heading difference to the first node of the chain at
    least ``base_m`` away (chord), or to the farthest one within 4 * base_m / step nodes; 0 when the
    chain is shorter than ``_PATH_MIN_CHORD_M`` [rad/m, sign of the driving direction]."""
    k, far, far_d = i, -1, 0.0
    for _ in range(max(1, int(4 * base_m / _PATH_STEP_M))):
        nxt = walk.get(k)
        if not nxt:
            break
        k = int(nxt[0])
        d = float(np.hypot(*(flat.t_xy[k] - flat.t_xy[i])))
        if d > far_d:
            far, far_d = k, d
        if d >= base_m:
            break
    if far < 0 or far_d < _PATH_MIN_CHORD_M:
        return 0.0
    return float(_wrap(flat.t_heading[i] - flat.t_heading[far])) / far_d


def _path_partner(
    flat: FlatGraph, tree: cKDTree, i: int, is_end: bool, rate: float, cfg: StitchConfig, reach_m: float,
    allowed: Callable[[int], bool],
) -> int:
    """The first topology node along the arc that continues the chain of end (start) node i
    forward (backward) with heading rate ``rate`` [rad/m] up to ``path_search_m``: the arc point
    lies in its cross-section (half its width across, one step along) and its heading is within
    ``max_heading_diff_deg`` of the arc's; among several at that point the nearest, among those
    ``allowed``; -1 if none (``StitchConfig.path_search_m``)."""
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    sign = 1.0 if is_end else -1.0
    p = flat.t_xy[i].astype(float).copy()
    h = float(flat.t_heading[i])
    u0, _ = _unit(h)
    n_steps = int(cfg.path_search_m / _PATH_STEP_M + 1e-9)
    for _ in range(n_steps):
        hm = h + sign * 0.5 * rate * _PATH_STEP_M  # heading in the middle of the arc step
        p = p + sign * _PATH_STEP_M * np.array([math.cos(hm), math.sin(hm)])
        h = h + sign * rate * _PATH_STEP_M
        best, best_d = -1, math.inf
        for j in tree.query_ball_point(p, reach_m):
            if j == i or math.cos(flat.t_heading[j] - h) < cos_h:
                continue
            if sign * float((flat.t_xy[j] - flat.t_xy[i]) @ u0) <= 0.0:
                continue  # behind an end (ahead of a start): the chain itself
            uj, nj = _unit(float(flat.t_heading[j]))
            rel = p - flat.t_xy[j]
            half = float(flat.t_width[j]) / 2.0 if math.isfinite(flat.t_width[j]) and flat.t_width[j] > 0 else 1.75
            if abs(float(rel @ uj)) > _PATH_STEP_M or abs(float(rel @ nj)) > half:
                continue
            d = float(np.hypot(*rel))
            if d < best_d and allowed(j):
                best, best_d = int(j), d
        if best >= 0:
            return best
    return -1


class _UnionFind:
    def __init__(self, labels: np.ndarray) -> None:
        self.parent = list(range(int(labels.max()) + 1 if len(labels) else 0))
        self.labels = labels

    def find(self, node: int) -> int:
        x = int(self.labels[node])
        while self.parent[x] != x:
            self.parent[x] = self.parent[self.parent[x]]
            x = self.parent[x]
        return x

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


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
        sizes: dict[str, np.ndarray] = {}
        spared: set[str] = set()

        def size_of(key: str) -> np.ndarray:
            if key not in sizes:
                g = self._graphs[key]
                out = np.zeros(g.n_topo, dtype=np.int64)
                for comp in g.components():
                    out[comp] = len(comp)
                sizes[key] = out
            return sizes[key]

        def walk(k: str) -> int:
            g, alive = self._graphs[k], self._alive[k]
            gi = flat.keys.index(k)
            own = size_of(k)

            def overlaps(t: int) -> bool:
                u, n = _unit(float(g.topo_heading[t]))
                fl = g.node_xy[g.topo_start[t] : g.topo_start[t + 1]] @ n
                ft = g.node_type[g.topo_start[t] : g.topo_start[t + 1]]
                radius = max(cfg.overlap_radius_m, cfg.overlap_search_m)
                for j in tree.query_ball_point(g.topo_xy[t], radius):
                    if flat.t_graph[j] == gi:
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
                    if cfg.trim_keep_longer and size_of(kj)[flat.t_local[j]] < own[t]:
                        spared.add(kj)
                        continue
                    return True
                return False

            killed = 0
            for comp in g.components():
                order = comp.tolist()
                for walk_order in (order, order[::-1]):
                    for t in walk_order:
                        if not alive[t] or not overlaps(t):
                            break
                        alive[t] = False
                        killed += 1
            return killed

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
            if b in existing.get(a):
                continue
            # 4. link the topology nodes and join their features
            existing.add(a, b)
            outdeg[a] += 1
            indeg[b] += 1
            uf.union(a, b)
            self._topo_links.add(self._link(flat, a, b, topo=True))
            rep.topology_links += 1
            if join:
                rep.feature_links += self._join_features(flat, a, b, out_adj, in_adj)
        if cfg.path_search_m > 0:
            self._path_links(flat, tree, todo, existing, indeg, outdeg, uf, rep)

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
        reach = math.hypot(_PATH_STEP_M, float(np.nanmax(np.where(flat.t_width > 0, flat.t_width, 3.5))) / 2.0)
        for i, is_end in todo:
            if (is_end and outdeg[i]) or (not is_end and indeg[i]):
                continue
            rate = _heading_rate(flat, pred if is_end else succ, i, cfg.path_curvature_m)
            if not is_end:
                rate = -rate  # measured from a later node back to the start: flip to driving sense

            def allowed(j: int, i: int = i, is_end: bool = is_end) -> bool:
                if uf.find(j) != uf.find(i):
                    return True
                return cfg.link_within_component and not _closes_cycle(existing, i, j, is_end)

            best = _path_partner(flat, tree, i, is_end, rate, cfg, reach, allowed)
            if best < 0:
                continue
            a, b = (i, best) if is_end else (best, i)
            if b in existing.get(a):
                continue
            existing.add(a, b)
            outdeg[a] += 1
            indeg[b] += 1
            uf.union(a, b)
            self._topo_links.add(self._link(flat, a, b, topo=True))
            rep.topology_links += 1
            rep.path_links += 1

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

    def _dedupe_loose_ends(self) -> int:
        """Drop the dangling ends of polylines that run on top of another segment's polyline.

        From every loose end (no successor) walk back, and from every loose start walk forward,
        while the node has a twin: a live feature node of another segment, of the same class
        (marking / border) within ``twin_lateral_m`` across and ``twin_along_m`` along the road,
        or on an edge of such a line within ``twin_lateral_m``. Those nodes map a place twice; the copy that
        continues survives, and the loose-end join then connects the rest.
        """
        cfg = self.config
        flat = self._flat()
        nn = flat.n_nodes
        if nn < 2:
            return 0
        e = flat.edges
        outdeg = np.bincount(e[:, 0], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        indeg = np.bincount(e[:, 1], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        nxt = np.full(nn, -1, dtype=np.int64)
        prv = np.full(nn, -1, dtype=np.int64)
        if len(e):
            one = (outdeg[e[:, 0]] == 1) & (indeg[e[:, 1]] == 1)
            nxt[e[one, 0]] = e[one, 1]
            prv[e[one, 1]] = e[one, 0]
        border = flat.n_type == _BORDER_CODE
        tree = cKDTree(flat.n_xy)
        alive = np.ones(nn, dtype=bool)

        heading = flat.t_heading[flat.node_topo()]
        # candidates up to half a bridged gap away: the other line may have no node next to j,
        # only an edge across a gap; j is a twin of a node or of an edge out of it
        reach = math.hypot(cfg.twin_along_m, cfg.twin_lateral_m) + _TWIN_EDGE_REACH_M
        out_adj = _Adjacency(e[:, 0], e[:, 1], nn)

        def close_to(j: int, k: int, n: np.ndarray, u: np.ndarray) -> bool:
            d = flat.n_xy[k] - flat.n_xy[j]
            if abs(float(d @ n)) <= cfg.twin_lateral_m and abs(float(d @ u)) <= cfg.twin_along_m:
                return True
            for k2 in out_adj.get(k):
                if not alive[k2] or k2 == j:
                    continue  # the edge into j itself (a stitch link) is no other line
                seg = flat.n_xy[k2] - flat.n_xy[k]
                length = float(math.hypot(*seg))
                if length < 1e-9:
                    continue
                t = float((flat.n_xy[j] - flat.n_xy[k]) @ seg) / length**2
                if 0.0 <= t <= 1.0:
                    off = flat.n_xy[k] + t * seg - flat.n_xy[j]
                    if float(math.hypot(*off)) <= cfg.twin_lateral_m:
                        return True
            return False

        def twin(j: int) -> bool:
            u, n = _unit(float(heading[j]))
            for k in tree.query_ball_point(flat.n_xy[j], reach):
                if alive[k] and flat.n_graph[k] != flat.n_graph[j] and border[k] == border[j]:
                    if close_to(j, int(k), n, u):
                        return True
            return False

        ends = [(int(flat.n_uid[i]), int(i), prv) for i in np.flatnonzero(outdeg == 0)]
        starts = [(int(flat.n_uid[i]), int(i), nxt) for i in np.flatnonzero(indeg == 0)]
        for _, i, step_to in sorted(ends + starts, key=lambda x: (x[0], x[1])):
            j = i
            while j >= 0 and alive[j] and twin(j):
                alive[j] = False
                j = int(step_to[j])
        dead = np.flatnonzero(~alive)
        for j in dead.tolist():
            k = flat.keys[flat.n_graph[j]]
            if k not in self._node_dead:
                self._node_dead[k] = np.zeros(self._graphs[k].n_nodes, dtype=bool)
            self._node_dead[k][flat.n_local[j]] = True
        return len(dead)

    def _join_loose_ends(self, rep: IntegrateReport) -> None:
        """Join polyline ends to polyline starts of other segments that continue them."""
        cfg = self.config
        flat = self._flat()
        nn = flat.n_nodes
        if nn < 2:
            return
        e = flat.edges
        outdeg = np.bincount(e[:, 0], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        indeg = np.bincount(e[:, 1], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        ends = np.flatnonzero(outdeg == 0)
        starts = np.flatnonzero(indeg == 0)
        if len(ends) == 0 and len(starts) == 0:
            return
        heading = flat.t_heading[flat.node_topo()]
        tree = cKDTree(flat.n_xy[starts])
        cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
        tan_j = math.tan(math.radians(cfg.join_angle_deg))
        prv = np.full(nn, -1, dtype=np.int64)
        nxt = np.full(nn, -1, dtype=np.int64)
        if len(e):
            one = (outdeg[e[:, 0]] == 1) & (indeg[e[:, 1]] == 1)
            prv[e[one, 1]] = e[one, 0]
            nxt[e[one, 0]] = e[one, 1]
        # the pivot's heading is no direction for a line it sees while turning onto or off a ramp
        # (a line's loose end beside an entry ramp's pivot, heading 35 deg off the line): ends and
        # starts whose own line leaves it are also compared in their lines' direction
        line_h = heading.copy()
        lim_l = math.radians(cfg.join_line_heading_deg)
        if cfg.join_line_heading_m > 0:
            for nodes, walk, sign in ((ends, prv, 1.0), (starts, nxt, -1.0)):
                for i in nodes.tolist():
                    h = _line_heading(flat.n_xy, walk, i, sign, cfg.join_line_heading_m)
                    if h is not None and abs(float(_wrap(h - heading[i]))) > lim_l:
                        line_h[i] = h
        gap = _GapCheck(flat, heading, cfg)
        cut: dict[tuple[int, int], tuple[int, list[int]]] = {}  # (end, start) -> (joined node, dropped)
        cand: list[tuple[float, int, int]] = []
        for i, near in zip(ends.tolist(), tree.query_ball_point(flat.n_xy[ends], cfg.join_radius_m)):
            for jj in near:
                j = int(starts[jj])
                if flat.n_graph[j] == flat.n_graph[i] and not cfg.join_same_segment:
                    continue
                if flat.n_type[j] != flat.n_type[i] and (
                    cfg.same_type_only or (flat.n_type[j] == _BORDER_CODE) != (flat.n_type[i] == _BORDER_CODE)
                ):
                    continue
                best: tuple[float, int, list[int]] | None = None
                for hh in (heading, line_h) if (line_h[i] != heading[i] or line_h[j] != heading[j]) else (heading,):
                    if math.cos(hh[j] - hh[i]) < cos_h:
                        continue
                    # on a circular arc the chord runs along the mean of the two tangents, so the
                    # chord's offset from that direction is the lateral error of the join, curvature-free
                    mean_h = hh[i] + 0.5 * float(_wrap(hh[j] - hh[i]))
                    u, n = _unit(mean_h)
                    d = flat.n_xy[j] - flat.n_xy[i]
                    along, lat = float(d @ u), abs(float(d @ n))
                    if lat > cfg.join_lateral_m + max(along, 0.0) * tan_j or along < -cfg.join_overlap_m:
                        continue
                    if 0 < cfg.join_gap_check_m < along and gap.unmapped(flat.n_xy[i], along, mean_h, u, n):
                        continue
                    # RULE turning join: passing in the lines' frame only where a pivot turned
                    # through the gap (a junction) is no continuation
                    if 0 < cfg.join_gap_check_m < along and hh is line_h and gap.crossed(flat.n_xy[i], along, mean_h, u, n):
                        continue
                    src, dropped = i, []
                    while along <= 0.0:  # the start lies beside the end: drop the end's overlap
                        if prv[src] < 0 or len(dropped) > 8:
                            break
                        dropped.append(src)
                        src = int(prv[src])
                        along = float((flat.n_xy[j] - flat.n_xy[src]) @ u)
                    if along <= 0.0:
                        continue
                    c = lat + 0.02 * along
                    if best is None or c < best[0]:
                        best = (c, src, dropped)
                if best is None:
                    continue
                cut[(i, j)] = (best[1], best[2])
                mismatch = cfg.type_mismatch_cost_m if flat.n_type[j] != flat.n_type[i] else 0.0
                cand.append((best[0] + mismatch, i, j))
        joined_e: set[int] = set()
        joined_s: set[int] = set()
        if cand:
            ei = sorted({c[1] for c in cand})
            sj = sorted({c[2] for c in cand})
            ri, cj = {v: k for k, v in enumerate(ei)}, {v: k for k, v in enumerate(sj)}
            cost = np.full((len(ei), len(sj)), _BIG)
            for c, i, j in cand:
                cost[ri[i], cj[j]] = min(cost[ri[i], cj[j]], c)
            rows, cols = linear_sum_assignment(cost)
            drop = np.ones(nn, dtype=bool)
            for r, c in zip(rows.tolist(), cols.tolist()):
                if cost[r, c] < _BIG:
                    src, dropped = cut[(ei[r], sj[c])]
                    drop[dropped] = False
                    self._feature_links.add(self._link(flat, src, sj[c], topo=False))
                    joined_e.add(ei[r])
                    joined_s.add(sj[c])
                    rep.loose_ends_joined += 1
            if not drop.all():
                self._kill(flat, lambda fl: drop)
        if cfg.branch_lateral_m > 0:
            rest_s = [int(j) for j in starts if int(j) not in joined_s]
            rest_e = [int(i) for i in ends if int(i) not in joined_e]
            rep.branches_joined += self._join_branches(flat, heading, rest_s, rest_e, e)

    def _join_branches(self, flat: FlatGraph, heading: np.ndarray, starts: list[int], ends: list[int], e: np.ndarray) -> int:
        """Join a polyline that starts (ends) beside another line of its type to that line: a
        split (merge) across segments, as the leftover assignment does inside one (Sec. V).

        A loose start joins the nearest node of another segment's polyline of the same type
        that lies behind it (0 < along <= ``branch_radius_m``) at most ``branch_lateral_m`` across
        the road; a loose end joins such a node ahead of it.
        """
        cfg = self.config
        if not starts and not ends:
            return 0
        tree = cKDTree(flat.n_xy)
        nn = flat.n_nodes
        outdeg = np.bincount(e[:, 0], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        indeg = np.bincount(e[:, 1], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        nxt = np.full(nn, -1, dtype=np.int64)
        prv = np.full(nn, -1, dtype=np.int64)
        if len(e):
            one = (outdeg[e[:, 0]] == 1) & (indeg[e[:, 1]] == 1)
            nxt[e[one, 0]] = e[one, 1]
            prv[e[one, 1]] = e[one, 0]

        def diverges(i: int, j: int, lat0: float, walk: np.ndarray) -> bool:
            """Whether the branch through i moves away from the line through j (not a twin
            running beside it): ~10 m on along the branch the offset grew by
            ``branch_divergence_m``."""
            k = i
            for _ in range(5):
                if walk[k] < 0:
                    break
                k = int(walk[k])
            if k == i:
                return False
            _, n = _unit(float(heading[k]))
            offs = [
                abs(float((flat.n_xy[q] - flat.n_xy[k]) @ n))
                for q in tree.query_ball_point(flat.n_xy[k], 6.0)
                if flat.n_graph[q] == flat.n_graph[j] and flat.n_type[q] == flat.n_type[j]
            ]
            return not offs or min(offs) >= lat0 + cfg.branch_divergence_m

        border = flat.n_type == _BORDER_CODE
        made = 0
        for nodes, sign, walk in ((starts, -1.0, nxt), (ends, 1.0, prv)):
            for i in nodes:
                u, n = _unit(float(heading[i]))
                best, best_d, best_lat = -1, math.inf, 0.0
                for j in tree.query_ball_point(flat.n_xy[i], cfg.branch_radius_m):
                    if flat.n_graph[j] == flat.n_graph[i]:
                        continue
                    if flat.n_type[j] != flat.n_type[i] and (
                        not cfg.branch_any_marking or border[j] or border[i]
                    ):
                        continue
                    if math.cos(heading[j] - heading[i]) < math.cos(math.radians(cfg.max_heading_diff_deg)):
                        continue
                    d = flat.n_xy[j] - flat.n_xy[i]
                    along, lat = sign * float(d @ u), abs(float(d @ n))
                    if along <= 0.0 or lat > cfg.branch_lateral_m:
                        continue
                    dist = math.hypot(along, lat)
                    if dist < best_d:
                        best, best_d, best_lat = int(j), dist, lat
                if best >= 0 and diverges(i, best, best_lat, walk):
                    a, b = (best, i) if sign < 0 else (i, best)
                    self._branch_links.add(self._link(flat, a, b, topo=False))
                    made += 1
        return made

    # -- export --
    def to_hdmap(
        self, *, version: int | None = None, stamp_ns: int = 0, drive_ids: Sequence[str] | None = None
    ) -> HDMap:
        """The complete map as an ``HDMap``: every field of MapFeature / TopologyNode filled."""
        flat = self._flat()
        if drive_ids is None:
            drive_ids = sorted({d for g in self._graphs.values() for d in g.drive_ids})
        features, topology = export_map(flat, self.config)
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
