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

from hdmap_core.graph.assignment import assign
from hdmap_core.errors import ConfigError, HdmapError
from hdmap_core.model import FeatureType
from hdmap_core.graph.segment_graph import ConnectionStats, SegmentGraph, stable_uid
from hdmap_core.steps import Segment, StepResult, left_normal

__all__ = ["ConnectionConfig", "connect_segment"]

_BORDER = int(FeatureType.ROAD_BORDER)


@dataclass(frozen=True)
class ConnectionConfig:
    """Parameters of the connection stage (the paper gives none of these numbers).

    Attributes:
        max_gap_m: steps without a result are bridged when the pivot travelled at most this far
            between two valid steps; a longer gap closes every polyline (RULE 3) [m].
        max_mean_angle_deg: a step whose assigned connections have a mean angle (to the heading)
            above this is rejected as an implausible optimisation result and bridged [deg].
        robust_angle: judge a step by the median connection angle instead of the mean, so that
            one feature leaving the cut while another enters does not reject a good step.
        mean_angle_slack: measure those connection angles with ``edge_slack_m`` taken off each
            connection's offset across the road, as the edge limit is: the maxima's own noise.
            On a tight curve the inner lines' maxima of consecutive steps lie < 1 m apart along
            the road, where 0.3 m of noise is 20 deg (carla_town06_30_s6's loop at y 148,
            radius ~13 m: 26 of its 33 steps rejected). False: the raw angles (the paper).
        max_edge_angle_deg: a single connection steeper than this is not made; 90 disables [deg].
        edge_slack_m: lateral slack added to the edge angle limit (noise of the maxima) [m].
        leftover_max_m: a leftover node is joined to its nearest neighbour only when that is at
            most this far across the cut; ``inf`` joins every leftover, as in the paper [m].
        leftover_same_type: join a leftover only to a node of its own type. At a gore the two
            lines resolve as one of their type first and split later (solid -> two solids), so
            real splits keep their leftover; a line that ends beside a line of the other marking
            type (solid beside dashed) no longer merges into it. False: the paper.
        fresh_first: assign the open ends of the last step first and let the ends bridged from
            earlier steps (``bridge_features``) take only the maxima left. One joint assignment
            minimises the summed distance, so a one-drive tip bridged from three steps back could
            take a well-supported line while the line it continues took its diverging neighbour
            (paper_like 4x: the through line of a gore continued a one-drive dashed maximum
            1.4 m beside it, and the exit lost its split; docs/pipeline.md "Fresh tips first").
            False: one assignment (the paper, the plain default).
        leftover_other_type_m: ... except when the marking of the other type is at most this far
            across: two markings that close are one place, so the leftover is a branch starting
            (ending) on the other line (an exit's dashed line starting on the solid edge line,
            0.2-0.5 m from it when first resolved; an entry's solid line ending on the dashed
            one). 0: same type only [m].
        bridge_features: keep a polyline whose feature is missing in a step open for ``max_gap_m``
            so that it continues when the feature reappears (per-feature gap bridging; the paper
            bridges whole steps only).
        min_separation_m: two lane markings (or two road borders) of one step closer than this
            are one feature seen twice (typically a misclassified cluster the overlap filter
            kept); only the one with more drives is used. 0 disables (the paper) [m].
        separation_count_ratio: ... only when the weaker one has at most this share of the
            stronger one's drives. 1.0 (default): always. (0.5 keeps two well supported lines
            about to diverge, but measured worse: they flicker and fragment more.)
        min_support_share: a maximum supported by fewer than this share of the step's drives
            (``counts < share * len(drive_ids)``) is noise (a false positive, a misclassified
            copy) and not used. 0 disables (the paper).
        support_window_m: when > 0, the share is taken of the best supported maximum of the step
            within this lateral distance (itself included) instead of all the step's drives: on a
            wide cut (a ramp beside the carriageway) the far lines are seen by only the drives
            near them, while a false positive or misclassified copy still sits beside a line many
            more drives saw [m].
        window_min_count: the window rule keeps only maxima of at least this many drives (a
            maximum of one drive flickers: one drive's false positive or misclassified stretch).
        lone_line_gap_m: when > 0, a maximum whose neighbours in its step (next inward and
            outward; none counts as far) are both at least this far away is kept with at least
            ``window_min_count`` drives, whatever the support share: a line seen only by the
            drives of the lane beside it lies a lane from the next line, while a misclassified
            copy or a false positive lies beside a line or inside a lane (carla_town04_50_s1:
            the inner edge line at a painted median, 3.5 m from a lane line of 7 drives, seen by
            the one drive in the lane between over 136 m; the right edge line 3.5 m inside the
            border, seen by one drive). 0 disables [m].
        lone_line_border_gap_m: for a marking, a road-border neighbour need only be this far
            away (the edge line lies 0.2-1.5 m inside the border, carla_town06_30_s1 x 326 ..
            476: 1.1 m, seen by one drive, the border by three; 0.5 m let one drive's solid
            lines 0.3-0.6 m from esmini_soderleden's border through). None: ``lone_line_gap_m``
            [m].
        lone_line_border_outer: the border neighbour of ``lone_line_border_gap_m`` counts only on
            the line's outer side (away from the cut's midpoint), where an edge line has its
            border. With 100 drives a lane line has one- or two-drive copies typed as border
            (the simulator's marking-to-border misclassification); taken as an edge line's
            border, such a copy let one drive's false line 2.3 m beside it through
            (esmini_soderleden_100_s4, precision 97.7 %).
        topo_pivot_lane_m: when > 0, the topology node of a step whose pivot's own position
            (``StepResult.pose``) lies beyond its refined cut gets a cross-section (midpoint,
            width) widened to reach this far beyond the pivot: the node describes the road the
            pivot drove. Where one side of a junction has no line, the cut sits on the side of
            the one border seen, its width carried from a step that ended at a stray line beside
            the pivot, and the node lay beside that road (carla_town04_30_s3's T-junction at x
            -388: a 4.5 m cut 1.15 m off the pivot, linked to its road 12 m back as if to the
            junction's side road). Only the topology node moves; the step's samples and
            features stay. 0: the cut as refined [m].
        tile_size_m: edge of the square tiles that key topology nodes by place [m].
        tip_frame_deg: a polyline end at least ``tip_frame_min_m`` (pivot travel) behind the new
            step (a bridged gap) whose own direction (from its node ~3 edges back, at least
            ``tip_frame_min_m`` away) differs from the new step's heading by more than this is
            paired in its own frame (along / across its direction) instead of the pivot's: where
            the pivot turns off (an exit ramp) the straight lines it still sees leave its
            heading, and in its frame the pairing shifted by one lane looked straight (Town04's
            cloverleaf: every line joined the next one 3.5 m over ~11 m). 0 disables [deg].
        tip_frame_min_m: see ``tip_frame_deg`` [m].
        bridge_edge_angle_deg: a connection longer than ``bridge_edge_min_m`` along (across a
            bridged gap) steeper than this is not made (``edge_slack_m`` added): a 30 deg edge
            over 10 m is a line that ended joined to its neighbour 6 m over (an inner gore
            border to the outer border at an entry), not one line. 90 disables [deg].
        bridge_edge_min_m: see ``bridge_edge_angle_deg`` [m].
        tip_frame_max_deg: ... and by at most this: a pivot turning further is turning at an
            intersection, where a line ending there must not continue straight across [deg].
        line_frame_deg: any open polyline end (also between consecutive steps, also on the
            identity fast path) whose own line direction (from its node at least 4 m back within
            6 edges, else the farthest at least ``line_frame_min_m`` back) differs from the new
            step's heading by more than this (and at most ``tip_frame_max_deg``) is paired in its
            own frame. Where a pivot comes in on an entry ramp at 17-25 deg to the carriageway, in
            its frame each carriageway line paired with the next lane's line (Town04: 3.2 m
            sideways over 6 m), or the step was rejected by the angle check (the true pairs
            looked 20 deg steep). An end without a direction of its own (a line the cut has just
            reached) keeps the pivot's frame: borrowing a neighbour's direction took a merging
            ramp line's at an entry (Town04 30 s3 fragmentation 1.541 -> 1.568). 0 disables (the
            paper) [deg].
        line_frame_min_m: see ``line_frame_deg`` [m].
        line_frame_max_deg: see ``line_frame_deg`` [deg].
        line_frame_check: a tip whose line leaves the heading by more than ``line_frame_max_deg``
            (and at most ``line_check_max_deg``) is paired in the pivot's frame, but an edge
            steeper than the edge limits (``max_edge_angle_deg``, ``bridge_edge_angle_deg``)
            against its own line direction, or not ahead along it, is not made: where the pivot
            turns off onto an exit the lines it leaves end in its segment instead of joining the
            next lane's line.
        line_check_max_deg: see ``line_frame_check``. 180 (default): any larger deviation. With
            90, a pivot turning off at a right angle across a bridged gap (an intersection, a
            T-junction joining the motorway) paired the lines it left in its new frame: on every
            CARLA fleet 1-4 lines turned a corner that no line has (Town04 50 s1: the median
            solid line continued 28 m across the carriageway into the side road) [deg].
        line_check_undirected: an end without a direction of its own (a line the cut has just
            reached) left behind where the pivot has since turned by more than
            ``line_frame_max_deg`` is checked against the pivot's heading at its step (the
            only direction known for it): at an intersection one node of a crossing line was
            joined across the turn to a line of the other road. Only with ``line_frame_deg`` and
            ``line_frame_check``.
        line_frame_bend_deg: ... both only for a line whose history is straight: the directions to
            its predecessors (at least ``line_frame_min_m`` back, within 6 edges) all lie within
            this of the line's direction. Where the road curves (Town06's corners and junction
            turns) the lines curve with the pivot, a direction from 4 m back lags its heading by
            12-30 deg, and in that frame true continuations looked steep: steps were rejected
            and chord edges across a turn refused (Town06 30 s3 coverage 98.92 -> 98.13). 0: any
            history [deg].
    """

    max_gap_m: float = 20.0
    max_mean_angle_deg: float = 15.0
    robust_angle: bool = True
    mean_angle_slack: bool = False
    max_edge_angle_deg: float = 35.0
    edge_slack_m: float = 0.3
    leftover_max_m: float = 2.0
    leftover_same_type: bool = True
    fresh_first: bool = False
    leftover_other_type_m: float = 1.0
    bridge_features: bool = True
    min_separation_m: float = 1.0
    separation_count_ratio: float = 1.0
    min_support_share: float = 0.25
    support_window_m: float = 0.0
    window_min_count: int = 1
    lone_line_gap_m: float = 0.0
    lone_line_border_gap_m: float | None = None
    lone_line_border_outer: bool = False
    topo_pivot_lane_m: float = 0.0
    tile_size_m: float = 256.0
    tip_frame_deg: float = 5.0
    tip_frame_min_m: float = 4.0
    tip_frame_max_deg: float = 30.0
    bridge_edge_angle_deg: float = 15.0
    bridge_edge_min_m: float = 3.0
    line_frame_deg: float = 0.0
    line_frame_min_m: float = 1.5
    line_frame_max_deg: float = 30.0
    line_frame_check: bool = True
    line_check_max_deg: float = 180.0
    line_check_undirected: bool = True
    line_frame_bend_deg: float = 0.0

    def __post_init__(self) -> None:
        if not self.max_gap_m >= 0:
            raise ConfigError(f"max_gap_m must be >= 0, got {self.max_gap_m}")
        for name in ("max_mean_angle_deg", "max_edge_angle_deg", "bridge_edge_angle_deg"):
            v = getattr(self, name)
            if not 0 < v <= 90:
                raise ConfigError(f"{name} must be in (0, 90], got {v}")
        if not self.edge_slack_m >= 0:
            raise ConfigError(f"edge_slack_m must be >= 0, got {self.edge_slack_m}")
        if not 0 < self.line_check_max_deg <= 180:
            raise ConfigError(f"line_check_max_deg must be in (0, 180], got {self.line_check_max_deg}")
        if not self.min_separation_m >= 0:
            raise ConfigError(f"min_separation_m must be >= 0, got {self.min_separation_m}")
        if not 0 <= self.min_support_share <= 1:
            raise ConfigError(f"min_support_share must be in [0, 1], got {self.min_support_share}")
        if not (self.support_window_m >= 0 and math.isfinite(self.support_window_m)):
            raise ConfigError(f"support_window_m must be finite and >= 0, got {self.support_window_m}")
        if not (self.lone_line_gap_m >= 0 and math.isfinite(self.lone_line_gap_m)):
            raise ConfigError(f"lone_line_gap_m must be finite and >= 0, got {self.lone_line_gap_m}")
        if self.lone_line_border_gap_m is not None and not (
            self.lone_line_border_gap_m >= 0 and math.isfinite(self.lone_line_border_gap_m)
        ):
            raise ConfigError(f"lone_line_border_gap_m must be None or finite and >= 0, got {self.lone_line_border_gap_m}")
        if not (self.topo_pivot_lane_m >= 0 and math.isfinite(self.topo_pivot_lane_m)):
            raise ConfigError(f"topo_pivot_lane_m must be finite and >= 0, got {self.topo_pivot_lane_m}")
        if self.window_min_count < 1:
            raise ConfigError(f"window_min_count must be >= 1, got {self.window_min_count}")
        if not (self.leftover_other_type_m >= 0 and math.isfinite(self.leftover_other_type_m)):
            raise ConfigError(f"leftover_other_type_m must be finite and >= 0, got {self.leftover_other_type_m}")
        if not self.leftover_max_m >= 0:
            raise ConfigError(f"leftover_max_m must be >= 0, got {self.leftover_max_m}")
        if not (self.tile_size_m > 0 and math.isfinite(self.tile_size_m)):
            raise ConfigError(f"tile_size_m must be > 0, got {self.tile_size_m}")
        for name in (
            "tip_frame_deg", "tip_frame_min_m", "tip_frame_max_deg", "bridge_edge_min_m",
            "line_frame_deg", "line_frame_min_m", "line_frame_max_deg", "line_frame_bend_deg",
        ):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"{name} must be finite and >= 0, got {v}")

    @classmethod
    def paper(cls) -> ConnectionConfig:
        """The paper's variant: every leftover joined, no per-edge limit, whole-step bridging only."""
        return cls(
            max_edge_angle_deg=90.0,
            leftover_max_m=math.inf,
            leftover_same_type=False,
            bridge_features=False,
            robust_angle=False,
            min_separation_m=0.0,
            min_support_share=0.0,
            tip_frame_deg=0.0,
            bridge_edge_angle_deg=90.0,
        )


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
            border[i] != border[j] or abs(lat[i] - lat[j]) >= min_sep_m or counts[i] > ratio * counts[j]
            for j in kept
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
                by_place[keep[by_place]], j_of, lat, typ, config.lone_line_gap_m, bgap,
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
    nrm = np.stack([-np.sin(hdg), np.cos(hdg)], axis=1)
    xy = mid[j_of] + lat[:, None] * nrm[j_of]
    return _Steps(valid, off, lat, xy, typ, cnt, std, slot, _fast_pairs(valid, off, xy, typ, hdg, config))


