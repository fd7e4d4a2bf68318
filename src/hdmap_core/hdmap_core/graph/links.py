"""Links between the topology graphs of segments (``stitching.py``, Sec. VI): the nearest valid
partner of a component start/end (kd-tree, distance, heading and connection-angle checks), the
short-cycle guard of links inside one component, and the search along a chain's own arc for an
end that stops short of a junction. Private helpers of ``MapGraph``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.graph.flat import FlatGraph, _unit, _wrap
from hdmap_core.graph.stitch_config import StitchConfig


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

    def added(self) -> list[tuple[int, int]]:
        """The edges added after construction, (i, j) pairs."""
        return [(i, j) for i, js in self._extra.items() for j in js]


#: A within-component link is refused when it would close a cycle of fewer topology nodes (~1 km).
_CYCLE_NODES = 500


def _half_widths(flat: FlatGraph, i: int, j: int) -> float:
    """Sum of the half road widths of topology nodes i and j (3.5 m for a width not known) [m]."""
    w = [float(flat.t_width[k]) if math.isfinite(flat.t_width[k]) and flat.t_width[k] > 0 else 3.5 for k in (i, j)]
    return 0.5 * (w[0] + w[1])


#: Slack of ``_features_overlap``: lines of one road seen by two pivots lie this far apart at most [m].
_OVERLAP_SLACK_M = 1.0


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


def _partner(
    flat: FlatGraph, tree: cKDTree, i: int, is_end: bool, cfg: StitchConfig, allowed: Callable[[int], bool]
) -> int:
    """The nearest topology node within ``max_distance_m`` that may continue the component end
    (start) node i (steps 2-3 of ``_stitch``: heading, behind/ahead, connection angle), among
    those ``allowed``; -1 if none."""
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    tan_c = math.tan(math.radians(min(cfg.max_connection_angle_deg, 89.999)))
    tan_s = math.tan(math.radians(min(cfg.side_link_angle_deg, 89.999)))
    cos_p = math.cos(math.radians(cfg.partner_angle_deg))
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
        if (cfg.side_link_angle_deg < 90.0 and lat > max(along, 0.0) * tan_s
                and (lat > _half_widths(flat, i, j) or not _features_overlap(flat, i, j, n, cfg.side_link_overlap))):
            continue  # RULE: two roads side by side (cross-sections apart) join only at a shallow angle
        if cfg.partner_angle_deg < 180.0 and dist > cfg.angle_free_m:
            # RULE: the link also runs within partner_angle_deg of the partner's own heading
            if float(d @ _unit(float(flat.t_heading[j]))[0]) < cos_p * dist:
                continue
        if dist < best_d:
            best, best_d = int(j), dist
    return best


def _reached_within(flat: FlatGraph, walk: _Adjacency, i: int, limit_m: float) -> set[int]:
    """Topology nodes reached from node i along ``walk`` (successors or predecessors) within
    ``limit_m`` of path (straight edges between node positions), i included."""
    import heapq

    best = {i: 0.0}
    heap = [(0.0, i)]
    while heap:
        d, k = heapq.heappop(heap)
        if d > best.get(k, math.inf):
            continue
        for nxt in walk.get(k):
            dn = d + float(np.hypot(*(flat.t_xy[nxt] - flat.t_xy[k])))
            if dn <= limit_m and dn < best.get(nxt, math.inf):
                best[nxt] = dn
                heapq.heappush(heap, (dn, nxt))
    return set(best)


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
    if rate != 0.0:  # RULE: no further than the arc turns path_max_turn_deg
        n_steps = min(n_steps, int(math.radians(cfg.path_max_turn_deg) / (abs(rate) * _PATH_STEP_M) + 1e-9))
    for _ in range(n_steps):
        hm = h + sign * 0.5 * rate * _PATH_STEP_M  # heading in the middle of the arc step
        p = p + sign * _PATH_STEP_M * np.array([math.cos(hm), math.sin(hm)])
        h = h + sign * rate * _PATH_STEP_M
        best = _entered(flat, tree, i, sign, u0, p, h, cos_h, reach_m, allowed)
        if best >= 0:
            return best
    return -1


#: Half the cross-section of a topology node whose width is not known [m].
_HALF_WIDTH_UNKNOWN_M = 1.75


def _in_cross_section(flat: FlatGraph, j: int, p: np.ndarray) -> float:
    """Distance from topology node j to point p when p lies in j's cross-section (half its width
    across, ``_HALF_WIDTH_UNKNOWN_M`` for a width not known; one step along), else inf [m].
    ``_entered_by_points`` applies the same test to many points at once."""
    uj, nj = _unit(float(flat.t_heading[j]))
    rel = p - flat.t_xy[j]
    w = float(flat.t_width[j])
    half = w / 2.0 if math.isfinite(w) and w > 0 else _HALF_WIDTH_UNKNOWN_M
    if abs(float(rel @ uj)) > _PATH_STEP_M or abs(float(rel @ nj)) > half:
        return math.inf
    return float(np.hypot(*rel))


def _entered(
    flat: FlatGraph, tree: cKDTree, i: int, sign: float, u0: np.ndarray, p: np.ndarray, h: float, cos_h: float,
    reach_m: float, allowed: Callable[[int], bool],
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


def _track_partner(
    flat: FlatGraph, tree: cKDTree, i: int, is_end: bool, track: tuple[np.ndarray, np.ndarray],
    k: int, cfg: StitchConfig, reach_m: float, allowed: Callable[[int], bool],
) -> int:
    """The first topology node on the path the pivot of end (start) node i drove on from it
    (back to it): ``track`` = (xy, heading) of the pivot's steps in driving order, ``k`` = the
    row of node i's step. A track point within ``track_search_m`` (walked along the track's
    heading; the walk stops at a gap over ``track_max_gap_m`` along it or a jump over
    ``track_max_jump_m`` in any direction) lies in the node's cross-section and the node heads
    within ``max_heading_diff_deg`` of the track there; among several at that point the nearest,
    among those ``allowed``; -1 if none (``StitchConfig.track_search_m``). With
    ``track_settle_deg`` a point where the track is still turning onto the node's heading
    (``_still_turning``) lands nowhere: the walk goes on."""
    xy, heading = track
    if not 0 <= k < len(xy):
        return -1
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    sign = 1 if is_end else -1
    u0, _ = _unit(float(flat.t_heading[i]))
    walked = 0.0
    for m in range(k + sign, len(xy) if is_end else -1, sign):
        gap = _track_gap(xy, heading, m - sign, m, cfg)
        if gap is None:
            break
        walked += gap
        if walked > cfg.track_search_m:
            break
        best = _entered(flat, tree, i, sign, u0, xy[m], float(heading[m]), cos_h, reach_m, allowed)
        if best >= 0 and cfg.track_settle_deg > 0 and _still_turning(flat, best, xy, heading, m, sign, cfg):
            continue  # RULE: the pivot is still turning onto the road here: land where it has settled
        if best >= 0:
            return best
    return -1


def _track_gap(xy: np.ndarray, heading: np.ndarray, m: int, n: int, cfg: StitchConfig) -> float | None:
    """How far the pivot drove from track row m to row n: the step along row n's heading [m];
    None where the two are no consecutive places of one drive (a gap over ``track_max_gap_m``
    along, or a jump over ``track_max_jump_m`` in any direction). Along the heading because a
    failed step's cut midpoint may jump across the road (its cut refined to other borders) though
    the pivot drove on; a run processed before keeps only its first and last step: a gap."""
    step = xy[n] - xy[m]
    gap = abs(float(np.dot(step, _unit(float(heading[n]))[0])))
    if gap > cfg.track_max_gap_m or float(np.hypot(*step)) > cfg.track_max_jump_m:
        return None
    return gap


def _still_turning(
    flat: FlatGraph, j: int, xy: np.ndarray, heading: np.ndarray, m: int, sign: int, cfg: StitchConfig
) -> bool:
    """Is the track (``xy``, ``heading``) at row m, walked in direction ``sign``, still turning
    onto node j's heading (``StitchConfig.track_settle_deg``)? Its heading there lies more than
    2 * ``track_settle_deg`` off the node's and the next row of the walk (no gap: within
    ``track_max_gap_m`` along its heading and ``track_max_jump_m`` in any direction) within
    ``track_settle_deg`` of it: the pivot settles onto the road one step later."""
    settle = math.radians(cfg.track_settle_deg)
    hj = float(flat.t_heading[j])
    n = m + sign
    if abs(_wrap(float(heading[m]) - hj)) <= 2.0 * settle or not 0 <= n < len(xy):
        return False
    if _track_gap(xy, heading, m, n, cfg) is None:
        return False
    return abs(_wrap(float(heading[n]) - hj)) <= settle


def _entered_by_points(
    flat: FlatGraph, tree: cKDTree, xy: np.ndarray, heading: np.ndarray, cos_h: tuple[float, ...], reach_m: float,
    margin_m: float | tuple[float, ...] = 0.0,
) -> list[np.ndarray]:
    """Per heading limit in ``cos_h``: (K,) per track point (``xy`` (K, 2), ``heading`` (K,)) the
    nearest topology node whose cross-section (``_in_cross_section``, widened by ``margin_m`` to
    each side; a tuple: one margin per limit) it lies in with a heading within acos(limit) of the
    point's; -1 where none. One tree query serves every limit."""
    margins = tuple(float(m) for m in margin_m) if isinstance(margin_m, tuple) else (float(margin_m),) * len(cos_h)
    if len(margins) != len(cos_h):
        raise ValueError("one margin per heading limit")
    outs = [np.full(len(xy), -1, dtype=np.int64) for _ in cos_h]
    if len(xy) == 0 or flat.n_topo == 0:
        return outs
    hits = tree.query_ball_point(xy, reach_m + max(margins))
    owner = np.repeat(np.arange(len(xy)), [len(h) for h in hits])
    if len(owner) == 0:
        return outs
    j = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    hj = flat.t_heading[j]
    u = np.stack([np.cos(hj), np.sin(hj)], axis=1)
    rel = xy[owner] - flat.t_xy[j]
    along = np.abs((rel * u).sum(axis=1))
    across = np.abs(rel[:, 0] * u[:, 1] - rel[:, 1] * u[:, 0])
    w = flat.t_width[j]
    half = np.where(np.isfinite(w) & (w > 0), w / 2.0, _HALF_WIDTH_UNKNOWN_M)
    near = along <= _PATH_STEP_M
    owner, j, d, c = owner[near], j[near], np.hypot(rel[near, 0], rel[near, 1]), np.cos(hj - heading[owner])[near]
    across, half = across[near], half[near]
    order = np.lexsort((j, d, owner))  # per point the nearest first (ties: lowest index)
    owner, j, d, c, across, half = owner[order], j[order], d[order], c[order], across[order], half[order]
    for out, lim, mg in zip(outs, cos_h, margins):
        ok = (c >= lim) & (across <= half + mg) & (d <= reach_m + mg)
        o, jj = owner[ok], j[ok]
        first = np.r_[True, o[1:] != o[:-1]] if len(o) else np.zeros(0, dtype=bool)
        out[o[first]] = jj[first]
    return outs


