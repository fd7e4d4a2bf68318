"""The complete map's hierarchical graph as flat arrays, its clean-up and its export (Sec. VI).

``FlatGraph`` is every live node and edge of a :class:`~hdmap_core.graph.map_graph.MapGraph` in global
indices: the topology graph (one node per used step) and the road-feature graph (one node per
aggregated maximum), with cross references (the feature nodes of topology node ``t`` are
``t_start[t]:t_start[t + 1]``). ``export_map`` cuts the feature graph into polylines
(``segment_graph.feature_chains``, closing rules RULE 1-4), cleans it up (spurs, bubbles, type
flicker, gores) and fills ``MapFeature`` / ``TopologyNode``. ``graph_from_hdmap`` goes the other
way, so that an existing map can be updated.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import nearest_on_same_cut
from hdmap_core.graph.segment_graph import ConnectionStats, SegmentGraph, chain_links, feature_chains, stable_uid
from hdmap_core.model import FeatureType, HDMap, MapFeature, TopologyNode

if TYPE_CHECKING:
    from hdmap_core.graph.stitch_config import StitchConfig

__all__ = ["FlatGraph", "export_map", "graph_from_hdmap"]

_BORDER_CODE = int(FeatureType.ROAD_BORDER)
_UNKNOWN_CODE = int(FeatureType.UNKNOWN)


# --- the flat view of all graphs (FlatGraph) --------------------------------------------------------------------


@dataclass
class FlatGraph:
    """All alive nodes and edges of a MapGraph in global indices (graphs in key order)."""

    keys: list[str]
    tmap: dict[str, np.ndarray]  # per graph: local topo index -> global or -1
    nmap: dict[str, np.ndarray]  # per graph: local feature node index -> global or -1
    t_graph: np.ndarray
    t_local: np.ndarray
    t_uid: np.ndarray
    t_xy: np.ndarray
    t_heading: np.ndarray
    t_width: np.ndarray
    t_start: np.ndarray
    n_graph: np.ndarray
    n_local: np.ndarray
    n_uid: np.ndarray
    n_xy: np.ndarray
    n_type: np.ndarray
    n_count: np.ndarray
    n_std: np.ndarray
    topo_edges: np.ndarray
    edges: np.ndarray
    leftover: np.ndarray

    @property
    def n_topo(self) -> int:
        return len(self.t_uid)

    @property
    def n_nodes(self) -> int:
        return len(self.n_uid)

    def node_topo(self) -> np.ndarray:
        return np.repeat(np.arange(self.n_topo), np.diff(self.t_start))


def _remap(mask: np.ndarray, offset: int) -> np.ndarray:
    out = np.full(len(mask), -1, dtype=np.int64)
    out[mask] = offset + np.arange(int(mask.sum()))
    return out


def _map_edges(e: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(e) == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=bool)
    g = m[e]
    ok = (g >= 0).all(axis=1)
    return g[ok], ok


def _wrap(a: np.ndarray | float) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def _unit(h: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([math.cos(h), math.sin(h)]), np.array([-math.sin(h), math.cos(h)])



# --- export ----------------------------------------------------------------------------------------


def _dedupe_uids(flat: FlatGraph) -> np.ndarray:
    """Node uids, made unique should two graphs carry the same pivot step (rehashed with the key)."""
    uid = flat.n_uid.copy()
    _, first, counts = np.unique(uid, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = np.flatnonzero(np.isin(uid, np.unique(uid)[counts > 1]))
        keep_first = set(first.tolist())
        for i in dup.tolist():
            if i not in keep_first:
                uid[i] = stable_uid(flat.keys[flat.n_graph[i]], int(flat.n_local[i]), 7)[()]
    return uid


def export_map(
    flat: FlatGraph, cfg: StitchConfig, *, protect: np.ndarray | None = None
) -> tuple[tuple[MapFeature, ...], tuple[TopologyNode, ...]]:
    """The polylines and topology nodes of ``flat`` (module docstring). ``protect``: (N,) bool,
    feature nodes whose polylines are not dropped as isolated specks (the ends of fills refuted
    by the negative evidence: a short piece between two junction mouths is drive-supported)."""
    uid = _dedupe_uids(flat)
    protect = np.zeros(flat.n_nodes, dtype=bool) if protect is None else np.asarray(protect, dtype=bool)
    if (cfg.spur_max_m > 0 or cfg.bubble_max_m > 0) and flat.n_nodes:
        keep = _spur_free(flat, uid, cfg.spur_max_m, cfg.bubble_max_m)
        if not keep.all():
            flat, uid, protect = _subset_nodes(flat, keep), uid[keep], protect[keep]
    nn = flat.n_nodes
    e = flat.edges
    if getattr(cfg, "edge_line_solid_m", 0.0) > 0 and nn:
        flat.n_type = _edge_lines_solid(flat, cfg.edge_line_solid_m, cfg.edge_line_max_drives)
    if cfg.min_type_run_m > 0 and nn:
        flat.n_type = _smooth_types(
            flat, uid, cfg.min_type_run_m, getattr(cfg, "sparse_type_run_m", 0.0), getattr(cfg, "sparse_drive_count", 0),
            minority_only=getattr(cfg, "sparse_minority_only", False),
            single_run_m=getattr(cfg, "single_drive_run_m", 0.0),
            end_run_m=getattr(cfg, "single_drive_end_run_m", 0.0),
            end_run_through=getattr(cfg, "single_drive_end_through_leftover", False),
        )
    unknown = flat.n_type == _UNKNOWN_CODE
    if unknown.any():
        # RULE unknown type: a line of unknown type that continues no typed line is dropped
        keep_n = ~unknown
        flat, uid, protect = _subset_nodes(flat, keep_n), uid[keep_n], protect[keep_n]
        nn, e = flat.n_nodes, flat.edges
    through = getattr(cfg, "through_lines", False)
    if getattr(cfg, "end_stub_max_m", 0.0) > 0 and len(e):
        drop = _end_stubs(flat, uid, cfg, through=through)
        if drop.any():
            keep_n = ~drop
            flat, uid, protect = _subset_nodes(flat, keep_n), uid[keep_n], protect[keep_n]
            nn, e = flat.n_nodes, flat.edges
    chains = feature_chains(nn, e, flat.leftover, flat.n_type, uid, through=through)
    link = chain_links(nn, e, flat.leftover, flat.n_type, through=through)
    outdeg = np.bincount(e[:, 0], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
    indeg = np.bincount(e[:, 1], minlength=nn) if len(e) else np.zeros(nn, dtype=np.int64)
    chain_of = np.full(nn, -1, dtype=np.int64)
    is_first = np.zeros(nn, dtype=bool)
    is_last = np.zeros(nn, dtype=bool)
    for k, c in enumerate(chains):
        chain_of[c] = k
        is_first[c[0]] = True
        is_last[c[-1]] = True
    cross = e[~link] if len(e) else e
    succ: dict[int, set[int]] = {}
    pred: dict[int, set[int]] = {}
    in_cross: dict[int, list[int]] = {}
    out_cross: dict[int, list[int]] = {}
    # a branch starting (ending) on the interior of a through line (``through_lines``) is no
    # successor (predecessor) link -- a link joins a last point to a first point -- but is drawn
    # from (to) the through line's node: (through chain, branch chain, "split" | "merge")
    attached: list[tuple[int, int, str]] = []
    for a, b in cross.tolist():
        ca, cb = int(chain_of[a]), int(chain_of[b])
        out_cross.setdefault(a, []).append(b)
        in_cross.setdefault(b, []).append(a)
        if is_last[a] and is_first[b]:
            succ.setdefault(ca, set()).add(cb)
            pred.setdefault(cb, set()).add(ca)
        elif is_first[b]:
            attached.append((ca, cb, "split"))
        elif is_last[a]:
            attached.append((cb, ca, "merge"))

    # geometry with junction points: a split's branches start at the split point, a merge's
    # inflows end at the merge point, a type change meets in the middle of its edge
    geoms = []
    for c in chains:
        idx = c.tolist()
        xy = flat.n_xy[c]
        cnt, std = flat.n_count[c], flat.n_std[c]
        f, last = idx[0], idx[-1]
        head = tail = None
        if len(in_cross.get(f, ())) == 1:
            u = in_cross[f][0]
            if outdeg[u] >= 2:
                head = flat.n_xy[u]
            elif indeg[f] == 1:
                head = 0.5 * (flat.n_xy[u] + flat.n_xy[f])
        if len(out_cross.get(last, ())) == 1 and outdeg[last] == 1:
            w = out_cross[last][0]
            if indeg[w] >= 2:
                tail = flat.n_xy[w]
            else:
                tail = 0.5 * (flat.n_xy[last] + flat.n_xy[w])
        if head is not None:
            xy, cnt, std = np.vstack([head, xy]), np.r_[cnt[:1], cnt], np.r_[std[:1], std]
        if tail is not None:
            xy, cnt, std = np.vstack([xy, tail]), np.r_[cnt, cnt[-1:]], np.r_[std, std[-1:]]
        if cfg.fill_spacing_m > 0 and len(xy) > 2:
            xy, cnt, std = _fill_gaps(xy, cnt, std, cfg.fill_spacing_m)
        geoms.append((xy, cnt, std))

    keep = np.ones(len(chains), dtype=bool)
    on_through = {k for t, b, _ in attached for k in (t, b)}
    for k, (xy, _, _) in enumerate(geoms):
        if len(xy) < 2:  # one point is no polyline: drop it, its neighbours link past it
            keep[k] = False
            ps, ss = pred.pop(k, set()), succ.pop(k, set())
            for p_ in ps:
                succ[p_].discard(k)
                succ[p_].update(x for x in ss if x != p_)
            for s_ in ss:
                pred[s_].discard(k)
                pred[s_].update(x for x in ps if x != s_)
    for k, (xy, _, _) in enumerate(geoms):
        if not keep[k]:
            continue
        isolated = not succ.get(k) and not pred.get(k) and k not in on_through
        length = float(np.hypot(*np.diff(xy, axis=0).T).sum()) if len(xy) > 1 else 0.0
        if isolated and (len(xy) < 2 or (length < cfg.min_isolated_length_m and not protect[chains[k]].any())):
            keep[k] = False
        elif (isolated and length < cfg.refuted_piece_min_m and protect[chains[k]].any()
              and int(np.max(geoms[k][1])) <= cfg.refuted_piece_max_drives):
            keep[k] = False  # one drive's speck left between refuted fills
    inner_m = getattr(cfg, "inner_border_max_m", 0.0)
    ctype = [int(flat.n_type[c[0]]) for c in chains]
    if inner_m > 0:
        inner, dup = _inner_borders(flat, chains, succ, pred, on_through, inner_m, getattr(cfg, "inner_border_max_drives", 1))
        as_line = getattr(cfg, "inner_border_dashed_drives", 0)
        for k in np.flatnonzero(inner & keep).tolist():
            if not dup[k] and int(flat.n_count[chains[k]].max()) <= as_line:
                # one drive's lane line reported as a border: a line between lane lines is
                # dashed (98 % of such points in the shared ground-truth maps)
                ctype[k] = int(FeatureType.DASHED)
            else:
                keep[k] = False
    fid = np.array([int(uid[c[0]]) for c in chains], dtype=np.uint64)
    runs = _continuation_runs(keep, succ, pred, ctype, fid) if cfg.merge_continuations else [[k] for k in np.flatnonzero(keep).tolist()]
    head_of = np.arange(len(chains))
    for run in runs:
        head_of[run] = run[0]

    features = []
    for run in runs:
        k0, k1 = run[0], run[-1]
        parts = [geoms[k] for k in run]
        xy = parts[0][0]
        cnt, std = parts[0][1], parts[0][2]
        for pxy, pcnt, pstd in parts[1:]:
            dup = len(xy) and len(pxy) and float(np.hypot(*(xy[-1] - pxy[0]))) < 1e-6
            xy, cnt, std = np.vstack([xy, pxy[dup:]]), np.r_[cnt, pcnt[dup:]], np.r_[std, pstd[dup:]]
        features.append(
            MapFeature(
                id=int(fid[k0]),
                type=_ftype(ctype[k0]),
                points=np.ascontiguousarray(xy, dtype=float),
                drive_count=np.asarray(cnt, dtype=np.int64),
                lateral_std=np.asarray(std, dtype=float),
                predecessors=tuple(sorted({int(fid[head_of[p]]) for p in pred.get(k0, ()) if keep[p]})),
                successors=tuple(sorted({int(fid[head_of[s]]) for s in succ.get(k1, ()) if keep[s]})),
            )
        )

    # topology: successors by uid, and the kept features crossing each step (in lateral order)
    te = flat.topo_edges
    t_uid = flat.t_uid.tolist()
    tsucc: dict[int, set[int]] = {}
    for a, b in te.tolist():
        tsucc.setdefault(a, set()).add(t_uid[b])
    fid_node = np.where(keep[chain_of], fid[head_of[chain_of]].astype(np.int64), -1).tolist() if nn else []
    bounds = flat.t_start.tolist()
    xy_l, hd_l, w_l = flat.t_xy, flat.t_heading.tolist(), flat.t_width.tolist()
    topology = []
    for t in range(flat.n_topo):
        feats = tuple(dict.fromkeys(f for f in fid_node[bounds[t] : bounds[t + 1]] if f >= 0))
        topology.append(
            TopologyNode(
                id=t_uid[t],
                position=xy_l[t].copy(),
                heading=hd_l[t],
                width=w_l[t],
                successors=tuple(sorted(tsucc.get(t, ()))),
                features=feats,
            )
        )
    if cfg.gore_max_m > 0:
        if attached:
            branch_of = [(int(fid[head_of[t]]), int(fid[head_of[b]]), kind) for t, b, kind in attached if keep[t] and keep[b]]
            features, topology = _gore_branches(features, topology, branch_of, cfg.gore_max_m)
        features, topology = _gore_junctions(features, topology, cfg.gore_max_m)
    features.sort(key=lambda f: f.id)
    topology.sort(key=lambda t: t.id)
    return tuple(features), tuple(topology)


def _inner_borders(
    flat: FlatGraph,
    chains: list[np.ndarray],
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
        inside = on_line = 0
        for i, near in zip(nodes.tolist(), tree.query_ball_point(flat.n_xy[nodes], reach_m)):
            j = mark[np.asarray(near, dtype=np.int64)]
            j = j[np.cos(heading[j] - heading[i]) > cos_h]
            if len(j) == 0:
                continue
            lat = (flat.n_xy[j] - flat.n_xy[i]) @ np.array([-math.sin(heading[i]), math.cos(heading[i])])
            inside += bool((lat > 0.5).any() and (lat < -0.5).any())
            on_line += bool((np.abs(lat) <= _DUP_LINE_M).any())
        out[k] = inside > 0.5 * len(nodes)
        dup[k] = on_line > 0.5 * len(nodes)
    return out, dup


_DUP_LINE_M = 1.0  # a marking this close across an inner border is the line it copies


_STUB_COVER_ALONG_M = 2.0  # a stub node's cross-section: this far along its heading (steps are 2 m apart)


def _end_stubs(flat: FlatGraph, uid: np.ndarray, cfg: StitchConfig, *, through: bool) -> np.ndarray:
    """(N,) bool: feature nodes of end stubs to drop (``StitchConfig.end_stub_max_m``).

    A stub is the run of drive-supported nodes at a loose end (no edge beyond it, none branching
    off it) up to ``end_stub_max_m`` long, joined to the rest of its line by an edge long enough
    to be filled (> 1.5 ``fill_spacing_m``) whose far end lies at least ``end_stub_side_m`` and
    ``end_stub_slope`` of the edge's length to the side, measured across the heading of the
    rest's last topology node (the pivot's, not the line's: a line curving away from its pivot,
    e.g. a border bending into a junction, is no jump). The stub and that edge are dropped. With
    ``end_stub_cover_m`` > 0 only where every stub node has a node of another polyline within
    that far across and ``_STUB_COVER_ALONG_M`` along (the road is mapped there; a stub that is
    the only map line on its cross-section stays)."""
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
    cover_m = float(getattr(cfg, "end_stub_cover_m", 0.0))
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
            if lat < cfg.end_stub_side_m or lat < cfg.end_stub_slope * float(np.hypot(*v)):
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
                u, n = _unit(float(heading[i]))
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


def _continuation_runs(
    keep: np.ndarray, succ: dict[int, set[int]], pred: dict[int, set[int]], ctype: list[int], fid: np.ndarray
) -> list[list[int]]:
    """Kept chains grouped into runs that are one polyline: k -> s when s is k's only kept
    successor, k is s's only kept predecessor and both have one type. Each run lists its chains
    in driving direction; a closed ring of such links is opened at its smallest feature id."""
    nxt: dict[int, int] = {}
    has_prev: set[int] = set()
    for k in np.flatnonzero(keep).tolist():
        ss = [x for x in succ.get(k, ()) if keep[x]]
        if len(ss) != 1 or ss[0] == k or ctype[ss[0]] != ctype[k]:
            continue
        s = ss[0]
        ps = [x for x in pred.get(s, ()) if keep[x]]
        if ps == [k]:
            nxt[k] = s
            has_prev.add(s)
    runs: list[list[int]] = []
    seen: set[int] = set()

    def walk(k: int) -> list[int]:
        run = [k]
        seen.add(k)
        while run[-1] in nxt and nxt[run[-1]] not in seen:
            run.append(nxt[run[-1]])
            seen.add(run[-1])
        return run

    for k in np.flatnonzero(keep).tolist():
        if k not in has_prev:
            runs.append(walk(k))
    for k in sorted((k for k in np.flatnonzero(keep).tolist() if k not in seen), key=lambda k: int(fid[k])):
        if k not in seen:  # on a ring of continuations
            runs.append(walk(k))
    return runs


def _length(points: np.ndarray) -> float:
    return float(np.hypot(*np.diff(points, axis=0).T).sum()) if len(points) > 1 else 0.0


def _gore_branches(
    features: list[MapFeature], topology: list[TopologyNode], branches: list[tuple[int, int, str]], max_m: float
) -> tuple[list[MapFeature], list[TopologyNode]]:
    """``_gore_junctions`` for through lines: a branch of the through line's own type that starts
    on it at most ``max_m`` after the through line began at a type change (a gore: the lane line
    ends, two solid lines start and are resolved as two only tens of metres on) gets the common
    piece prepended and the lane line as its predecessor, so the split sits where the lane line
    ends. Merges mirror this.

    Args:
        branches: (through feature id, branch feature id, "split" | "merge").
    """
    from dataclasses import replace as _replace

    byid = {f.id: f for f in features}
    changed = False
    for tid, bid, kind in sorted(branches):
        c, b = byid.get(tid), byid.get(bid)
        if c is None or b is None or b.type != c.type or len(c.points) < 2 or len(b.points) < 2:
            continue
        outer = c.predecessors if kind == "split" else c.successors
        if len(outer) != 1 or outer[0] not in byid or byid[outer[0]].type == c.type:
            continue
        if (b.predecessors if kind == "split" else b.successors):
            continue
        p = byid[outer[0]]
        end = b.points[0] if kind == "split" else b.points[-1]
        i = int(np.argmin(np.hypot(*(np.asarray(c.points) - end).T)))
        if float(np.hypot(*(c.points[i] - end))) > 1e-6:
            continue
        # The common piece is the one maximum of two lines not yet resolved, i.e. their middle:
        # both lines leave the lane line's end tangentially and are ``sep`` apart where first
        # resolved, so over the piece each is moved half the separation, growing with the square
        # of the distance from the lane line's end (a line leaving tangentially), to its side.
        cp = np.asarray(c.points, dtype=float)
        if kind == "split":
            if i == 0 or i + 1 >= len(cp) or _length(cp[: i + 1]) > max_m:
                continue
            arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(cp[: i + 2], axis=0).T))]
            half = 0.5 * (np.asarray(b.points[1], dtype=float) - cp[i + 1])
            shift = ((arc[: i + 1] / max(arc[i + 1], 1e-9)) ** 2)[:, None] * half
            common, rest = slice(0, i + 1), np.asarray(b.points[1:], dtype=float)
            b = _replace(b, points=np.vstack([cp[common] + shift, rest]),
                         drive_count=np.r_[c.drive_count[: i + 1], b.drive_count[1:]],
                         lateral_std=np.r_[c.lateral_std[: i + 1], b.lateral_std[1:]], predecessors=(p.id,))
            p = _replace(p, successors=tuple(sorted(set(p.successors) | {b.id})))
        else:
            if i == len(cp) - 1 or i == 0 or _length(cp[i:]) > max_m:
                continue
            arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(cp[i - 1 :][::-1], axis=0).T))][::-1]  # to the end
            half = 0.5 * (np.asarray(b.points[-2], dtype=float) - cp[i - 1])
            shift = ((arc[1:] / max(arc[0], 1e-9)) ** 2)[:, None] * half
            common, rest = slice(i, len(cp)), np.asarray(b.points[:-1], dtype=float)
            b = _replace(b, points=np.vstack([rest, cp[common] + shift]),
                         drive_count=np.r_[b.drive_count[:-1], c.drive_count[i:]],
                         lateral_std=np.r_[b.lateral_std[:-1], c.lateral_std[i:]], successors=(p.id,))
            p = _replace(p, predecessors=tuple(sorted(set(p.predecessors) | {b.id})))
        cp = cp.copy()
        cp[common] -= shift
        c = _replace(c, points=cp)
        byid[b.id], byid[p.id], byid[c.id] = b, p, c
        changed = True
    if not changed:
        return features, topology
    return [byid[f.id] for f in features], topology


def _gore_junctions(
    features: list[MapFeature], topology: list[TopologyNode], max_m: float
) -> tuple[list[MapFeature], list[TopologyNode]]:
    """Move splits (merges) of gore lines back (forward) to where the lane line's type changes.

    At a gore a lane line (dashed) ends and two solid lines start from its end and diverge slowly;
    the aggregation resolves them as two only once they are ~1 m apart, so the connection yields
    dashed -> one solid -> split into two solids, the split tens of metres late. The common solid
    piece is both lines at once: when it is at most ``max_m`` long, starts at a type change and
    splits into two polylines of its own type, it is prepended to both branches, which become the
    lane line's two successors. Merges mirror this.
    """
    from dataclasses import replace as _replace

    byid = {f.id: f for f in features}
    gone: dict[int, tuple[int, ...]] = {}  # removed common piece -> the branches that absorbed it
    for c in sorted(features, key=lambda f: f.id):
        if c.id in gone or _length(c.points) > max_m:
            continue
        for mode in ("split", "merge"):
            outer = c.predecessors if mode == "split" else c.successors
            branches = c.successors if mode == "split" else c.predecessors
            if len(outer) != 1 or len(branches) != 2 or outer[0] in gone or any(b in gone for b in branches):
                continue
            p = byid[outer[0]]
            bs = [byid[b] for b in branches]
            if p.type == c.type or any(b.type != c.type for b in bs):
                continue
            back = (lambda b: b.predecessors) if mode == "split" else (lambda b: b.successors)
            if any(back(b) != (c.id,) for b in bs):
                continue
            for b in bs:
                if mode == "split":
                    pts = np.vstack([c.points, b.points[1:]])
                    cnt, std = np.r_[c.drive_count, b.drive_count[1:]], np.r_[c.lateral_std, b.lateral_std[1:]]
                    byid[b.id] = _replace(b, points=pts, drive_count=cnt, lateral_std=std, predecessors=(p.id,))
                else:
                    pts = np.vstack([b.points[:-1], c.points])
                    cnt, std = np.r_[b.drive_count[:-1], c.drive_count], np.r_[b.lateral_std[:-1], c.lateral_std]
                    byid[b.id] = _replace(b, points=pts, drive_count=cnt, lateral_std=std, successors=(p.id,))
            links = p.successors if mode == "split" else p.predecessors
            new_links = tuple(sorted({x for x in links if x != c.id} | set(branches)))
            byid[p.id] = _replace(p, **({"successors": new_links} if mode == "split" else {"predecessors": new_links}))
            gone[c.id] = tuple(branches)
            del byid[c.id]
            break
    if not gone:
        return features, topology
    topo = []
    for t in topology:
        if any(f in gone for f in t.features):
            feats: list[int] = []
            for f in t.features:
                for g in gone.get(f, (f,)):
                    if g not in feats:
                        feats.append(g)
            t = _replace(t, features=tuple(feats))
        topo.append(t)
    return list(byid.values()), topo


def _spur_free(flat: FlatGraph, uid: np.ndarray, spur_max_m: float, bubble_max_m: float) -> np.ndarray:
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


def _subset_nodes(flat: FlatGraph, keep: np.ndarray) -> FlatGraph:
    """The flat graph restricted to the kept feature nodes (topology unchanged)."""
    new_idx = np.full(len(keep), -1, dtype=np.int64)
    new_idx[keep] = np.arange(int(keep.sum()))
    e, ok = _map_edges(flat.edges, new_idx)
    leftover = flat.leftover[ok] if len(ok) else flat.leftover
    if len(e):
        # a leftover edge whose sibling branch was pruned no longer joins a split or merge
        outdeg = np.bincount(e[:, 0], minlength=int(keep.sum()))
        indeg = np.bincount(e[:, 1], minlength=int(keep.sum()))
        leftover = leftover & ((outdeg[e[:, 0]] >= 2) | (indeg[e[:, 1]] >= 2))
    per_topo = np.bincount(flat.node_topo()[keep], minlength=flat.n_topo)
    return FlatGraph(
        keys=flat.keys,
        tmap=flat.tmap,
        nmap={k: np.where(v >= 0, new_idx[np.maximum(v, 0)], -1) for k, v in flat.nmap.items()},
        t_graph=flat.t_graph,
        t_local=flat.t_local,
        t_uid=flat.t_uid,
        t_xy=flat.t_xy,
        t_heading=flat.t_heading,
        t_width=flat.t_width,
        t_start=np.concatenate([[0], np.cumsum(per_topo)]).astype(np.int64),
        n_graph=flat.n_graph[keep],
        n_local=flat.n_local[keep],
        n_uid=flat.n_uid[keep],
        n_xy=flat.n_xy[keep],
        n_type=flat.n_type[keep],
        n_count=flat.n_count[keep],
        n_std=flat.n_std[keep],
        topo_edges=flat.topo_edges,
        edges=e,
        leftover=leftover,
    )


def _edge_lines_solid(flat: FlatGraph, within_m: float, max_drives: int) -> np.ndarray:
    """(N,) node types with weakly supported (or unknown) markings beside a border of their
    cross-section typed solid (``StitchConfig.edge_line_solid_m``)."""
    types = flat.n_type.copy()
    topo = flat.node_topo()
    border = types == _BORDER_CODE
    weak = ~border & ((types == _UNKNOWN_CODE) | (flat.n_count <= max_drives))
    if not (weak.any() and border.any()):
        return types
    h = flat.t_heading[topo]
    nrm = np.stack([-np.sin(h), np.cos(h)], axis=1)
    lat = np.einsum("ij,ij->i", flat.n_xy - flat.t_xy[topo], nrm)
    # the laterally nearest border of the same topology node (cut widths are < 1e3 m)
    bi, wi = np.flatnonzero(border), np.flatnonzero(weak)
    _, near = nearest_on_same_cut(topo[wi], lat[wi], topo[bi], lat[bi], width=1e3)
    # RULE edge line: the marking beside the road's border is its solid edge line
    types[wi[near <= within_m]] = int(FeatureType.SOLID)
    return types


def _smooth_types(
    flat: FlatGraph,
    uid: np.ndarray,
    min_run_m: float,
    sparse_run_m: float = 0.0,
    sparse_count: int = 0,
    *,
    minority_only: bool = False,
    single_run_m: float = 0.0,
    end_run_m: float = 0.0,
    end_run_through: bool = False,
) -> np.ndarray:
    """Marking types with short runs along a polyline relabelled to their neighbours' type.

    Aggregated types flicker where drives misclassify dashed/solid (5-10 % of stretches), and every
    flicker would close the polyline (RULE 1). A run of one marking type shorter than
    ``min_run_m`` inside a polyline takes the type of its longer neighbouring run; runs are merged
    shortest first. Road borders and markings are never relabelled into each other. A run between
    two runs of one other type (a flicker: A B A) seen by at most ``sparse_count`` drives (median
    over its nodes) is relabelled up to ``sparse_run_m``: with 1-3 drives one drive's
    misclassification decides the type for tens of metres. With ``minority_only`` such a run of
    two or more drives is relabelled only when the better supported of its neighbour runs has
    more drives (median); a flicker run of one drive is relabelled up to ``single_run_m`` when it
    is not longer than both of its neighbour runs. A run at the polyline's end seen by one drive
    is relabelled up to ``end_run_m`` when it is not longer than its one neighbour run and that
    run was seen by more drives. With ``end_run_through`` that end rule alone is judged once more
    afterwards, along chains that go on through leftover edges (1:1): the exported polyline goes
    on there, so the chain's end is no line's end and its neighbour run lies beyond the edge.

    Returns:
        (N,) int type codes.
    """
    types = flat.n_type.copy()
    is_border = (types == _BORDER_CODE).astype(np.int64)
    chains = feature_chains(flat.n_nodes, flat.edges, flat.leftover, is_border, uid)
    for c in chains:
        if len(c) < 3 or is_border[c[0]]:
            continue
        t = types[c]
        cut = np.flatnonzero(t[1:] != t[:-1]) + 1
        if len(cut) == 0:
            continue
        seg = np.r_[0.0, np.hypot(*np.diff(flat.n_xy[c], axis=0).T)]
        bounds = np.r_[0, cut, len(c)].tolist()
        runs = [[bounds[k], bounds[k + 1], int(t[bounds[k]])] for k in range(len(bounds) - 1)]

        def length(r: list[int]) -> float:
            return float(seg[r[0] + 1 : r[1]].sum() + (seg[r[1]] if r[1] < len(c) else 0.0))

        cnt = flat.n_count[c]

        def med(r: list[int]) -> float:
            return float(np.median(cnt[r[0] : r[1]]))

        def short(i: int) -> bool:
            r = runs[i]
            if length(r) < min_run_m or r[2] == _UNKNOWN_CODE:
                # RULE unknown type: a line whose drives disagreed on its type (a type clash kept,
                # hdmap_core.pipeline.alignment) takes the type of the line it continues
                return True
            # RULE flicker: only a run between two runs of one other type (A B A)
            if not (0 < i < len(runs) - 1 and runs[i - 1][2] == runs[i + 1][2]):
                return False
            m = med(r)
            if length(r) < sparse_run_m and m <= sparse_count:
                # RULE minority: a run of >= 2 drives is one drive's misclassification only when
                # the runs beside it were seen by more drives (on 30-drive CARLA fleets 3-drive
                # solid runs between 2-3-drive dashed runs are real: the lines before junctions)
                if not minority_only or m <= 1 or m < max(med(runs[i - 1]), med(runs[i + 1])):
                    return True
            # RULE single drive: one drive's type is no evidence against the line's type before
            # and after it, over a whole misclassified stretch (20-200 m in the simulator) --
            # unless the run is longer than both neighbours (S 78 m, D 145 m, S 77 m of one
            # drive: the two short runs are the likelier misclassification)
            longest = length(r) > max(length(runs[i - 1]), length(runs[i + 1]))
            return length(r) < single_run_m and m <= 1 and not longest

        def end_short(i: int) -> bool:
            # RULE single-drive end: one drive's type at a polyline's end is no evidence against
            # the type better supported drives gave the line before it (the flicker rules want a
            # neighbour on both sides). Judged last, when no other run is to be merged: a
            # neighbour that is itself short or a flicker is no run of its own yet.
            if not (i == 0 or i == len(runs) - 1):
                return False
            r, nb = runs[i], (runs[1] if i == 0 else runs[-2])
            m = med(r)
            return m <= 1 and med(nb) > m and length(r) < end_run_m and length(r) <= length(nb)

        while len(runs) > 1:
            cand = [i for i in range(len(runs)) if short(i)]
            if not cand and end_run_m > 0:
                cand = [i for i in range(len(runs)) if end_short(i)]
            if not cand:
                break
            k = min(cand, key=lambda i: (length(runs[i]), i))
            left = runs[k - 1] if k > 0 else None
            right = runs[k + 1] if k + 1 < len(runs) else None
            into = left if right is None or (left is not None and length(left) >= length(right)) else right
            runs[k][2] = into[2]
            merged: list[list[int]] = []
            for r in runs:  # join neighbours of equal type
                if merged and merged[-1][2] == r[2]:
                    merged[-1][1] = r[1]
                else:
                    merged.append(r)
            runs = merged
        for a, b, ty in runs:
            t[a:b] = ty
        types[c] = t
    if end_run_through and end_run_m > 0:
        # RULE single-drive end across leftover edges: only the end rule (no min run, no flicker:
        # along the longer chains the single-drive flicker rule relabelled true runs)
        g = copy.copy(flat)
        g.n_type = types
        g.leftover = np.zeros_like(flat.leftover)
        types = _smooth_types(g, uid, 0.0, end_run_m=end_run_m)
    return types


def _fill_gaps(
    xy: np.ndarray, cnt: np.ndarray, std: np.ndarray, spacing_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fill polyline edges longer than 1.5 x spacing with cubic Hermite points.

    Args:
        xy: (N, 2) points [m], N >= 3; cnt: (N,) drive counts; std: (N,) lateral std [m].

    Returns:
        The same arrays with the filled points inserted (count 0, std the larger of the ends').
    """
    seg = np.hypot(*np.diff(xy, axis=0).T)
    long = np.flatnonzero(seg > 1.5 * spacing_m)
    if len(long) == 0:
        return xy, cnt, std
    # tangents: central differences, one-sided at the ends, scaled per edge below
    tang = np.gradient(xy, axis=0)
    tang /= np.maximum(np.hypot(*tang.T), 1e-12)[:, None]
    pieces_xy, pieces_c, pieces_s = [], [], []
    prev = 0
    for k in long.tolist():
        pieces_xy.append(xy[prev : k + 1])
        pieces_c.append(cnt[prev : k + 1])
        pieces_s.append(std[prev : k + 1])
        n_new = int(math.ceil(seg[k] / spacing_m)) - 1
        t = (np.arange(1, n_new + 1) / (n_new + 1))[:, None]
        p0, p1 = xy[k], xy[k + 1]
        # tangents of the neighbouring edges (not through the gap itself)
        m0 = (xy[k] - xy[k - 1]) if k > 0 else (p1 - p0)
        m1 = (xy[k + 2] - xy[k + 1]) if k + 2 < len(xy) else (p1 - p0)
        m0 = m0 / max(np.hypot(*m0), 1e-12) * seg[k]
        m1 = m1 / max(np.hypot(*m1), 1e-12) * seg[k]
        h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
        pieces_xy.append(h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1)
        pieces_c.append(np.zeros(n_new, dtype=cnt.dtype))
        pieces_s.append(np.full(n_new, max(std[k], std[k + 1])))
        prev = k + 1
    pieces_xy.append(xy[prev:])
    pieces_c.append(cnt[prev:])
    pieces_s.append(std[prev:])
    del tang
    return np.vstack(pieces_xy), np.concatenate(pieces_c), np.concatenate(pieces_s)


