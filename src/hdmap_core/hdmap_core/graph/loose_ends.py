"""Loose ends of the stitched map (beyond the paper; Sec. VI).

Dangling polyline ends that run on top of another segment's line are de-duplicated
(``dedupe_loose_ends``), loose ends that continue each other are joined (``join_loose_ends``; the
gap is filled at export), and branches that start or end on a line's interior are linked (a split
or merge across segments). Plain functions of the map's flat view; the caller applies the result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from hdmap_core.geometry import heading_frame, wrap_angle
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.links import Adjacency
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.model import FeatureType

__all__ = ["LooseEndJoins", "dedupe_loose_ends", "join_loose_ends"]

#: a long join (``join_gap_check_m``) is refused where drives passed over at least this share of its
#: length and saw nothing there (0..1)
_JOIN_GAP_COVERAGE = 0.8

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: two feature nodes of different segments at most this far apart across the road ...
_TWIN_LATERAL_M = 0.5
#: ... and this far along it (steps are 2 m apart) are one place [m].
_TWIN_ALONG_M = 1.2
#: a branch start looks this far behind it for the line it leaves [m] ...
_BRANCH_RADIUS_M = 8.0
#: ... only when the branch moves away from the line: ~10 m on, its offset grew by at least this
#: (a copy running beside the line is no branch) [m].
_BRANCH_DIVERGENCE_M = 0.3
#: a branch may join a lane marking of the other type (an exit's dashed line starts on the solid
#: edge line; an entry's solid line ends on the dashed one); a road border joins only a border.
#: False: same type only.
_BRANCH_ANY_MARKING = True
#: how far across the road a loose start may lie from the end's arc [m] ...
_JOIN_LATERAL_M = 0.5
#: ... plus this angle's share of the distance [deg].
_JOIN_ANGLE_DEG = 1.0
#: a long join is refused where drives passed within this of its direction and saw nothing
#: (``join_gap_check_m``) [deg]
_JOIN_GAP_HEADING_DEG = 10.0
#: a join checked in its lines' frame is refused where a pivot's topology node in the middle of the
#: gap lies within this across it and turned (``join_line_cross_deg``) [m]
_JOIN_LINE_CROSS_LATERAL_M = 12.0

_BIG = 1.0e9
_TWIN_EDGE_REACH_M = 10.0  # half the longest gap the connection bridges by default (max_gap_m)
_BORDER_CODE = int(FeatureType.ROAD_BORDER)


@dataclass
class LooseEndJoins:
    """What ``join_loose_ends`` found, in global feature-node indices of its ``FlatGraph``.

    ``links``: (end, start) feature links joining loose ends; ``dropped``: (N,) bool, nodes of an
    end's overlap beside the start it joins, to drop; ``branch_links``: (a, b) split/merge links
    of branches to another segment's line (stored as leftover edges).
    """

    links: list[tuple[int, int]] = field(default_factory=list)
    dropped: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    branch_links: list[tuple[int, int]] = field(default_factory=list)


class _GapCheck:
    """Whether a long loose-end join crosses a place drives passed with no line mapped beside it
    (``StitchConfig.join_gap_check_m``). Trees are built on first use."""

    LO, HI = 0.25, 0.75  # the middle half of the gap, along the join
    BIN_M = 2.0  # step spacing

    def __init__(self, flat: FlatGraph, node_heading: np.ndarray, cfg: StitchConfig) -> None:
        self._flat = flat
        self._node_heading = node_heading
        self._lat = cfg.join_gap_lateral_m
        self._cos = math.cos(math.radians(_JOIN_GAP_HEADING_DEG))
        self._cover = _JOIN_GAP_COVERAGE
        self._cross_cos = math.cos(math.radians(cfg.join_line_cross_deg)) if cfg.join_line_cross_deg > 0 else None
        self._cross_lat = _JOIN_LINE_CROSS_LATERAL_M
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
        ``h``), within ``_JOIN_LINE_CROSS_LATERAL_M`` across, heads more than
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
        too (drive-supported nodes cover < ``_JOIN_GAP_COVERAGE`` of its 2 m bins)."""
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