def _track_bridges(
    flat: FlatGraph, tree: cKDTree, xy: np.ndarray, heading: np.ndarray, cfg: StitchConfig, reach_m: float,
    on_road: Callable[[int, int], bool],
) -> list[tuple[int, int]]:
    """(A, B) topology node pairs a pivot's track (``xy``, ``heading`` in driving order) bridges:
    the track leaves node A's cross-section, runs through at least one point that lies in no
    node's cross-section (within ``track_bridge_heading_deg``) for at most ``track_bridge_m``
    (two points further apart than ``track_max_gap_m`` end the walk), and enters node B's
    (``StitchConfig.track_bridge_m``). A is left running along it (within
    ``max_heading_diff_deg``; with ``track_bridge_leave_margin_m`` a point up to that far beyond
    A's cross-section leaves it too where the walk has no road to leave yet); points turning off
    it within ``track_bridge_heading_deg`` while still in the cross-section of a node A's road
    leads to (``on_road(A, node)``) keep A."""
    # leaving a road the track runs along it (within max_heading_diff_deg); entering one at a
    # merge it may still be turning (within track_bridge_heading_deg)
    cos_leave = math.cos(math.radians(cfg.max_heading_diff_deg))
    cos_enter = math.cos(math.radians(cfg.track_bridge_heading_deg))
    # RULE: with track_bridge_leave_margin_m a track that has no road to leave from (its start, or
    # after a gap: a run processed before keeps only its first and last step) leaves the road
    # whose cross-section, widened by the margin, its point lies in: the last point before a
    # junction's failed steps is a cut midpoint already pulled off the road's middle
    # (carla_town04_50_s1: 5.6 m across a node 4.8 m half wide). Only there: a bridge still ends
    # in a node's own cross-section, and a walk off a road is not cut short by the margin.
    if cfg.track_bridge_leave_margin_m > 0:
        leave, enter, wide = _entered_by_points(
            flat, tree, xy, heading, (cos_leave, cos_enter, cos_leave), reach_m, (0.0, 0.0, cfg.track_bridge_leave_margin_m),
        )
    else:
        leave, enter = _entered_by_points(flat, tree, xy, heading, (cos_leave, cos_enter), reach_m)
        wide = np.full(len(xy), -1, dtype=np.int64)
    out: list[tuple[int, int]] = []
    last, unmapped, walked = -1, 0, 0.0
    for m in range(len(xy)):
        if m > 0:
            # a bridge claims the pivot drove the track: consecutive points no further apart than
            # track_max_gap_m in any direction (the track search's jumps of failed steps' cut
            # midpoints, up to track_max_jump_m across, land on other roads at junctions)
            gap = float(np.hypot(*(xy[m] - xy[m - 1])))
            walked += gap
            if gap > cfg.track_max_gap_m:
                last, unmapped, walked = -1, 0, 0.0
        if enter[m] < 0:
            if last < 0 and wide[m] >= 0:
                leave[m] = wide[m]
                last, unmapped, walked = m, 0, 0.0
            else:
                unmapped += 1
            continue
        if last >= 0 and unmapped > 0 and walked <= cfg.track_bridge_m and leave[last] != enter[m]:
            out.append((int(leave[last]), int(enter[m])))
        if leave[m] >= 0:
            last, unmapped, walked = m, 0, 0.0
        elif unmapped > 0 or last < 0 or not on_road(int(leave[last]), int(enter[m])):
            last, unmapped, walked = -1, 0, 0.0  # entered at a merge angle: no road to leave from
        # else still on the road it left last (a node the map reaches from there), turning off
        # it: the bridge starts at the last point that ran along it
    return out


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