def _ftype(code: int) -> FeatureType:
    try:
        return FeatureType(code)
    except ValueError:
        return FeatureType.UNKNOWN



def _attachments(feats: list[MapFeature]) -> list[tuple[int, str, int, int]]:
    """Branches drawn on a through line: (branch id, "split" | "merge", through id, index of the
    through line's interior point that is the branch's first (split) or last (merge) point). Only
    an end without a link counts, of a feature with >= 3 points, on a line of its class."""
    pts = [np.asarray(f.points, dtype=float)[:, :2] for f in feats]
    if not pts or sum(len(p) for p in pts) == 0:
        return []
    allp = np.concatenate(pts)
    owner = np.repeat(np.arange(len(feats)), [len(p) for p in pts])
    index = np.concatenate([np.arange(len(p)) for p in pts])
    tree = cKDTree(allp)
    border = [int(f.type) == _BORDER_CODE for f in feats]
    out = []
    for a, f in enumerate(feats):
        if len(pts[a]) < 3:
            continue
        for kind, q, linked in (("split", pts[a][0], f.predecessors), ("merge", pts[a][-1], f.successors)):
            if linked:
                continue
            for k in sorted(tree.query_ball_point(q, 1e-6)):
                g = int(owner[k])
                if g != a and border[g] == border[a] and 0 < index[k] < len(pts[g]) - 1:
                    out.append((int(f.id), kind, int(feats[g].id), int(index[k])))
                    break
    return out


