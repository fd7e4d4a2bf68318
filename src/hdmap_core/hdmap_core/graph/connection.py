"""Connection of distribution maxima along one pivot drive (Sec. V of Immel et al. 2023).

The aggregated maxima of consecutive sampling steps are joined by a rectangular linear assignment
(``scipy.optimize.linear_sum_assignment``, Karp 1980); nodes left over at splits and merges are
joined to their nearest neighbour on the other side (the paper's modified assignment,
``assignment.py``). Steps whose
mean connection angle is implausible are rejected, road borders never connect to another type, and
steps without a result are bridged when the gap to the next valid step is short.

The result is a :class:`SegmentGraph`: the hierarchical graph of one segment (Sec. VI), a topology
graph with one node per used step (road midpoint, heading, width) and a road-feature graph whose
nodes are the maxima and whose edges are the connections (the data model is in
``segment_graph.py``). Polylines are the maximal chains of the feature graph that no closing rule
cuts (:func:`~hdmap_core.graph.segment_graph.feature_chains`):

- RULE 1: an edge joining two different types closes the polyline (a new one opens).
- RULE 2: an edge made by the leftover (modified) assignment closes it; splits and merges follow.
- RULE 3: a gap longer than ``max_gap_m`` closes it (no edge is made across the gap).
- RULE 4: a step already processed through another pivot (``StepResult.processed_before``)
  closes it (no edge, the topology chain breaks); stitching (Sec. VI) joins it to the other pivot.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from hdmap_core.errors import HdmapError
from hdmap_core.graph.assignment import assign
from hdmap_core.graph.connection_config import ConnectionConfig
from hdmap_core.graph.segment_graph import ConnectionStats, SegmentGraph, stable_uid
from hdmap_core.model import FeatureType
from hdmap_core.steps import Segment, StepResult, left_normal

__all__ = ["connect_segment"]

#: a step whose assigned connections have a mean angle (to the heading) above this is rejected
#: as an implausible optimisation result and bridged [deg].
_MAX_MEAN_ANGLE_DEG = 15.0

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: a tip's own line direction is taken from its node at least this far back (pivot travel): shorter
#: stretches are too noisy to give a direction [m]
_TIP_FRAME_MIN_M = 4.0
#: ... and by at most this: a pivot turning further is turning at an intersection, where a line
#: ending there must not continue straight across [deg].
_TIP_FRAME_MAX_DEG = 30.0
#: ... the line frame's direction falls back to the farthest node at least this far back [m]
_LINE_FRAME_MIN_M = 1.5

_BORDER = int(FeatureType.ROAD_BORDER)


# --- the connection of one segment ----------------------------------------------------------------


def _check_step(st: StepResult) -> None:
    """Raise when a step that will be used has inconsistent arrays or a non-finite pose."""
    k = np.shape(st.lateral_m)
    for name in ("types", "counts", "std_m"):
        if np.shape(getattr(st, name)) != k:
            raise HdmapError(
                f"step {st.index} of pivot {st.pivot_id!r}: {name} has shape {np.shape(getattr(st, name))}, "
                f"lateral_m has {k}"
            )
    if not _pose_ok(st):
        raise HdmapError(f"step {st.index} of pivot {st.pivot_id!r}: midpoint/heading missing or not finite")


def _separate(
    lat: np.ndarray, types: np.ndarray, counts: np.ndarray, min_sep_m: float, ratio: float = 1.0
) -> np.ndarray | None:
    """Indices of the maxima to keep when markings (or borders) of one step lie closer than
    ``min_sep_m`` and one has at most ``ratio`` times the drives of the other: the better
    supported one wins (two lines about to diverge have similar support and both stay).
    None: keep all (the common case, no copy)."""
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
        if all(
            border[i] != border[j] or abs(lat[i] - lat[j]) >= min_sep_m or counts[i] > ratio * counts[j] for j in kept
        ):
            kept.append(i)
    return np.sort(np.asarray(kept, dtype=np.int64))


@dataclass
class _Steps:
    """The valid steps of a segment, flattened: maxima sorted by lateral position within a step.

    Step j owns maxima ``off[j]:off[j + 1]``; ``slot`` is each maximum's index in its step's own
    arrays (the stable slot of its id).
    """

    steps: list[StepResult]
    off: np.ndarray
    lat: np.ndarray
    xy: np.ndarray
    typ: np.ndarray
    cnt: np.ndarray
    std: np.ndarray
    slot: np.ndarray
    fast: np.ndarray  # (J,) bool: step j continues step j-1 by the identity pairing, all plausible


def _flatten(valid: list[StepResult], config: ConnectionConfig) -> _Steps:
    k = np.array([len(st.lateral_m) for st in valid], dtype=np.int64)
    off = np.concatenate([[0], np.cumsum(k)]).astype(np.int64)
    j_of = np.repeat(np.arange(len(valid)), k)
    lat = np.concatenate([np.asarray(st.lateral_m, dtype=float).reshape(-1) for st in valid])
    typ = np.concatenate([np.asarray(st.types, dtype=np.int64).reshape(-1) for st in valid])
    cnt = np.concatenate([np.asarray(st.counts).reshape(-1) for st in valid]).astype(np.int64)
    std = np.concatenate([np.asarray(st.std_m, dtype=float).reshape(-1) for st in valid])
    slot = np.arange(len(lat)) - off[j_of]
    keep = np.isfinite(lat)
    by_place = np.lexsort((lat, j_of))  # the maxima by step, then lateral position
    if config.min_support_share > 0:
        n_drives = np.array([max(len(st.drive_ids), 1) for st in valid])[j_of]
        ok = cnt >= config.min_support_share * n_drives
        if config.support_window_m > 0:
            ref = _local_max_count(j_of, lat, cnt, off, config.support_window_m)
            ok |= (cnt >= config.min_support_share * ref) & (cnt >= config.window_min_count)
        if config.lone_line_gap_m > 0:
            bgap = config.lone_line_gap_m if config.lone_line_border_gap_m is None else config.lone_line_border_gap_m
            ok |= _lone_lines(
                by_place[keep[by_place]],
                j_of,
                lat,
                typ,
                config.lone_line_gap_m,
                bgap,
                outer_only=config.lone_line_border_outer,
            ) & (cnt >= config.window_min_count)
        keep &= ok
    if config.min_separation_m > 0:
        keep &= _separate_all(j_of, lat, typ, cnt, config.min_separation_m, config.separation_count_ratio)
    order = by_place[keep[by_place]]
    j_of, lat, typ, cnt, std, slot = j_of[order], lat[order], typ[order], cnt[order], std[order], slot[order]
    k = np.bincount(j_of, minlength=len(valid))
    off = np.concatenate([[0], np.cumsum(k)]).astype(np.int64)
    mid = np.array([np.asarray(st.midpoint, dtype=float) for st in valid]).reshape(-1, 2)
    hdg = np.array([float(st.heading) for st in valid])
    nrm = left_normal(hdg)
    xy = mid[j_of] + lat[:, None] * nrm[j_of]
    return _Steps(valid, off, lat, xy, typ, cnt, std, slot, _fast_pairs(valid, off, xy, typ, hdg, config))


def _lone_lines(
    order: np.ndarray,
    j_of: np.ndarray,
    lat: np.ndarray,
    typ: np.ndarray,
    gap_m: float,
    border_gap_m: float,
    *,
    outer_only: bool = False,
) -> np.ndarray:
    """(M,) bool: of the maxima ``order`` (the valid ones, sorted by step, then lateral position),
    those whose neighbours among them in their step (next lower and next higher lateral position)
    are both at least ``gap_m`` away (a missing neighbour counts as far); for a marking, a
    road-border neighbour need only be ``border_gap_m`` away (an edge line), with ``outer_only``
    only on the marking's outer side (lateral position farther from 0, the cut's midpoint)."""
    out = np.zeros(len(lat), dtype=bool)
    if len(order) == 0:
        return out
    j = j_of[order]
    new = np.r_[True, j[1:] != j[:-1]]
    end = np.r_[j[1:] != j[:-1], True]
    x = lat[order]
    border = typ[order] == _BORDER
    gap_next = np.where(end, np.inf, np.r_[np.diff(x), np.inf])
    gap_prev = np.where(new, np.inf, np.r_[np.inf, np.diff(x)])
    edge_next = ~border & np.r_[border[1:], False]
    edge_prev = ~border & np.r_[False, border[:-1]]
    if outer_only:  # the border of an edge line lies outward: higher lateral left of 0, lower right of it
        edge_next &= x > 0
        edge_prev &= x < 0
    need_next = np.where(edge_next, border_gap_m, gap_m)
    need_prev = np.where(edge_prev, border_gap_m, gap_m)
    out[order[(gap_prev >= need_prev) & (gap_next >= need_next)]] = True
    return out


def _local_max_count(
    j_of: np.ndarray, lat: np.ndarray, cnt: np.ndarray, off: np.ndarray, window_m: float
) -> np.ndarray:
    """(M,) the largest count among the maxima of the same step within ``window_m`` laterally
    (itself included). j_of (M,) step of each maximum (maxima grouped by step, ``off`` (J+1,)
    the CSR offsets), lat (M,) lateral position [m], cnt (M,) drive counts."""
    k = np.diff(off)
    # All ordered pairs (a, b) within each step: a repeats k times, b runs over the step.
    a = np.repeat(np.arange(len(lat)), k[j_of])
    first = off[j_of][np.repeat(np.arange(len(lat)), k[j_of])]
    b = first + (np.arange(len(a)) - np.repeat(np.cumsum(k[j_of]) - k[j_of], k[j_of]))
    near = np.abs(lat[a] - lat[b]) <= window_m
    ref = cnt.astype(np.int64).copy()
    np.maximum.at(ref, a[near], cnt[b[near]])
    return ref


def _separate_all(
    j_of: np.ndarray, lat: np.ndarray, typ: np.ndarray, cnt: np.ndarray, min_sep_m: float, ratio: float
) -> np.ndarray:
    """(M,) bool keep-mask: a marking (or border) within ``min_sep_m`` of a better supported one of
    the same class in the same step is one feature seen twice and is dropped."""
    keep = np.ones(len(lat), dtype=bool)
    cls = (typ == _BORDER).astype(np.int64)
    order = np.lexsort((lat, cls, j_of))
    same = (j_of[order][1:] == j_of[order][:-1]) & (cls[order][1:] == cls[order][:-1])
    close = same & (np.diff(lat[order]) < min_sep_m)
    if not close.any():
        return keep
    for j in np.unique(j_of[order][1:][close]).tolist():
        idx = np.flatnonzero(j_of == j)
        sel = _separate(lat[idx], typ[idx], cnt[idx], min_sep_m, ratio)
        if sel is not None:
            drop = np.ones(len(idx), dtype=bool)
            drop[sel] = False
            keep[idx[drop]] = False
    return keep


def _fast_pairs(
    valid: list[StepResult], off: np.ndarray, xy: np.ndarray, typ: np.ndarray, hdg: np.ndarray, config: ConnectionConfig
) -> np.ndarray:
    """Which steps continue the previous valid step by the identity pairing of their sorted maxima
    with every edge plausible and flat (the common case; the same result the assignment gives)."""
    n = len(valid)
    fast = np.zeros(n, dtype=bool)
    if n < 2:
        return fast
    k = np.diff(off)
    s_m = np.array([float(st.s_m) for st in valid])
    cand = np.zeros(n, dtype=bool)
    cand[1:] = (k[1:] == k[:-1]) & (k[1:] > 0) & ((s_m[1:] - s_m[:-1]) <= config.max_gap_m)
    j = np.flatnonzero(cand)
    if len(j) == 0:
        return fast
    # element-wise: maxima of step j against those of step j-1 at the same rank
    kk = k[j]
    elem_j = np.repeat(j, kk)
    cur = (
        np.concatenate([np.arange(off[a], off[a + 1]) for a in j.tolist()])
        if len(j) < 64
        else (np.repeat(off[j], kk) + (np.arange(kk.sum()) - np.repeat(np.cumsum(kk) - kk, kk)))
    )
    prev = cur - off[elem_j] + off[elem_j - 1]
    d = xy[cur] - xy[prev]
    c, sn = np.cos(hdg[elem_j]), np.sin(hdg[elem_j])
    along = d[:, 0] * c + d[:, 1] * sn
    lat = np.abs(-d[:, 0] * sn + d[:, 1] * c)
    tan_e = math.tan(math.radians(min(config.max_edge_angle_deg, 89.999)))
    tan_m = math.tan(math.radians(_MAX_MEAN_ANGLE_DEG))
    slack = config.edge_slack_m if config.mean_angle_slack else 0.0
    ok = (
        (typ[cur] == typ[prev])
        & (along > 0)
        & (lat <= config.edge_slack_m + along * tan_e)
        & (lat <= slack + along * tan_m)
    )
    bad = np.bincount(elem_j[~ok], minlength=n)
    fast[j] = bad[j] == 0
    return fast


class _Builder:
    """Accumulates the used steps and the edges of a SegmentGraph."""

    def __init__(self, flat: _Steps) -> None:
        self.f = flat
        self.used: list[int] = []  # valid-step index j of each topology node
        self.node_base: list[int] = []  # first node index of each topology node
        self.topo_edges: list[tuple[int, int]] = []
        self.fast_links: list[int] = []  # topology node t continues t-1 by identity
        self.edges: list[tuple[int, int]] = []
        self.leftover: list[bool] = []
        self.n = 0
        m = len(flat.lat)
        self.flat_of = np.full(m, -1, dtype=np.int64)  # row of each node in the flattened steps
        self.pred = np.full(m, -1, dtype=np.int64)  # each node's predecessor on its line (-1: none yet)

    def add(self, j: int) -> int:
        self.used.append(j)
        self.node_base.append(self.n)
        a, b = int(self.f.off[j]), int(self.f.off[j + 1])
        self.flat_of[self.n : self.n + b - a] = np.arange(a, b)
        self.n += b - a
        return len(self.used) - 1

    @functools.cached_property
    def _xy_list(self) -> list[list[float]]:
        """The steps' points as Python floats, for the per-line walks."""
        return self.f.xy.tolist()

    def _walk(self, node: int) -> Iterator[tuple[int, float, float]]:
        """(predecessor, dx, dy from it to ``node``) along the line ending in ``node``, nearest first."""
        xy, fo, pred = self._xy_list, self.flat_of, self.pred
        px, py = xy[fo[node]]
        q = node
        while True:
            q = int(pred[q])
            if q < 0:
                return
            qx, qy = xy[fo[q]]
            yield q, px - qx, py - qy

    def line_directions(self, nodes: np.ndarray, min_m: float, far_m: float = 4.0, hops: int = 6) -> np.ndarray:
        """(n, 2) unit direction of the line ending in each node: from its first predecessor at
        least ``far_m`` back (at most ``hops`` edges), else from the farthest one at least
        ``min_m`` back; NaN where there is none. (A walk per line in Python: a step has a handful
        of lines, and an array walk's per-call cost was 10x this on the fast path.)"""
        chosen = np.full(len(nodes), -1, dtype=np.int64)
        for r, node in enumerate(nodes.tolist()):
            best = 0.0
            for _, (q, dx, dy) in zip(range(hops), self._walk(node)):
                dist = math.hypot(dx, dy)
                if dist >= min_m and dist > best:
                    chosen[r], best = q, dist
                if dist >= far_m:
                    break
        out = np.full((len(nodes), 2), np.nan)
        has = chosen >= 0
        if has.any():
            d = self.f.xy[self.flat_of[nodes[has]]] - self.f.xy[self.flat_of[chosen[has]]]
            out[has] = d / np.hypot(d[:, 0], d[:, 1])[:, None]
        return out

    def line_bends(self, nodes: np.ndarray, dirs: np.ndarray, min_m: float, hops: int = 6) -> np.ndarray:
        """(n,) how far each line's history bends [deg]: the largest angle between its direction
        ``dirs`` (from ``line_directions``) and the direction from any predecessor at least
        ``min_m`` back (within ``hops`` edges) to its node; 0 where there is none."""
        out = np.zeros(len(nodes))
        for r, node in enumerate(nodes.tolist()):
            ux, uy = dirs[r]
            if not math.isfinite(ux):
                continue
            for _, (_, dx, dy) in zip(range(hops), self._walk(node)):
                dist = math.hypot(dx, dy)
                if dist >= min_m:
                    c = min(1.0, max(-1.0, (dx * ux + dy * uy) / dist))
                    out[r] = max(out[r], math.degrees(math.acos(c)))
        return out

    def tips_of(self, t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Node indices, points and types of topology node t."""
        j = self.used[t]
        a, b = int(self.f.off[j]), int(self.f.off[j + 1])
        return np.arange(self.node_base[t], self.node_base[t] + b - a), self.f.xy[a:b], self.f.typ[a:b]


def _tip_frames(
    b: _Builder, tip_idx: np.ndarray, gap_m: np.ndarray, heading: float, config: ConnectionConfig
) -> np.ndarray | None:
    """(n, 2) own line direction of each tip at least ``_TIP_FRAME_MIN_M`` back (pivot
    travel ``gap_m``) that leaves the step heading by more than ``config.tip_frame_deg`` (NaN for
    the others); None when no tip does."""
    if config.tip_frame_deg <= 0 or len(tip_idx) == 0:
        return None
    far = gap_m >= _TIP_FRAME_MIN_M
    if not far.any():
        return None
    # the first predecessor at least _TIP_FRAME_MIN_M back
    u = np.full((len(tip_idx), 2), np.nan)
    u[far] = b.line_directions(tip_idx[far], _TIP_FRAME_MIN_M, far_m=_TIP_FRAME_MIN_M)
    dev = _leaves_heading(u, heading, config.tip_frame_deg, _TIP_FRAME_MAX_DEG)
    if not dev.any():
        return None
    out = np.full((len(tip_idx), 2), np.nan)
    out[dev] = u[dev]
    return out


def _leaves_heading(u: np.ndarray, heading: float, min_deg: float, max_deg: float) -> np.ndarray:
    """(n,) bool: unit directions ``u`` (NaN rows: none) that leave ``heading`` by more than
    ``min_deg`` and at most ``max(max_deg, min_deg)``."""
    c = u @ np.array([math.cos(heading), math.sin(heading)])
    cos_max = math.cos(math.radians(min_deg))
    top = max(max_deg, min_deg)
    cos_lim = -math.inf if top >= 180.0 else math.cos(math.radians(top))
    return np.isfinite(c) & (c < cos_max) & (c >= cos_lim)


def _line_frames(
    b: _Builder, tip_idx: np.ndarray, heading: float, config: ConnectionConfig
) -> tuple[np.ndarray, np.ndarray] | None:
    """Own line directions of the tips (NaN rows: none), as (frame, check):

    - frame (n, 2): of each tip whose line leaves the step heading by more than
      ``config.line_frame_deg`` and at most ``line_frame_max_deg``: paired in that frame;
    - check (n, 2): of each tip whose line leaves it by more (at most ``line_check_max_deg``):
      paired in the pivot's frame, but an edge implausible in the line's own frame is not made.

    None when no tip's line leaves the heading by more than ``line_frame_deg``."""
    if config.line_frame_deg <= 0 or len(tip_idx) == 0:
        return None
    # the directions alone first: on most steps no line leaves the heading and the history's
    # bend, a walk over all 6 edges, is not needed (connection 0.8 -> 5-6 s on paper_like_134_s1
    # when every step walked it)
    u = b.line_directions(tip_idx, _LINE_FRAME_MIN_M)
    dev = _leaves_heading(u, heading, config.line_frame_deg, config.line_frame_max_deg)
    # beyond line_frame_max_deg (up to line_check_max_deg): checked only
    far = (
        _leaves_heading(u, heading, max(config.line_frame_max_deg, config.line_frame_deg), config.line_check_max_deg)
        if config.line_frame_check
        else np.zeros(len(u), dtype=bool)
    )
    if not (dev.any() or far.any()):
        return None
    if config.line_frame_bend_deg > 0:
        straight = b.line_bends(tip_idx, u, _LINE_FRAME_MIN_M) <= config.line_frame_bend_deg
        dev &= straight
        far &= straight
        if not (dev.any() or far.any()):
            return None
    out = np.full((len(tip_idx), 2), np.nan)
    out[dev] = u[dev]
    chk = np.full((len(tip_idx), 2), np.nan)
    chk[far] = u[far]
    return out, chk


def _turned(h0: float | np.ndarray, h1: float, config: ConnectionConfig) -> bool | np.ndarray:
    """The pivot's heading changed from ``h0`` (one or per tip) to ``h1`` by more than
    ``line_frame_max_deg``; always False unless ``line_check_undirected`` and the line-frame rule
    with its check are on."""
    if not (config.line_check_undirected and config.line_frame_deg > 0 and config.line_frame_check):
        return np.zeros(np.shape(h0), dtype=bool) if np.ndim(h0) else False
    return np.cos(h1 - h0) < math.cos(math.radians(max(config.line_frame_max_deg, config.line_frame_deg)))


def _undirected_checks(
    b: _Builder,
    tip_idx: np.ndarray,
    tip_s: np.ndarray,
    head_at: dict[float, float],
    heading: float,
    config: ConnectionConfig,
    tip_dir: np.ndarray | None,
    tip_check: np.ndarray | None,
) -> np.ndarray | None:
    """``tip_check`` plus, for each end without a direction of its own (no frame, no check: a
    line the cut had just reached) left behind where the pivot has since turned by more than
    ``line_frame_max_deg`` (``line_check_undirected``), the pivot's heading at the end's step as
    the direction its edges are checked against: at an intersection the one node of a crossing
    line, seen as the pivot began to turn, was joined across the turn's bridged gap to a line of
    the road it turned onto (carla_town06_50_s3: 14 m, x 8-22, y -136)."""
    if len(tip_idx) == 0:
        return tip_check
    h_tip = np.array([head_at[float(x)] for x in tip_s])
    turned = np.asarray(_turned(h_tip, heading, config))  # (n,): one heading per tip
    if tip_dir is not None:
        turned &= ~np.isfinite(tip_dir[:, 0])
    if tip_check is not None:
        turned &= ~np.isfinite(tip_check[:, 0])
    if not turned.any():
        return tip_check
    u = b.line_directions(tip_idx[turned], _LINE_FRAME_MIN_M)
    rows = np.flatnonzero(turned)[~np.isfinite(u[:, 0])]
    if len(rows) == 0:
        return tip_check
    out = np.full((len(tip_idx), 2), np.nan) if tip_check is None else tip_check.copy()
    out[rows] = np.stack([np.cos(h_tip[rows]), np.sin(h_tip[rows])], axis=1)
    return out


def connect_segment(segment: Segment, *, config: ConnectionConfig = ConnectionConfig()) -> SegmentGraph:
    """Connect the aggregated maxima of one pivot drive into polylines (Sec. V).

    Args:
        segment: the pivot's steps (any order; sorted by ``index`` here; not modified).
        config: connection parameters.

    Returns:
        The segment's hierarchical graph. Steps that are invalid, processed before, or rejected
        by the angle check get no topology node.

    Malformed steps (arrays of different lengths, non-finite midpoint or heading) are skipped
    like invalid ones and reported in ``stats.malformed`` / ``stats.problems``; non-finite
    maxima are dropped.

    Raises:
        HdmapError: a step belongs to another pivot than the segment.
    """
    steps = sorted(segment.steps, key=lambda s: s.index)
    for st in steps:
        if st.pivot_id != segment.pivot_id:
            raise HdmapError(f"segment {segment.pivot_id!r} holds a step of pivot {st.pivot_id!r}")
    stats = ConnectionStats(steps=len(steps))
    # a malformed step (arrays of different lengths, non-finite pose) is reported and skipped like
    # an invalid one: the rest of the segment goes on
    bad: set[int] = set()
    for k, st in enumerate(steps):
        if st.valid and not st.processed_before and len(st.lateral_m):
            try:
                _check_step(st)
            except HdmapError as err:
                bad.add(k)
                stats.malformed += 1
                if len(stats.problems) < 10:
                    stats.problems.append(str(err))
    if bad:
        steps = [replace(st, valid=False) if k in bad else st for k, st in enumerate(steps)]
    valid = [st for st in steps if st.valid and not st.processed_before and len(st.lateral_m)]
    flat = _flatten(valid, config) if valid else None
    b = _Builder(flat) if flat is not None else None
    # open polyline ends: either exactly the nodes of topology node ``last_topo`` (tips is None),
    # or explicit arrays (node index, pivot distance of its step, point, type)
    tips: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
    last_topo: int | None = None
    last_j = -1
    last_s = 0.0
    head_at: dict[float, float] = {}  # pivot heading of each used step, by its pivot distance
    skipped = False
    drive_ids: set[str] = set()
    j = -1

    for st in steps:
        if st.processed_before:
            # RULE 4: a section already processed by another pivot closes every polyline
            stats.processed_before += 1
            tips, last_topo = None, None
            continue
        if not st.valid or len(st.lateral_m) == 0:
            stats.invalid += 1
            skipped = True
            continue
        j += 1
        assert b is not None and flat is not None  # valid steps exist here
        a0, a1 = int(flat.off[j]), int(flat.off[j + 1])
        if a0 == a1:  # every maximum was non-finite
            stats.invalid += 1
            skipped = True
            continue
        if last_topo is not None and st.s_m - last_s > config.max_gap_m:
            # RULE 3: the gap to the last valid step exceeds the threshold: close everything
            stats.gaps_closed += 1
            tips, last_topo = None, None
        # the common case: same features as the last step, every edge plausible, no line leaving
        # the heading (its line frames, once computed for this test, serve the assignment too)
        lf_last = None
        fast = last_topo is not None and tips is None and bool(flat.fast[j]) and last_j == j - 1
        if fast and _turned(head_at[last_s], float(st.heading), config):
            fast = False  # across a turn the ends without a direction of their own are checked
        if fast and config.line_frame_deg > 0:
            assert last_topo is not None  # fast: there is a last step
            lf_last = _line_frames(b, b.tips_of(last_topo)[0], float(st.heading), config)
            fast = lf_last is None
        if fast:
            assert last_topo is not None
            t = b.add(j)
            b.topo_edges.append((last_topo, t))
            b.fast_links.append(t)
            p0, q0 = b.node_base[last_topo], b.node_base[t]
            b.pred[q0 : q0 + a1 - a0] = np.arange(p0, p0 + a1 - a0)
        elif last_topo is not None:
            if tips is None:
                ti, tx, tt = b.tips_of(last_topo)
                tips = (ti, np.full(len(ti), last_s), tx, tt)
            tip_idx, tip_s, tip_xy, tip_type = tips
            live = (st.s_m - tip_s) <= config.max_gap_m  # RULE 3 per polyline (bridged features)
            tip_idx, tip_s, tip_xy, tip_type = tip_idx[live], tip_s[live], tip_xy[live], tip_type[live]
            tip_dir = _tip_frames(b, tip_idx, st.s_m - tip_s, float(st.heading), config)
            # lf_last is set only for last_topo's own nodes (tips was None); all live: the same ends
            lf = lf_last if lf_last is not None and live.all() else _line_frames(b, tip_idx, float(st.heading), config)
            tip_check = None
            if lf is not None:
                line_dir, tip_check = lf
                if tip_dir is not None:  # a bridged gap's tip frame comes first
                    line_dir = np.where(np.isfinite(tip_dir[:, :1]), tip_dir, line_dir)
                    tip_check = np.where(np.isfinite(tip_dir[:, :1]), np.nan, tip_check)
                tip_dir = line_dir
            tip_check = _undirected_checks(b, tip_idx, tip_s, head_at, float(st.heading), config, tip_dir, tip_check)
            res = assign(
                tip_xy,
                tip_type,
                tip_s == last_s,
                flat.xy[a0:a1],
                flat.typ[a0:a1],
                st.heading,
                config,
                tip_dir,
                tip_check,
            )
            if res.mean_angle_deg > _MAX_MEAN_ANGLE_DEG:
                stats.rejected_angle += 1  # implausible optimisation result: treat as a gap
                skipped = True
                tips = (tip_idx, tip_s, tip_xy, tip_type)
                continue
            t = b.add(j)
            base = b.node_base[t]
            b.topo_edges.append((last_topo, t))
            used = set()
            for pairs, lo in ((res.regular, False), (res.leftover, True)):
                for i, k in pairs:
                    b.edges.append((int(tip_idx[i]), base + k))
                    b.leftover.append(lo)
                    used.add(i)
                    if not lo and b.pred[base + k] < 0:
                        b.pred[base + k] = int(tip_idx[i])
            if config.bridge_features and len(used) < len(tip_idx):
                keep = np.ones(len(tip_idx), dtype=bool)
                keep[list(used)] = False
                ti, tx, tt = b.tips_of(t)
                tips = (
                    np.concatenate([tip_idx[keep], ti]),
                    np.concatenate([tip_s[keep], np.full(len(ti), st.s_m)]),
                    np.concatenate([tip_xy[keep], tx]),
                    np.concatenate([tip_type[keep], tt]),
                )
            else:
                tips = None
        else:
            t = b.add(j)
            tips = None
        if skipped and last_topo is not None:
            stats.gaps_bridged += 1
        last_topo, last_j, last_s, skipped = t, j, st.s_m, False
        head_at[st.s_m] = float(st.heading)
        stats.used += 1
        drive_ids.update(st.drive_ids)

    return _finish(segment, b, stats, drive_ids, config)


def _topo_sections(steps: list[StepResult], lane_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) midpoints and (T,) widths of the topology nodes of ``steps``: each step's refined
    cut; with ``lane_m`` > 0, where the pivot's own position lies beyond it, widened to reach
    ``lane_m`` beyond the pivot (``ConnectionConfig.topo_pivot_lane_m``; a step without a finite
    pose keeps its cut)."""
    mid = np.array([np.asarray(st.midpoint, dtype=float) for st in steps]).reshape(-1, 2)
    width = np.array([float(st.width_m) for st in steps])
    if lane_m <= 0 or not len(steps):
        return mid, width
    pose = np.array(
        [np.full(2, np.nan) if st.pose is None else np.asarray(st.pose, dtype=float).reshape(2) for st in steps]
    )
    normal = left_normal(np.array([float(st.heading) for st in steps])).reshape(-1, 2)
    own = np.einsum("ij,ij->i", pose - mid, normal)  # the pivot along the cut, + = left [m]
    ok = np.isfinite(own) & np.isfinite(width) & (np.abs(own) > 0.5 * width)  # the pivot beyond its cut
    lo = np.minimum(-0.5 * width, own - lane_m)
    hi = np.maximum(0.5 * width, own + lane_m)
    shift = np.where(ok, 0.5 * (lo + hi), 0.0)
    return mid + shift[:, None] * normal, np.where(ok, hi - lo, width)


def _pose_ok(st: StepResult) -> bool:
    """Does step ``st`` carry a finite 2-D midpoint and heading?"""
    try:
        mid = np.asarray(st.midpoint, dtype=float)
        return mid.shape == (2,) and bool(np.isfinite(mid).all()) and math.isfinite(st.heading)
    except (TypeError, ValueError):
        return False


def _empty_of(st: StepResult) -> np.ndarray | None:
    """The step's empty intervals as a finite (M, 2) array with lo <= hi; None when not judged
    (or malformed: then not used, rather than failing the segment)."""
    if st.empty_m is None:
        return None
    try:
        e = np.asarray(st.empty_m, dtype=float).reshape(-1, 2)
    except (TypeError, ValueError):
        return None
    if e.size == 0:
        return e
    e = e[np.isfinite(e).all(axis=1)]
    return np.sort(e, axis=1)


def _finish(
    segment: Segment, b: _Builder | None, stats: ConnectionStats, drive_ids: set[str], config: ConnectionConfig
) -> SegmentGraph:
    used = np.asarray(b.used if b is not None else [], dtype=np.int64)
    f = b.f if b is not None else None
    topo_steps = [f.steps[j] for j in used.tolist()] if f is not None else []
    first = topo_steps[0].index if topo_steps else (segment.steps[0].index if segment.steps else 0)
    step_idx = np.array([st.index for st in topo_steps], dtype=np.int64)
    if f is not None and len(used):
        k = f.off[used + 1] - f.off[used]
        rows = np.repeat(f.off[used], k) + (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k))
    else:
        k = np.zeros(0, dtype=np.int64)
        rows = np.zeros(0, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(k)]).astype(np.int64)
    node_step = np.repeat(step_idx, k)
    # edges: the identity links of the fast path, then those of the assignment
    e_fast = np.zeros((0, 2), dtype=np.int64)
    if b is not None and b.fast_links:
        t = np.asarray(b.fast_links, dtype=np.int64)
        kt = k[t]
        rank = np.arange(kt.sum()) - np.repeat(np.cumsum(kt) - kt, kt)
        e_fast = np.stack([np.repeat(starts[t - 1], kt) + rank, np.repeat(starts[t], kt) + rank], axis=1)
    e_slow = np.asarray(b.edges if b is not None else [], dtype=np.int64).reshape(-1, 2)
    edges = np.concatenate([e_fast, e_slow])
    leftover = np.concatenate([np.zeros(len(e_fast), dtype=bool), np.asarray(b.leftover if b else [], dtype=bool)])
    n = len(rows)
    if len(edges):
        order = np.lexsort((edges[:, 1], edges[:, 0]))
        edges, leftover = edges[order], leftover[order]
        stats.splits = int((np.bincount(edges[:, 0], minlength=n) >= 2).sum())
        stats.merges = int((np.bincount(edges[:, 1], minlength=n) >= 2).sum())
    stats.suppressed = int(sum(len(st.lateral_m) for st in f.steps) - len(f.lat)) if f is not None else 0

    def pick(a: np.ndarray | None, empty: np.ndarray) -> np.ndarray:
        return a[rows] if a is not None else empty

    # the pivot's driven path: every step with a finite pose, used or not, in step order
    track = sorted((st for st in segment.steps if _pose_ok(st)), key=lambda st: st.index)
    empties = [_empty_of(st) for st in track]

    topo_xy, topo_width = _topo_sections(topo_steps, config.topo_pivot_lane_m)
    return SegmentGraph(
        key=f"{segment.pivot_id}@{first}",
        pivot_id=segment.pivot_id,
        topo_uid=stable_uid("topo:" + segment.pivot_id, step_idx),
        topo_step=step_idx,
        topo_xy=topo_xy,
        topo_heading=np.array([float(st.heading) for st in topo_steps]),
        topo_width=topo_width,
        topo_edges=np.asarray(b.topo_edges if b else [], dtype=np.int64).reshape(-1, 2),
        topo_start=starts,
        node_uid=stable_uid(
            "feature:" + segment.pivot_id, node_step, pick(f.slot if f else None, np.zeros(0, np.int64))
        ),
        node_xy=pick(f.xy if f else None, np.zeros((0, 2))),
        node_type=pick(f.typ if f else None, np.zeros(0, np.int64)),
        node_count=pick(f.cnt if f else None, np.zeros(0, np.int64)),
        node_std=pick(f.std if f else None, np.zeros(0)),
        edges=edges,
        edge_leftover=leftover,
        drive_ids=tuple(sorted(drive_ids)),
        stats=stats,
        tile_size_m=config.tile_size_m,
        track_step=np.array([int(st.index) for st in track], dtype=np.int64),
        track_s=np.array([float(st.s_m) for st in track]),
        track_xy=np.array([np.asarray(st.midpoint, dtype=float) for st in track]).reshape(-1, 2),
        track_pose=(
            np.array([np.asarray(st.pose, dtype=float) for st in track]).reshape(-1, 2)
            if all(st.pose is not None for st in track)
            else np.zeros((0, 2))
        ),
        track_heading=np.array([float(st.heading) for st in track]),
        track_judged=np.array([e is not None for e in empties], dtype=bool),
        track_empty_start=np.concatenate([[0], np.cumsum([0 if e is None else len(e) for e in empties])]).astype(
            np.int64
        ),
        track_empty=np.concatenate([np.zeros((0, 2))] + [e for e in empties if e is not None]).reshape(-1, 2),
    )