def _chain_steps(e: np.ndarray, nn: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Out- and in-degree (nn,) of the feature graph with edges ``e`` (E, 2), and each node's next
    / previous node along an edge that is the only one out of its start and into its end (-1
    where there is none)."""
    outdeg = np.bincount(e[:, 0], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
    indeg = np.bincount(e[:, 1], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
    nxt = np.full(nn, -1, dtype=np.int64)
    prv = np.full(nn, -1, dtype=np.int64)
    if len(e):
        one = (outdeg[e[:, 0]] == 1) & (indeg[e[:, 1]] == 1)
        nxt[e[one, 0]] = e[one, 1]
        prv[e[one, 1]] = e[one, 0]
    return outdeg, indeg, nxt, prv


def dedupe_loose_ends(flat: FlatGraph) -> np.ndarray:
    """Drop the dangling ends of polylines that run on top of another segment's polyline.

    From every loose end (no successor) walk back, and from every loose start walk forward,
    while the node has a twin: a live feature node of another segment, of the same class
    (marking / border) within ``_TWIN_LATERAL_M`` across and ``_TWIN_ALONG_M`` along the road,
    or on an edge of such a line within ``_TWIN_LATERAL_M``. Those nodes map a place twice; the copy that
    continues survives, and the loose-end join then connects the rest.

    Returns:
        (N,) bool: the feature nodes to drop.
    """
    nn = flat.n_nodes
    if nn < 2:
        return np.zeros(nn, dtype=bool)
    e = flat.edges
    outdeg, indeg, nxt, prv = _chain_steps(e, nn)
    border = flat.n_type == _BORDER_CODE
    tree = cKDTree(flat.n_xy)
    alive = np.ones(nn, dtype=bool)

    heading = flat.t_heading[flat.node_topo()]
    # candidates up to half a bridged gap away: the other line may have no node next to j,
    # only an edge across a gap; j is a twin of a node or of an edge out of it
    reach = math.hypot(_TWIN_ALONG_M, _TWIN_LATERAL_M) + _TWIN_EDGE_REACH_M
    out_adj = Adjacency(e[:, 0], e[:, 1], nn)

    def close_to(j: int, k: int, n: np.ndarray, u: np.ndarray) -> bool:
        d = flat.n_xy[k] - flat.n_xy[j]
        if abs(float(d @ n)) <= _TWIN_LATERAL_M and abs(float(d @ u)) <= _TWIN_ALONG_M:
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
                if float(math.hypot(*off)) <= _TWIN_LATERAL_M:
                    return True
        return False

    def twin(j: int) -> bool:
        u, n = heading_frame(float(heading[j]))
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
    return ~alive


def join_loose_ends(flat: FlatGraph, *, config: StitchConfig) -> LooseEndJoins:
    """Join polyline ends to polyline starts of other segments that continue them (one
    rectangular assignment over all candidate pairs), and loose branches to the line they split
    from or merge into (``StitchConfig.branch_lateral_m``)."""
    cfg = config
    nn = flat.n_nodes
    out = LooseEndJoins(dropped=np.zeros(nn, dtype=bool))
    if nn < 2:
        return out
    e = flat.edges
    outdeg, indeg, nxt, prv = _chain_steps(e, nn)
    ends = np.flatnonzero(outdeg == 0)
    starts = np.flatnonzero(indeg == 0)
    if len(ends) == 0 and len(starts) == 0:
        return out
    heading = flat.t_heading[flat.node_topo()]
    tree = cKDTree(flat.n_xy[starts])
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    tan_j = math.tan(math.radians(_JOIN_ANGLE_DEG))
    # the pivot's heading is no direction for a line it sees while turning onto or off a ramp
    # (a line's loose end beside an entry ramp's pivot, heading 35 deg off the line): ends and
    # starts whose own line leaves it are also compared in their lines' direction
    line_h = heading.copy()
    lim_l = math.radians(cfg.join_line_heading_deg)
    if cfg.join_line_heading_m > 0:
        for nodes, walk, sign in ((ends, prv, 1.0), (starts, nxt, -1.0)):
            for i in nodes.tolist():
                h = _line_heading(flat.n_xy, walk, i, sign, cfg.join_line_heading_m)
                if h is not None and abs(float(wrap_angle(h - heading[i]))) > lim_l:
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
                (cfg.same_type_only and cfg.join_other_marking_m <= 0)
                or (flat.n_type[j] == _BORDER_CODE) != (flat.n_type[i] == _BORDER_CODE)
            ):
                continue
            # RULE other marking: a solid end and a dashed start (or the reverse) close ahead
            # are one line whose type flickered at the cut (``join_other_marking_m``)
            other_marking = bool(flat.n_type[j] != flat.n_type[i]) and cfg.same_type_only
            best: tuple[float, int, list[int]] | None = None
            for hh in (heading, line_h) if (line_h[i] != heading[i] or line_h[j] != heading[j]) else (heading,):
                if math.cos(hh[j] - hh[i]) < cos_h:
                    continue
                # on a circular arc the chord runs along the mean of the two tangents, so the
                # chord's offset from that direction is the lateral error of the join, curvature-free
                mean_h = hh[i] + 0.5 * float(wrap_angle(hh[j] - hh[i]))
                u, n = heading_frame(mean_h)
                d = flat.n_xy[j] - flat.n_xy[i]
                along, lat = float(d @ u), abs(float(d @ n))
                if lat > _JOIN_LATERAL_M + max(along, 0.0) * tan_j or along < -cfg.join_overlap_m:
                    continue
                if other_marking and along > cfg.join_other_marking_m:
                    continue
                if 0 < cfg.join_gap_check_m < along and gap.unmapped(flat.n_xy[i], along, mean_h, u, n):
                    continue
                # RULE turning join: passing in the lines' frame only where a pivot turned
                # through the gap (a junction) is no continuation
                if 0 < cfg.join_gap_check_m < along and hh is line_h and gap.crossed(flat.n_xy[i], along, mean_h, u, n):
                    continue
                src = i
                dropped: list[int] = []
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
                out.links.append((src, sj[c]))
                joined_e.add(ei[r])
                joined_s.add(sj[c])
        out.dropped = ~drop
    if cfg.branch_lateral_m > 0:
        rest_s = [int(j) for j in starts if int(j) not in joined_s]
        rest_e = [int(i) for i in ends if int(i) not in joined_e]
        out.branch_links = _join_branches(flat, heading, rest_s, rest_e, e, cfg)
    return out


def _join_branches(
    flat: FlatGraph, heading: np.ndarray, starts: list[int], ends: list[int], e: np.ndarray, cfg: StitchConfig
) -> list[tuple[int, int]]:
    """Join a polyline that starts (ends) beside another line of its type to that line: a
    split (merge) across segments, as the leftover assignment does inside one (Sec. V).

    A loose start joins the nearest node of another segment's polyline of the same type
    that lies behind it (0 < along <= ``_BRANCH_RADIUS_M``) at most ``branch_lateral_m`` across
    the road; a loose end joins such a node ahead of it.
    """
    if not starts and not ends:
        return []
    tree = cKDTree(flat.n_xy)
    nn = flat.n_nodes
    outdeg, indeg, nxt, prv = _chain_steps(e, nn)

    def diverges(i: int, j: int, lat0: float, walk: np.ndarray) -> bool:
        """Whether the branch through i moves away from the line through j (not a twin
        running beside it): ~10 m on along the branch the offset grew by
        ``_BRANCH_DIVERGENCE_M``."""
        k = i
        for _ in range(5):
            if walk[k] < 0:
                break
            k = int(walk[k])
        if k == i:
            return False
        _, n = heading_frame(float(heading[k]))
        offs = [
            abs(float((flat.n_xy[q] - flat.n_xy[k]) @ n))
            for q in tree.query_ball_point(flat.n_xy[k], 6.0)
            if flat.n_graph[q] == flat.n_graph[j] and flat.n_type[q] == flat.n_type[j]
        ]
        return not offs or min(offs) >= lat0 + _BRANCH_DIVERGENCE_M

    border = flat.n_type == _BORDER_CODE
    made: list[tuple[int, int]] = []
    for nodes, sign, walk in ((starts, -1.0, nxt), (ends, 1.0, prv)):
        for i in nodes:
            u, n = heading_frame(float(heading[i]))
            best, best_d, best_lat = -1, math.inf, 0.0
            for j in tree.query_ball_point(flat.n_xy[i], _BRANCH_RADIUS_M):
                if flat.n_graph[j] == flat.n_graph[i]:
                    continue
                if flat.n_type[j] != flat.n_type[i] and (not _BRANCH_ANY_MARKING or border[j] or border[i]):
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
                made.append((a, b))
    return made
