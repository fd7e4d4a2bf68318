"""The pivots' own tracks as evidence for links (beyond the paper; Sec. VI).

Where a component end has no partner by distance and heading, the path its pivot drove on says
where the road goes: ``pivot_tracks`` puts each pivot's track together from its segment graphs,
``track_partner`` walks it from an end to the first topology node it enters, and
``track_bridges`` finds nodes a track leaves and re-enters across steps no node covers (a junction).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import heading_frame, wrap_angle
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.links import HALF_WIDTH_UNKNOWN_M, PATH_STEP_M, entered
from hdmap_core.graph.segment_graph import SegmentGraph
from hdmap_core.graph.stitch_config import StitchConfig

__all__ = ["pivot_tracks", "track_partner", "entered_by_points", "track_bridges"]

# Rules of following a pivot's track, measured with the track links (docs/graph.md, "Track links");
# no preset changes them.
#: two consecutive track points further apart than this along the track's heading are a gap (a
#: run of steps processed before keeps only its first and last step) [m] ...
_TRACK_MAX_GAP_M = 6.0
#: ... and two track points further apart than this (in any direction) are a gap too: a failed
#: step's cut midpoint may lie across the road from the last (carla_town06_30_s1: 8.96 m, 2 m
#: along), but a cut refined onto another road is no path the pivot drove [m].
_TRACK_MAX_JUMP_M = 12.0
#: a track bridge (``track_bridge_m``): the track enters node B (and stays on the road of A while turning off
#: it) with a heading this close to the node's; it leaves A within ``max_heading_diff_deg``.
#: Wider than that: a pivot entering a road at a merge is still turning when its track reaches
#: the road's cross-section (35 deg on Town04). Consecutive track points more than
#: ``_TRACK_MAX_GAP_M`` apart in any direction end a bridge's walk [deg].
_TRACK_BRIDGE_HEADING_DEG = 45.0


def track_partner(
    flat: FlatGraph,
    tree: cKDTree,
    i: int,
    is_end: bool,
    track: tuple[np.ndarray, np.ndarray],
    k: int,
    cfg: StitchConfig,
    reach_m: float,
    allowed: Callable[[int], bool],
) -> int:
    """The first topology node on the path the pivot of end (start) node i drove on from it
    (back to it): ``track`` = (xy, heading) of the pivot's steps in driving order, ``k`` = the
    row of node i's step. A track point within ``track_search_m`` (walked along the track's
    heading; the walk stops at a gap over ``_TRACK_MAX_GAP_M`` along it or a jump over
    ``_TRACK_MAX_JUMP_M`` in any direction) lies in the node's cross-section and the node heads
    within ``max_heading_diff_deg`` of the track there; among several at that point the nearest,
    among those ``allowed``; -1 if none (``StitchConfig.track_search_m``). With
    ``track_settle_deg`` a point where the track is still turning onto the node's heading
    (``_still_turning``) lands nowhere: the walk goes on."""
    xy, heading = track
    if not 0 <= k < len(xy):
        return -1
    cos_h = math.cos(math.radians(cfg.max_heading_diff_deg))
    sign = 1 if is_end else -1
    u0, _ = heading_frame(float(flat.t_heading[i]))
    walked = 0.0
    for m in range(k + sign, len(xy) if is_end else -1, sign):
        gap = _track_gap(xy, heading, m - sign, m, cfg)
        if gap is None:
            break
        walked += gap
        if walked > cfg.track_search_m:
            break
        best = entered(flat, tree, i, sign, u0, xy[m], float(heading[m]), cos_h, reach_m, allowed)
        if best >= 0 and cfg.track_settle_deg > 0 and _still_turning(flat, best, xy, heading, m, sign, cfg):
            continue  # RULE: the pivot is still turning onto the road here: land where it has settled
        if best >= 0:
            return best
    return -1


def _track_gap(xy: np.ndarray, heading: np.ndarray, m: int, n: int, cfg: StitchConfig) -> float | None:
    """How far the pivot drove from track row m to row n: the step along row n's heading [m];
    None where the two are no consecutive places of one drive (a gap over ``_TRACK_MAX_GAP_M``
    along, or a jump over ``_TRACK_MAX_JUMP_M`` in any direction). Along the heading because a
    failed step's cut midpoint may jump across the road (its cut refined to other borders) though
    the pivot drove on; a run processed before keeps only its first and last step: a gap."""
    step = xy[n] - xy[m]
    gap = abs(float(np.dot(step, heading_frame(float(heading[n]))[0])))
    if gap > _TRACK_MAX_GAP_M or float(np.hypot(*step)) > _TRACK_MAX_JUMP_M:
        return None
    return gap


def _still_turning(
    flat: FlatGraph, j: int, xy: np.ndarray, heading: np.ndarray, m: int, sign: int, cfg: StitchConfig
) -> bool:
    """Is the track (``xy``, ``heading``) at row m, walked in direction ``sign``, still turning
    onto node j's heading (``StitchConfig.track_settle_deg``)? Its heading there lies more than
    2 * ``track_settle_deg`` off the node's and the next row of the walk (no gap: within
    ``_TRACK_MAX_GAP_M`` along its heading and ``_TRACK_MAX_JUMP_M`` in any direction) within
    ``track_settle_deg`` of it: the pivot settles onto the road one step later."""
    settle = math.radians(cfg.track_settle_deg)
    hj = float(flat.t_heading[j])
    n = m + sign
    if abs(wrap_angle(float(heading[m]) - hj)) <= 2.0 * settle or not 0 <= n < len(xy):
        return False
    if _track_gap(xy, heading, m, n, cfg) is None:
        return False
    return bool(abs(wrap_angle(float(heading[n]) - hj)) <= settle)


def entered_by_points(
    flat: FlatGraph,
    tree: cKDTree,
    xy: np.ndarray,
    heading: np.ndarray,
    cos_h: tuple[float, ...],
    reach_m: float,
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
    half = np.where(np.isfinite(w) & (w > 0), w / 2.0, HALF_WIDTH_UNKNOWN_M)
    near = along <= PATH_STEP_M
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


def track_bridges(
    flat: FlatGraph,
    tree: cKDTree,
    xy: np.ndarray,
    heading: np.ndarray,
    cfg: StitchConfig,
    reach_m: float,
    on_road: Callable[[int, int], bool],
) -> list[tuple[int, int]]:
    """(A, B) topology node pairs a pivot's track (``xy``, ``heading`` in driving order) bridges:
    the track leaves node A's cross-section, runs through at least one point that lies in no
    node's cross-section (within ``_TRACK_BRIDGE_HEADING_DEG``) for at most ``track_bridge_m``
    (two points further apart than ``_TRACK_MAX_GAP_M`` end the walk), and enters node B's
    (``StitchConfig.track_bridge_m``). A is left running along it (within
    ``max_heading_diff_deg``; with ``track_bridge_leave_margin_m`` a point up to that far beyond
    A's cross-section leaves it too where the walk has no road to leave yet); points turning off
    it within ``_TRACK_BRIDGE_HEADING_DEG`` while still in the cross-section of a node A's road
    leads to (``on_road(A, node)``) keep A."""
    # leaving a road the track runs along it (within max_heading_diff_deg); entering one at a
    # merge it may still be turning (within _TRACK_BRIDGE_HEADING_DEG)
    cos_leave = math.cos(math.radians(cfg.max_heading_diff_deg))
    cos_enter = math.cos(math.radians(_TRACK_BRIDGE_HEADING_DEG))
    # RULE: with track_bridge_leave_margin_m a track that has no road to leave from (its start, or
    # after a gap: a run processed before keeps only its first and last step) leaves the road
    # whose cross-section, widened by the margin, its point lies in: the last point before a
    # junction's failed steps is a cut midpoint already pulled off the road's middle
    # (carla_town04_50_s1: 5.6 m across a node 4.8 m half wide). Only there: a bridge still ends
    # in a node's own cross-section, and a walk off a road is not cut short by the margin.
    if cfg.track_bridge_leave_margin_m > 0:
        leave, enter, wide = entered_by_points(
            flat,
            tree,
            xy,
            heading,
            (cos_leave, cos_enter, cos_leave),
            reach_m,
            (0.0, 0.0, cfg.track_bridge_leave_margin_m),
        )
    else:
        leave, enter = entered_by_points(flat, tree, xy, heading, (cos_leave, cos_enter), reach_m)
        wide = np.full(len(xy), -1, dtype=np.int64)
    out: list[tuple[int, int]] = []
    last, unmapped, walked = -1, 0, 0.0
    for m in range(len(xy)):
        if m > 0:
            # a bridge claims the pivot drove the track: consecutive points no further apart than
            # _TRACK_MAX_GAP_M in any direction (the track search's jumps of failed steps' cut
            # midpoints, up to _TRACK_MAX_JUMP_M across, land on other roads at junctions)
            gap = float(np.hypot(*(xy[m] - xy[m - 1])))
            walked += gap
            if gap > _TRACK_MAX_GAP_M:
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


def pivot_tracks(
    graphs: Sequence[SegmentGraph], *, use_pose: bool
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], dict[str, np.ndarray]]:
    """Per pivot drive, its track over all its segment graphs, and per graph its track rows.

    Live, one pivot's steps come in one graph per tile: the graphs' pivot ids are per tile
    (``SegmentGraph.pivot_drive`` names the drive) and their step indices count from each tile's
    clip of the drive, so the pieces are ordered by ``track_s`` (the travelled distance on the
    whole drive); graphs without it are ordered by step.

    Args:
        graphs: segment graphs, in key order.
        use_pose: take the pivot's own positions (``track_pose``) when every piece of a pivot has
            them (``StitchConfig.track_pose``), else its steps' cut midpoints (``track_xy``).

    Returns:
        ``tracks``: pivot drive -> (xy (K, 2) [m], heading (K,) [rad]) in order of travelled
        distance, each step once; ``rows``: graph key -> (S,) row in its pivot's track of each of
        the graph's ``track_step``.
    """
    parts: dict[str, list[SegmentGraph]] = {}
    for g in graphs:
        if len(g.track_step):
            parts.setdefault(g.pivot_drive or g.pivot_id, []).append(g)
    tracks, rows = {}, {}
    for pid, gs in parts.items():
        # RULE track_pose: the pivot's own positions where every piece has them
        pose = use_pose and all(len(g.track_pose) == len(g.track_step) for g in gs)
        attr = "track_pose" if pose else "track_xy"
        if len(gs) == 1:
            g = gs[0]
            tracks[pid] = (getattr(g, attr), g.track_heading)
            rows[g.key] = np.arange(len(g.track_step))
            continue
        by_s = all(len(g.track_s) == len(g.track_step) for g in gs)
        order = [np.asarray(g.track_s if by_s else g.track_step, dtype=float) for g in gs]
        _, first, inverse = np.unique(np.concatenate(order), return_index=True, return_inverse=True)
        tracks[pid] = (
            np.concatenate([getattr(g, attr) for g in gs])[first],
            np.concatenate([g.track_heading for g in gs])[first],
        )
        at = np.cumsum([0] + [len(o) for o in order])
        for g, a, b in zip(gs, at[:-1], at[1:]):
            rows[g.key] = inverse[a:b]
    return tracks, rows