def _lone_lines(
    order: np.ndarray, j_of: np.ndarray, lat: np.ndarray, typ: np.ndarray, gap_m: float, border_gap_m: float,
    *, outer_only: bool = False,
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


def _local_max_count(j_of: np.ndarray, lat: np.ndarray, cnt: np.ndarray, off: np.ndarray, window_m: float) -> np.ndarray:
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
    cur = np.concatenate([np.arange(off[a], off[a + 1]) for a in j.tolist()]) if len(j) < 64 else (
        np.repeat(off[j], kk) + (np.arange(kk.sum()) - np.repeat(np.cumsum(kk) - kk, kk))
    )
    prev = cur - off[elem_j] + off[elem_j - 1]
    d = xy[cur] - xy[prev]
    c, sn = np.cos(hdg[elem_j]), np.sin(hdg[elem_j])
    along = d[:, 0] * c + d[:, 1] * sn
    lat = np.abs(-d[:, 0] * sn + d[:, 1] * c)
    tan_e = math.tan(math.radians(min(config.max_edge_angle_deg, 89.999)))
    tan_m = math.tan(math.radians(config.max_mean_angle_deg))
    slack = config.edge_slack_m if config.mean_angle_slack else 0.0
    ok = (typ[cur] == typ[prev]) & (along > 0) & (lat <= config.edge_slack_m + along * tan_e) & (lat <= slack + along * tan_m)
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
    """(n, 2) own line direction of each tip at least ``config.tip_frame_min_m`` back (pivot
    travel ``gap_m``) that leaves the step heading by more than ``config.tip_frame_deg`` (NaN for
    the others); None when no tip does."""
    if config.tip_frame_deg <= 0 or len(tip_idx) == 0:
        return None
    far = gap_m >= config.tip_frame_min_m
    if not far.any():
        return None
    # the first predecessor at least tip_frame_min_m back
    u = np.full((len(tip_idx), 2), np.nan)
    u[far] = b.line_directions(tip_idx[far], config.tip_frame_min_m, far_m=config.tip_frame_min_m)
    dev = _leaves_heading(u, heading, config.tip_frame_deg, config.tip_frame_max_deg)
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


def _line_frames(b: _Builder, tip_idx: np.ndarray, heading: float, config: ConnectionConfig) -> tuple[np.ndarray, np.ndarray] | None:
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
    u = b.line_directions(tip_idx, config.line_frame_min_m)
    dev = _leaves_heading(u, heading, config.line_frame_deg, config.line_frame_max_deg)
    # beyond line_frame_max_deg (up to line_check_max_deg): checked only
    far = (
        _leaves_heading(u, heading, max(config.line_frame_max_deg, config.line_frame_deg), config.line_check_max_deg)
        if config.line_frame_check else np.zeros(len(u), dtype=bool)
    )
    if not (dev.any() or far.any()):
        return None
    if config.line_frame_bend_deg > 0:
        straight = b.line_bends(tip_idx, u, config.line_frame_min_m) <= config.line_frame_bend_deg
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
    b: _Builder, tip_idx: np.ndarray, tip_s: np.ndarray, head_at: dict[float, float], heading: float,
    config: ConnectionConfig, tip_dir: np.ndarray | None, tip_check: np.ndarray | None,
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
    turned = _turned(h_tip, heading, config)
    if tip_dir is not None:
        turned &= ~np.isfinite(tip_dir[:, 0])
    if tip_check is not None:
        turned &= ~np.isfinite(tip_check[:, 0])
    if not turned.any():
        return tip_check
    u = b.line_directions(tip_idx[turned], config.line_frame_min_m)
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
            lf_last = _line_frames(b, b.tips_of(last_topo)[0], float(st.heading), config)
            fast = lf_last is None
        if fast:
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
                tip_xy, tip_type, tip_s == last_s, flat.xy[a0:a1], flat.typ[a0:a1], st.heading, config, tip_dir, tip_check
            )
            if res.mean_angle_deg > config.max_mean_angle_deg:
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
    pose = np.array([np.full(2, np.nan) if st.pose is None else np.asarray(st.pose, dtype=float).reshape(2) for st in steps])
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
        node_uid=stable_uid("feature:" + segment.pivot_id, node_step, pick(f.slot if f else None, np.zeros(0, np.int64))),
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
        track_pose=(np.array([np.asarray(st.pose, dtype=float) for st in track]).reshape(-1, 2)
                    if all(st.pose is not None for st in track) else np.zeros((0, 2))),
        track_heading=np.array([float(st.heading) for st in track]),
        track_judged=np.array([e is not None for e in empties], dtype=bool),
        track_empty_start=np.concatenate([[0], np.cumsum([0 if e is None else len(e) for e in empties])]).astype(np.int64),
        track_empty=np.concatenate([np.zeros((0, 2))] + [e for e in empties if e is not None]).reshape(-1, 2),
    )
