"""Partners of component ends in the complete topology graph (Sec. VI, steps 2-3).

The nearest valid partner of a component start/end (``partner``: kd-tree, distance, heading and
connection-angle checks), the short-cycle guard of links inside one component (``closes_cycle``),
the bounded reach of a node along the map (``reached_within``) and the search along a chain's own
arc for an end that stops short of a junction (``path_partner``). ``linking.link_segments`` runs them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from hdmap_core.geometry import heading_frame, wrap_angle
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.stitch_config import StitchConfig

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: links shorter than this skip the connection-angle check [m].
_ANGLE_FREE_M = 3.0
#: a predecessor may lie at most this far ahead of the start it links to (and a successor this
#: far behind the end) [m].
_BEHIND_TOL_M = 1.0

__all__ = [
    "Adjacency",
    "PATH_STEP_M",
    "HALF_WIDTH_UNKNOWN_M",
    "partner",
    "reached_within",
    "closes_cycle",
    "heading_rate",
    "path_partner",
    "entered",
]

#: A within-component link is refused when it would close a cycle of fewer topology nodes (~1 km).
_CYCLE_NODES = 500

#: Slack of ``_features_overlap``: lines of one road seen by two pivots lie this far apart at most [m].
_OVERLAP_SLACK_M = 1.0

#: Arc step of the path search (the step spacing) [m] and the shortest chord a heading rate is taken over [m].
PATH_STEP_M = 2.0
_PATH_MIN_CHORD_M = 4.0

#: Half the cross-section of a topology node whose width is not known [m].
HALF_WIDTH_UNKNOWN_M = 1.75


class Adjacency:
    """Neighbour lookup over a fixed edge list (sorted, searched on demand) plus added edges.

    Args:
        src, dst: (E,) edge tails and heads.
        n: number of nodes.
    """

    def __init__(self, src: np.ndarray, dst: np.ndarray, n: int) -> None:
        order = np.argsort(src, kind="stable")
        self._src = np.asarray(src, dtype=np.int64)[order]
        self._dst = np.asarray(dst, dtype=np.int64)[order]
        self._ptr = np.searchsorted(self._src, np.arange(n + 1))
        self._n = n
        self._extra: dict[int, list[int]] = {}
        self._matrix: csr_matrix | None = None

    def get(self, i: int) -> list[int]:
        out = self._dst[self._ptr[i] : self._ptr[i + 1]].tolist()
        return out + self._extra.get(i, [])

    def add(self, i: int, j: int) -> None:
        self._extra.setdefault(i, []).append(j)
        self._matrix = None

    def added(self) -> list[tuple[int, int]]:
        """The edges added after construction, (i, j) pairs."""
        return [(i, j) for i, js in self._extra.items() for j in js]

    def matrix(self, xy: np.ndarray) -> csr_matrix:
        """(n, n) sparse matrix of every edge (added ones too) weighted by its length between
        node positions ``xy`` (n, 2) [m]; kept until the next ``add``. Repeated edges appear once
        (their lengths are equal), loops not at all."""
        if self._matrix is None:
            extra = np.asarray(self.added(), dtype=np.int64).reshape(-1, 2)
            src = np.concatenate([self._src, extra[:, 0]])
            dst = np.concatenate([self._dst, extra[:, 1]])
            pairs = np.unique(np.stack([src, dst], axis=1)[src != dst], axis=0)
            d = xy[pairs[:, 1]] - xy[pairs[:, 0]]
            w = np.hypot(d[:, 0], d[:, 1])
            # explicit zeros stay edges (csgraph reads the stored entries): nodes at one place
            self._matrix = csr_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(self._n, self._n))
        return self._matrix


def _half_widths(flat: FlatGraph, i: int, j: int) -> float:
    """Sum of the half road widths of topology nodes i and j (3.5 m for a width not known) [m]."""
    w = [float(flat.t_width[k]) if math.isfinite(flat.t_width[k]) and flat.t_width[k] > 0 else 3.5 for k in (i, j)]
    return 0.5 * (w[0] + w[1])


def _features_overlap(flat: FlatGraph, i: int, j: int, n: np.ndarray, share: float) -> bool:
    """Do the lateral spans (along ``n``) of topology nodes i's and j's features overlap by at
    least ``share`` of the narrower span (less ``_OVERLAP_SLACK_M``)? True when ``share`` is 0 or a
    node has no features (nothing to tell)."""
    if share <= 0:
        return True
    a, b = slice(flat.t_start[i], flat.t_start[i + 1]), slice(flat.t_start[j], flat.t_start[j + 1])
    la, lb = flat.n_xy[a] @ n, flat.n_xy[b] @ n
    if len(la) == 0 or len(lb) == 0:
        return True
    overlap = min(la.max(), lb.max()) - max(la.min(), lb.min())
    narrow = min(la.max() - la.min(), lb.max() - lb.min())
    return bool(overlap + _OVERLAP_SLACK_M >= share * narrow)


def partner(
    flat: FlatGraph, tree: cKDTree, i: int, is_end: bool, cfg: StitchConfig, allowed: Callable[[int], bool]
) -> int:
    """The nearest topology node within ``max_distance_m`` that may continue the component end
    (start) node i (steps 2-3 of ``_stitch``: heading, behind/ahead, connection angle), among
    those ``allowed``; -1 if none."""
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    tan_c = math.tan(math.radians(min(cfg.max_connection_angle_deg, 89.999)))
    tan_s = math.tan(math.radians(min(cfg.side_link_angle_deg, 89.999)))
    cos_p = math.cos(math.radians(cfg.partner_angle_deg))
    u, n = heading_frame(float(flat.t_heading[i]))
    best, best_d = -1, math.inf
    # 2. nearest neighbours in the complete topology graph (kd-tree)
    for j in tree.query_ball_point(flat.t_xy[i], cfg.max_distance_m):
        if math.cos(flat.t_heading[j] - flat.t_heading[i]) < cos_h or not allowed(j):
            continue
        d = flat.t_xy[j] - flat.t_xy[i] if is_end else flat.t_xy[i] - flat.t_xy[j]
        along, lat, dist = float(d @ u), abs(float(d @ n)), float(math.hypot(*d))
        # 3. distance and connection-angle check
        if along < -_BEHIND_TOL_M:
            continue
        if dist > _ANGLE_FREE_M and lat > max(along, 0.0) * tan_c:
            continue
        if (
            cfg.side_link_angle_deg < 90.0
            and lat > max(along, 0.0) * tan_s
            and (lat > _half_widths(flat, i, j) or not _features_overlap(flat, i, j, n, cfg.side_link_overlap))
        ):
            continue  # RULE: two roads side by side (cross-sections apart) join only at a shallow angle
        if cfg.partner_angle_deg < 180.0 and dist > _ANGLE_FREE_M:
            # RULE: the link also runs within partner_angle_deg of the partner's own heading
            if float(d @ heading_frame(float(flat.t_heading[j]))[0]) < cos_p * dist:
                continue
        if dist < best_d:
            best, best_d = int(j), dist
    return best


def reached_within(flat: FlatGraph, walk: Adjacency, i: int, limit_m: float) -> set[int]:
    """Topology nodes reached from node i along ``walk`` (successors or predecessors) within
    ``limit_m`` of path (straight edges between node positions), i included (Dijkstra,
    ``scipy.sparse.csgraph``)."""
    dist = dijkstra(walk.matrix(flat.t_xy), directed=True, indices=i, limit=limit_m)
    return set(np.flatnonzero(dist <= limit_m).tolist())


def closes_cycle(successors: Adjacency, i: int, j: int, is_end: bool) -> bool:
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


def heading_rate(flat: FlatGraph, walk: Adjacency, i: int, base_m: float) -> float:
    """Heading change per metre of the chain at its end (``walk`` = predecessors) or start
    (``walk`` = successors) node i: the heading difference to the first node of the chain at
    least ``base_m`` away (chord), or to the farthest one within 4 * base_m / step nodes; 0 when the
    chain is shorter than ``_PATH_MIN_CHORD_M`` [rad/m, sign of the driving direction]."""
    k, far, far_d = i, -1, 0.0
    for _ in range(max(1, int(4 * base_m / PATH_STEP_M))):
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
    return float(wrap_angle(flat.t_heading[i] - flat.t_heading[far])) / far_d


def path_partner(
    flat: FlatGraph,
    tree: cKDTree,
    i: int,
    is_end: bool,
    rate: float,
    cfg: StitchConfig,
    reach_m: float,
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
    u0, _ = heading_frame(h)
    n_steps = int(cfg.path_search_m / PATH_STEP_M + 1e-9)
    if rate != 0.0:  # RULE: no further than the arc turns path_max_turn_deg
        n_steps = min(n_steps, int(math.radians(cfg.path_max_turn_deg) / (abs(rate) * PATH_STEP_M) + 1e-9))
    for _ in range(n_steps):
        hm = h + sign * 0.5 * rate * PATH_STEP_M  # heading in the middle of the arc step
        p = p + sign * PATH_STEP_M * np.array([math.cos(hm), math.sin(hm)])
        h = h + sign * rate * PATH_STEP_M
        best = entered(flat, tree, i, sign, u0, p, h, cos_h, reach_m, allowed)
        if best >= 0:
            return best
    return -1


def _in_cross_section(flat: FlatGraph, j: int, p: np.ndarray) -> float:
    """Distance from topology node j to point p when p lies in j's cross-section (half its width
    across, ``HALF_WIDTH_UNKNOWN_M`` for a width not known; one step along), else inf [m].
    ``entered_by_points`` applies the same test to many points at once."""
    uj, nj = heading_frame(float(flat.t_heading[j]))
    rel = p - flat.t_xy[j]
    w = float(flat.t_width[j])
    half = w / 2.0 if math.isfinite(w) and w > 0 else HALF_WIDTH_UNKNOWN_M
    if abs(float(rel @ uj)) > PATH_STEP_M or abs(float(rel @ nj)) > half:
        return math.inf
    return float(np.hypot(*rel))


def entered(
    flat: FlatGraph,
    tree: cKDTree,
    i: int,
    sign: float,
    u0: np.ndarray,
    p: np.ndarray,
    h: float,
    cos_h: float,
    reach_m: float,
    allowed: Callable[[int], bool],
) -> int:
    """The nearest node (among those ``allowed``) whose cross-section point p, heading h, enters
    for the walk from end (``sign`` +1) or start (-1) node i with heading vector ``u0``; nodes
    heading more than acos(``cos_h``) off h and nodes behind an end (ahead of a start), the chain
    itself, do not count; -1 if none."""
    best, best_d = -1, math.inf
    for j in tree.query_ball_point(p, reach_m):
        if j == i or math.cos(flat.t_heading[j] - h) < cos_h:
            continue
        if sign * float((flat.t_xy[j] - flat.t_xy[i]) @ u0) <= 0.0:
            continue  # behind an end (ahead of a start): the chain itself
        d = _in_cross_section(flat, j, p)
        if d < best_d and allowed(j):
            best, best_d = int(j), d
    return best