def graph_from_hdmap(hdmap: HDMap, *, key: str = "base", tile_size_m: float = 256.0) -> SegmentGraph:
    """Rebuild a hierarchical graph from an ``HDMap`` so that new segments can be stitched to it.

    Each feature point becomes a feature node, attached to the nearest topology node that lists
    the feature (else the nearest one); junction points added at export (split/merge/type change)
    are removed again so that a re-export does not duplicate them. The first node of every feature
    carries the feature's id, so an unchanged feature keeps its id.
    """
    feats = list(hdmap.features)
    topo = list(hdmap.topology)
    by_id = {int(f.id): f for f in feats}
    t_index = {int(t.id): k for k, t in enumerate(topo)}
    lo: dict[int, int] = {}
    hi: dict[int, int] = {}
    for f in feats:
        lo[int(f.id)], hi[int(f.id)] = 0, len(f.points)
    for f in feats:  # drop junction points that duplicate a neighbour's point
        for s in f.successors:
            g = by_id.get(int(s))
            if g is None or len(g.points) == 0 or len(f.points) == 0:
                continue
            if np.hypot(*(np.asarray(g.points[0]) - np.asarray(f.points[-1]))) < 1e-6:
                merge = len(g.predecessors) >= 2
                split = len(f.successors) >= 2
                if merge and not split and hi[int(f.id)] - lo[int(f.id)] > 1:
                    hi[int(f.id)] -= 1
                elif hi[int(g.id)] - lo[int(g.id)] > 1:
                    lo[int(g.id)] += 1
                    if not (merge or split) and hi[int(f.id)] - lo[int(f.id)] > 1:
                        hi[int(f.id)] -= 1
    # a branch drawn from (to) a through line's interior (``through_lines``): its first (last)
    # point is the through line's node; it becomes a leftover edge again, the point is dropped
    attach = _attachments(feats)
    for bid, kind, _, _ in attach:
        if kind == "split":
            lo[bid] += 1
        else:
            hi[bid] -= 1
    # topology
    if topo:
        t_xy = np.array([np.asarray(t.position, dtype=float)[:2] for t in topo])
        t_h = np.array([float(t.heading) for t in topo])
        t_w = np.array([float(t.width) for t in topo])
        t_uid = np.array([int(t.id) for t in topo], dtype=np.uint64)
    else:
        t_xy, t_h, t_w, t_uid = np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.uint64)
    t_edges = [(k, t_index[int(s)]) for k, t in enumerate(topo) for s in t.successors if int(s) in t_index]
    listing: dict[int, list[int]] = {}
    for k, t in enumerate(topo):
        for fid in t.features:
            listing.setdefault(int(fid), []).append(k)
    tree = cKDTree(t_xy) if len(t_xy) else None

    n_xy, n_type, n_cnt, n_std, n_uid, n_topo, n_feat, n_pos = [], [], [], [], [], [], [], []
    extra_topo: list[tuple[np.ndarray, float]] = []
    for f in feats:
        fid = int(f.id)
        pts = np.asarray(f.points, dtype=float)[:, :2][lo[fid] : hi[fid]]
        if len(pts) == 0:
            continue
        cnt = np.asarray(f.drive_count)[lo[fid] : hi[fid]] if len(f.drive_count) else np.zeros(len(pts))
        std = np.asarray(f.lateral_std)[lo[fid] : hi[fid]] if len(f.lateral_std) else np.zeros(len(pts))
        cand = listing.get(fid, [])
        if cand:
            d = np.linalg.norm(pts[:, None, :] - t_xy[cand][None, :, :], axis=2)
            tk = np.asarray(cand)[np.argmin(d, axis=1)]
        elif tree is not None:
            tk = tree.query(pts)[1]
        else:  # a map without topology: one pseudo topology node per feature point
            hdg = np.arctan2(*np.diff(pts, axis=0).T[::-1]) if len(pts) > 1 else np.zeros(1)
            hdg = np.r_[hdg, hdg[-1:]][: len(pts)]
            tk = len(topo) + len(extra_topo) + np.arange(len(pts))
            extra_topo.extend((p, float(h)) for p, h in zip(pts, hdg))
        uids = stable_uid(f"base:{fid}", np.arange(len(pts)))
        uids[0] = np.uint64(fid & ((1 << 63) - 1)) or np.uint64(1)
        n_xy.append(pts)
        n_type.append(np.full(len(pts), int(f.type)))
        n_cnt.append(cnt)
        n_std.append(std)
        n_uid.append(uids)
        n_topo.append(np.asarray(tk, dtype=np.int64))
        n_feat.append(np.full(len(pts), fid, dtype=np.uint64))
        n_pos.append(np.arange(len(pts)))
    if extra_topo:
        t_xy = np.vstack([t_xy, np.array([p for p, _ in extra_topo])])
        t_h = np.r_[t_h, [h for _, h in extra_topo]]
        t_w = np.r_[t_w, np.zeros(len(extra_topo))]
        t_uid = np.r_[t_uid, stable_uid("base-topo", np.arange(len(extra_topo)))]

    def cat(parts, shape, dtype):
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype=dtype)

    xy = cat(n_xy, (0, 2), float)
    tk = cat(n_topo, (0,), np.int64)
    order = np.argsort(tk, kind="stable")
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    feat_of = cat(n_feat, (0,), np.uint64)
    pos = cat(n_pos, (0,), np.int64)
    # edges: along each feature, and from a feature's last node to each successor's first node
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    edges = []
    for i in range(len(xy)):
        fid = int(feat_of[i])
        first.setdefault(fid, i)
        last[fid] = i
        if pos[i] > 0:
            edges.append((i - 1, i))
    for f in feats:
        for s in f.successors:
            if int(f.id) in last and int(s) in first:
                edges.append((last[int(f.id)], first[int(s)]))
    n_plain = len(edges)
    for bid, kind, tid, k in attach:
        if bid in first and tid in first:
            node = first[tid] + k - lo[tid]
            edges.append((node, first[bid]) if kind == "split" else (last[bid], node))
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    e_left = np.arange(len(e)) >= n_plain
    counts = np.bincount(tk, minlength=len(t_uid)) if len(tk) else np.zeros(len(t_uid), dtype=np.int64)
    return SegmentGraph(
        key=key,
        pivot_id=key,
        topo_uid=t_uid.astype(np.uint64),
        topo_step=np.arange(len(t_uid), dtype=np.int64),
        topo_xy=t_xy.reshape(-1, 2),
        topo_heading=t_h,
        topo_width=t_w,
        topo_edges=np.asarray(t_edges, dtype=np.int64).reshape(-1, 2),
        topo_start=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        node_uid=cat(n_uid, (0,), np.uint64)[order],
        node_xy=xy[order],
        node_type=cat(n_type, (0,), np.int64)[order],
        node_count=cat(n_cnt, (0,), np.int64)[order],
        node_std=cat(n_std, (0,), float)[order],
        edges=inv[e] if len(e) else e,
        edge_leftover=e_left,
        drive_ids=tuple(hdmap.drive_ids),
        stats=ConnectionStats(),
        tile_size_m=tile_size_m,
    )
