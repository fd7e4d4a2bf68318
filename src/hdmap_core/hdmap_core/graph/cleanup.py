"""Clean-up rules of the stitched feature graph (beyond the paper; Sec. VI export).

Each function reads a :class:`~hdmap_core.graph.flat.FlatGraph` and returns a mask; none
modifies its input. The rule families:

- RULE spur / bubble (``spur_free``): short dead-end branches off a split or into a merge, and the
  weaker of two short branches between one split and one merge, are pruned;
- RULE end stub (``end_stubs``): a short run at a loose end joined by a long sideways jump is dropped;
- RULE inner border (``inner_borders``): one drive's lane line reported as a road border, lying
  between lane lines, is found (the export relabels or drops it).

Gore placement (``gores.py``) and type smoothing (``type_runs.py``) are the other export rules.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import heading_frame
from hdmap_core.graph.flat import FlatGraph
from hdmap_core.graph.segment_graph import chain_links, feature_chains
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.model import FeatureType

__all__ = ["spur_free", "end_stubs", "inner_borders"]

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: an end stub's far end must also lie this share of the edge's length to the side (a fill that
#: jumps across, not one that drifts along a curve)
_END_STUB_SLOPE = 0.1
#: an end stub (``end_stub_max_m``) is a fill whose far end lies at least this far to the side [m]
_END_STUB_SIDE_M = 2.0

_BORDER_CODE = int(FeatureType.ROAD_BORDER)

_DUP_LINE_M = 1.0  # a marking this close across an inner border is the line it copies

_STUB_COVER_ALONG_M = 2.0  # a stub node's cross-section: this far along its heading (steps are 2 m apart)


def spur_free(flat: FlatGraph, uid: np.ndarray, *, spur_max_m: float, bubble_max_m: float) -> np.ndarray:
    """(N,) keep-mask without spurs: short polylines hanging off a split with no successor, or
    into a merge with no predecessor (a feature flickering into view beside another makes a
    split and an immediate dead end). Two rounds, so that a spur's removal can expose another."""
    nn = flat.n_nodes
    keep = np.ones(nn, dtype=bool)
    for _ in range(2):
        e = flat.edges[keep[flat.edges[:, 0]] & keep[flat.edges[:, 1]]] if len(flat.edges) else flat.edges
        lo = flat.leftover[keep[flat.edges[:, 0]] & keep[flat.edges[:, 1]]] if len(flat.edges) else flat.leftover
        outdeg = np.bincount(e[:, 0], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        indeg = np.bincount(e[:, 1], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
        link = chain_links(nn, e, lo, flat.n_type)
        cross = e[~link] if len(e) else e
        into = dict(zip(cross[:, 1].tolist(), cross[:, 0].tolist()))
        outof = dict(zip(cross[:, 0].tolist(), cross[:, 1].tolist()))
        killed = 0
        chains = feature_chains(nn, e, lo, flat.n_type, uid)
        # bubbles: two short branches from one split node to one merge node (a flicker beside a
        # line that comes back): the branch with fewer drives goes
        by_ends: dict[tuple[int, int], list[np.ndarray]] = {}
        for c in chains:
            first, last = int(c[0]), int(c[-1])
            if first in into and last in outof and outdeg[into[first]] >= 2 and indeg[outof[last]] >= 2:
                by_ends.setdefault((into[first], outof[last]), []).append(c)
        direct = set(map(tuple, cross.tolist()))
        for (u, w), branches in by_ends.items():
            if (u, w) in direct:  # the other branch is the edge u -> w itself
                for c in branches:
                    if float(np.hypot(*np.diff(flat.n_xy[c], axis=0).T).sum()) < bubble_max_m and keep[c].all():
                        keep[c] = False
                        killed += 1
                continue
            if len(branches) < 2:
                continue
            chord = flat.n_xy[w] - flat.n_xy[u]
            nrm = np.array([-chord[1], chord[0]]) / max(float(np.hypot(*chord)), 1e-9)

            def rank(c: np.ndarray) -> tuple[float, float, int]:
                dev = float(np.abs((flat.n_xy[c] - flat.n_xy[u]) @ nrm).mean())
                return (-float(flat.n_count[c].mean()), dev, int(uid[c[0]]))

            branches.sort(key=rank)
            for c in branches[1:]:
                if float(np.hypot(*np.diff(flat.n_xy[c], axis=0).T).sum()) < bubble_max_m and keep[c].all():
                    keep[c] = False
                    killed += 1
        for c in chains:
            if not keep[c[0]] or len(c) > spur_max_m:  # > spur_max_m nodes is surely longer
                continue
            first, last = int(c[0]), int(c[-1])
            has_in, has_out = first in into or indeg[first] > 0, last in outof or outdeg[last] > 0
            if has_in == has_out:
                continue  # isolated (speck filter) or through-going
            length = float(np.hypot(*np.diff(flat.n_xy[c], axis=0).T).sum()) if len(c) > 1 else 0.0
            if length >= spur_max_m:
                continue
            if has_in and outdeg[into[first]] >= 2 if first in into else False:
                keep[c] = False
                killed += 1
            elif has_out and indeg[outof[last]] >= 2 if last in outof else False:
                keep[c] = False
                killed += 1
        if not killed:
            break
    return keep


def end_stubs(flat: FlatGraph, uid: np.ndarray, *, config: StitchConfig, through: bool) -> np.ndarray:
    """(N,) bool: feature nodes of end stubs to drop (``StitchConfig.end_stub_max_m``).

    A stub is the run of drive-supported nodes at a loose end (no edge beyond it, none branching
    off it) up to ``end_stub_max_m`` long, joined to the rest of its line by an edge long enough
    to be filled (> 1.5 ``fill_spacing_m``) whose far end lies at least ``_END_STUB_SIDE_M`` and
    ``_END_STUB_SLOPE`` of the edge's length to the side, measured across the heading of the
    rest's last topology node (the pivot's, not the line's: a line curving away from its pivot,
    e.g. a border bending into a junction, is no jump). The stub and that edge are dropped. With
    ``end_stub_cover_m`` > 0 only where every stub node has a node of another polyline within
    that far across and ``_STUB_COVER_ALONG_M`` along (the road is mapped there; a stub that is
    the only map line on its cross-section stays)."""
    cfg = config
    nn = flat.n_nodes
    drop = np.zeros(nn, dtype=bool)
    e = flat.edges
    fill_m = 1.5 * cfg.fill_spacing_m if cfg.fill_spacing_m > 0 else 3.0
    outdeg = np.bincount(e[:, 0], minlength=nn)
    indeg = np.bincount(e[:, 1], minlength=nn)
    nxt = np.full(nn, -1, dtype=np.int64)
    prv = np.full(nn, -1, dtype=np.int64)
    one_out = outdeg[e[:, 0]] == 1
    one_in = indeg[e[:, 1]] == 1
    nxt[e[one_out, 0]] = e[one_out, 1]
    prv[e[one_in, 1]] = e[one_in, 0]
    node_topo = flat.node_topo()
    heading = flat.t_heading[node_topo]
    xy = flat.n_xy
    cover_m = float(cfg.end_stub_cover_m)
    tree = None
    stubs: list[tuple[list[int], int]] = []
    for tail in (True, False):
        # loose ends: a tail has no out edge and one in edge; a head the other way round
        ends = np.flatnonzero((outdeg == 0) & (indeg == 1)) if tail else np.flatnonzero((indeg == 0) & (outdeg == 1))
        back = prv if tail else nxt
        for i in ends.tolist():
            run = [i]
            length = 0.0
            j = i
            ok = False
            while True:
                k = int(back[j])
                if k < 0:
                    break
                d = float(np.hypot(*(xy[j] - xy[k])))
                if d > fill_m:  # the jumping edge (the rest's end node may also split or merge)
                    ok = True
                    break
                # the stub continues through nodes with no other edge
                if outdeg[k] != 1 or indeg[k] != 1 or flat.n_count[k] <= 0:
                    break
                length += d
                if length > cfg.end_stub_max_m:
                    break
                run.append(k)
                j = k
            if not ok or (flat.n_count[run] <= 0).any():  # a stub is drive-supported
                continue
            p0, p1 = xy[k], xy[j]
            h = float(heading[k])
            v = p1 - p0
            lat = abs(math.cos(h) * v[1] - math.sin(h) * v[0])
            if lat < _END_STUB_SIDE_M or lat < _END_STUB_SLOPE * float(np.hypot(*v)):
                continue
            stubs.append((run, k))
    if not stubs:
        return drop
    if cover_m > 0:
        chains = feature_chains(nn, e, flat.leftover, flat.n_type, uid, through=through)
        chain_of = np.full(nn, -1, dtype=np.int64)
        for c_i, c in enumerate(chains):
            chain_of[c] = c_i
        tree = cKDTree(xy)
        reach = math.hypot(cover_m, _STUB_COVER_ALONG_M)
    for run, k in stubs:
        if tree is not None:
            own = {int(chain_of[run[0]]), int(chain_of[k])}
            covered = True
            for i in run:
                u, n = heading_frame(float(heading[i]))
                near = np.asarray(tree.query_ball_point(xy[i], reach), dtype=np.int64)
                near = near[~np.isin(chain_of[near], list(own))]
                d = xy[near] - xy[i]
                if not ((np.abs(d @ u) <= _STUB_COVER_ALONG_M) & (np.abs(d @ n) <= cover_m)).any():
                    covered = False
                    break
            if not covered:
                continue
        drop[run] = True
    return drop


def inner_borders(
    flat: FlatGraph,
    chains: list[np.ndarray],
    *,
    succ: dict[int, set[int]],
    pred: dict[int, set[int]],
    on_through: set[int],
    reach_m: float,
    max_drives: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(C,) bool: isolated road-border chains of at most ``max_drives`` drives (max over their
    nodes) that run inside the road: at most of their drive-supported nodes a lane marking of
    the same direction lies within ``reach_m`` on both sides. A road border has the road on one
    side only; one drive's marking reported as a border (the simulator's marking_to_border, 1 %
    of marking stretches) lies between two lane lines. Second (C,) bool: at most of those nodes
    a marking also lies within ``_DUP_LINE_M`` across (the line is mapped already)."""
    out = np.zeros(len(chains), dtype=bool)
    dup = np.zeros(len(chains), dtype=bool)
    mark = np.flatnonzero(flat.n_type != _BORDER_CODE)
    if len(mark) == 0:
        return out, dup
    heading = flat.t_heading[flat.node_topo()]
    tree = cKDTree(flat.n_xy[mark])
    cos_h = math.cos(math.radians(30.0))
    for k, c in enumerate(chains):
        if int(flat.n_type[c[0]]) != _BORDER_CODE or succ.get(k) or pred.get(k) or k in on_through:
            continue
        if int(flat.n_count[c].max()) > max_drives:
            continue
        nodes = c[flat.n_count[c] > 0]
        if len(nodes) == 0:
            continue
        # every (node, marking node near it) pair at once: the same tests as node by node
        near = tree.query_ball_point(flat.n_xy[nodes], reach_m)
        lens = np.fromiter((len(x) for x in near), dtype=np.int64, count=len(near))
        at = np.repeat(np.arange(len(nodes)), lens)  # the chain node of each pair
        i = nodes[at]
        j = mark[np.fromiter((q for x in near for q in x), dtype=np.int64, count=int(lens.sum()))]
        ok = np.cos(heading[j] - heading[i]) > cos_h
        at, i, j = at[ok], i[ok], j[ok]
        d = flat.n_xy[j] - flat.n_xy[i]
        lat = d[:, 0] * -np.sin(heading[i]) + d[:, 1] * np.cos(heading[i])
        left, right, line = (np.zeros(len(nodes), dtype=bool) for _ in range(3))
        left[at[lat > 0.5]] = True
        right[at[lat < -0.5]] = True
        line[at[np.abs(lat) <= _DUP_LINE_M]] = True
        out[k] = int((left & right).sum()) > 0.5 * len(nodes)
        dup[k] = int(line.sum()) > 0.5 * len(nodes)
    return out, dup
