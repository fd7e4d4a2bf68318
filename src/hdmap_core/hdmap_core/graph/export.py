"""The stitched map graph exported as polylines and topology nodes (Sec. VI).

``export_map`` cuts the feature graph of a :class:`~hdmap_core.graph.flat.FlatGraph` into
polylines (``segment_graph.feature_chains``, closing rules RULE 1-4 of Sec. V), applies the
clean-up rules (``cleanup.py``: spurs, bubbles, end stubs, inner borders; ``type_runs.py``: type
flicker; ``gores.py``: gore splits) and fills ``MapFeature`` / ``TopologyNode``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from hdmap_core.errors import HdmapError
from hdmap_core.graph.cleanup import end_stubs, inner_borders, spur_free
from hdmap_core.graph.flat import FlatGraph, dedupe_uids, subset_nodes
from hdmap_core.graph.gores import gore_branches, gore_junctions
from hdmap_core.graph.segment_graph import chain_links, feature_chains
from hdmap_core.graph.stitch_config import StitchConfig
from hdmap_core.graph.type_runs import edge_lines_solid, smooth_types
from hdmap_core.model import FeatureType, MapFeature, TopologyNode

__all__ = ["export_map", "export_with_plan", "export_planned", "ExportPlan"]

#: a refuted piece (``refuted_piece_min_m``) is one of at most this many drives at any of its points
_REFUTED_PIECE_MAX_DRIVES = 1

# Rules measured and adopted with this stage (docs/graph.md); no preset changes them, so they are
# constants, not settings
#: the edge-line rule types only markings of at most this many drives (or disputed ones): a marking
#: many drives saw as dashed keeps its type
_EDGE_LINE_MAX_DRIVES = 1

_UNKNOWN_CODE = int(FeatureType.UNKNOWN)


@dataclass(frozen=True)
class ExportPlan:
    """Every decision of one :func:`export_map` call, to export the same graph with its feature
    nodes moved (:func:`export_planned`: the live map after a fusion) without deciding again.

    Attributes:
        n_uid: (N,) the uids of the flat graph's feature nodes (the same graph, moved, has them).
        chains: per chain, (its nodes, its head, its tail), nodes as indices of that flat graph;
            a head (tail) is () (none), (u,) (node u's point) or (u, f) (the middle of u and f).
        runs: per feature, (its chains in driving direction, id, type, predecessors, successors).
        topology: the topology nodes (before the gore rules, which run again on the moved lines).
        branches: (through feature id, branch feature id, "split" | "merge") for ``gore_branches``.
        fill_spacing_m, gore_max_m: the config's.
    """

    n_uid: np.ndarray
    chains: tuple[tuple[np.ndarray, tuple[int, ...], tuple[int, ...]], ...]
    runs: tuple[tuple[tuple[int, ...], int, FeatureType, tuple[int, ...], tuple[int, ...]], ...]
    topology: tuple[TopologyNode, ...]
    branches: tuple[tuple[int, int, str], ...]
    fill_spacing_m: float
    gore_max_m: float


def export_map(
    flat: FlatGraph, *, config: StitchConfig, protect: np.ndarray | None = None
) -> tuple[tuple[MapFeature, ...], tuple[TopologyNode, ...]]:
    """The polylines and topology nodes of ``flat`` (module docstring). ``protect``: (N,) bool,
    feature nodes whose polylines are not dropped as isolated specks (the ends of fills refuted
    by the negative evidence: a short piece between two junction mouths is drive-supported)."""
    features, topology, _ = export_with_plan(flat, config=config, protect=protect)
    return features, topology


def export_planned(flat: FlatGraph, plan: ExportPlan) -> tuple[tuple[MapFeature, ...], tuple[TopologyNode, ...]]:
    """``flat`` exported with the decisions of ``plan`` (an export of the same graph before its
    feature nodes moved): every polyline of the same nodes, at their new positions (junction
    points and gap fills made again); the gore rules run again on them.

    Raises:
        HdmapError: ``flat`` does not have the plan's feature nodes.
    """
    if flat.n_nodes != len(plan.n_uid) or not np.array_equal(flat.n_uid, plan.n_uid):
        raise HdmapError("export_planned: the flat graph is not the one the plan was made of")
    geoms = {}
    for run, *_ in plan.runs:
        for k in run:
            geoms[k] = _chain_geometry(flat.n_xy, flat.n_count, flat.n_std, plan.chains[k], plan.fill_spacing_m)
    features = [
        _run_feature([geoms[k] for k in run], fid, ftype, pred, succ) for run, fid, ftype, pred, succ in plan.runs
    ]
    return _finish(features, list(plan.topology), list(plan.branches), plan.gore_max_m)


def export_with_plan(
    flat: FlatGraph, *, config: StitchConfig, protect: np.ndarray | None = None
) -> tuple[tuple[MapFeature, ...], tuple[TopologyNode, ...], ExportPlan]:
    """:func:`export_map` and the plan of its decisions (:func:`export_planned`)."""
    cfg = config
    uid = dedupe_uids(flat)
    n_uid = flat.n_uid
    orig = np.arange(flat.n_nodes)  # each node's index in the flat graph given (the plan's)
    protect = np.zeros(flat.n_nodes, dtype=bool) if protect is None else np.asarray(protect, dtype=bool)
    if (cfg.spur_max_m > 0 or cfg.bubble_max_m > 0) and flat.n_nodes:
        # RULE spur / bubble
        keep = spur_free(flat, uid, spur_max_m=cfg.spur_max_m, bubble_max_m=cfg.bubble_max_m)
        if not keep.all():
            flat, uid, protect, orig = subset_nodes(flat, keep), uid[keep], protect[keep], orig[keep]
    nn = flat.n_nodes
    e = flat.edges
    if cfg.edge_line_solid_m > 0 and nn:
        # RULE edge line
        types = edge_lines_solid(flat, within_m=cfg.edge_line_solid_m, max_drives=_EDGE_LINE_MAX_DRIVES)
        flat = dataclasses.replace(flat, n_type=types)
    if cfg.min_type_run_m > 0 and nn:
        # RULE flicker / minority / single drive (type_runs.smooth_types)
        types = smooth_types(
            flat,
            uid,
            min_run_m=cfg.min_type_run_m,
            sparse_run_m=cfg.sparse_type_run_m,
            sparse_count=cfg.sparse_drive_count,
            minority_only=cfg.sparse_minority_only,
            single_run_m=cfg.single_drive_run_m,
            end_run_m=cfg.single_drive_end_run_m,
            end_run_through=cfg.single_drive_end_through_leftover,
        )
        flat = dataclasses.replace(flat, n_type=types)
    unknown = flat.n_type == _UNKNOWN_CODE
    if unknown.any():
        # RULE unknown type: a line of unknown type that continues no typed line is dropped
        keep_n = ~unknown
        flat, uid, protect, orig = subset_nodes(flat, keep_n), uid[keep_n], protect[keep_n], orig[keep_n]
        nn, e = flat.n_nodes, flat.edges
    through = cfg.through_lines
    if cfg.end_stub_max_m > 0 and len(e):
        # RULE end stub
        drop = end_stubs(flat, uid, config=cfg, through=through)
        if drop.any():
            keep_n = ~drop
            flat, uid, protect, orig = subset_nodes(flat, keep_n), uid[keep_n], protect[keep_n], orig[keep_n]
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
    specs = []
    for c in chains:
        f, last = int(c[0]), int(c[-1])
        head: tuple[int, ...] = ()
        tail: tuple[int, ...] = ()
        if len(in_cross.get(f, ())) == 1:
            u = in_cross[f][0]
            if outdeg[u] >= 2:
                head = (u,)
            elif indeg[f] == 1:
                head = (u, f)
        if len(out_cross.get(last, ())) == 1 and outdeg[last] == 1:
            w = out_cross[last][0]
            tail = (w,) if indeg[w] >= 2 else (last, w)
        specs.append((c, head, tail))
    geoms = [_chain_geometry(flat.n_xy, flat.n_count, flat.n_std, sp, cfg.fill_spacing_m) for sp in specs]

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
        elif (
            isolated
            and length < cfg.refuted_piece_min_m
            and protect[chains[k]].any()
            and int(np.max(geoms[k][1])) <= _REFUTED_PIECE_MAX_DRIVES
        ):
            keep[k] = False  # one drive's speck left between refuted fills
    inner_m = cfg.inner_border_max_m
    ctype = [int(flat.n_type[c[0]]) for c in chains]
    if inner_m > 0:
        # RULE inner border
        inner, dup = inner_borders(
            flat,
            chains,
            succ=succ,
            pred=pred,
            on_through=on_through,
            reach_m=inner_m,
            max_drives=cfg.inner_border_max_drives,
        )
        as_line = cfg.inner_border_dashed_drives
        for k in np.flatnonzero(inner & keep).tolist():
            if not dup[k] and int(flat.n_count[chains[k]].max()) <= as_line:
                # one drive's lane line reported as a border: a line between lane lines is
                # dashed (98 % of such points in the shared ground-truth maps)
                ctype[k] = int(FeatureType.DASHED)
            else:
                keep[k] = False
    fid = np.array([int(uid[c[0]]) for c in chains], dtype=np.uint64)
    runs = (
        _continuation_runs(keep, succ, pred, ctype, fid)
        if cfg.merge_continuations
        else [[k] for k in np.flatnonzero(keep).tolist()]
    )
    head_of = np.arange(len(chains))
    for run in runs:
        head_of[run] = run[0]

    planned = []
    for run in runs:
        k0, k1 = run[0], run[-1]
        planned.append(
            (
                tuple(run),
                int(fid[k0]),
                _ftype(ctype[k0]),
                tuple(sorted({int(fid[head_of[p]]) for p in pred.get(k0, ()) if keep[p]})),
                tuple(sorted({int(fid[head_of[s]]) for s in succ.get(k1, ()) if keep[s]})),
            )
        )
    features = [_run_feature([geoms[k] for k in run], fid_k, ft, pr, sc) for run, fid_k, ft, pr, sc in planned]

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
    branch_of = [(int(fid[head_of[t]]), int(fid[head_of[b]]), kind) for t, b, kind in attached if keep[t] and keep[b]]
    used = {k for run in runs for k in run}
    plan = ExportPlan(
        n_uid=n_uid,
        chains=tuple(
            (orig[c], tuple(int(orig[i]) for i in hd), tuple(int(orig[i]) for i in tl))
            if k in used
            else (orig[:0], (), ())
            for k, (c, hd, tl) in enumerate(specs)
        ),
        runs=tuple(planned),
        topology=tuple(topology),
        branches=tuple(branch_of),
        fill_spacing_m=cfg.fill_spacing_m,
        gore_max_m=cfg.gore_max_m,
    )
    out_features, out_topology = _finish(features, topology, branch_of, cfg.gore_max_m)
    return out_features, out_topology, plan


def _finish(
    features: list[MapFeature], topology: list[TopologyNode], branch_of: list[tuple[int, int, str]], gore_max_m: float
) -> tuple[tuple[MapFeature, ...], tuple[TopologyNode, ...]]:
    """The gore rules, then features and topology nodes in id order."""
    if gore_max_m > 0:
        if branch_of:
            features, topology = gore_branches(features, topology, branch_of, max_m=gore_max_m)
        features, topology = gore_junctions(features, topology, max_m=gore_max_m)
    features.sort(key=lambda f: f.id)
    topology.sort(key=lambda t: t.id)
    return tuple(features), tuple(topology)


def _chain_geometry(
    n_xy: np.ndarray, n_count: np.ndarray, n_std: np.ndarray, spec, fill_spacing_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A chain's points, drive counts and uncertainties: its nodes, with its head and tail
    junction points (``spec``: nodes, head, tail as in ``ExportPlan.chains``) and gaps filled."""
    c, head, tail = spec
    xy, cnt, std = n_xy[c], n_count[c], n_std[c]
    if head:
        hp = n_xy[head[0]] if len(head) == 1 else 0.5 * (n_xy[head[0]] + n_xy[head[1]])
        xy, cnt, std = np.vstack([hp, xy]), np.r_[cnt[:1], cnt], np.r_[std[:1], std]
    if tail:
        tp = n_xy[tail[0]] if len(tail) == 1 else 0.5 * (n_xy[tail[0]] + n_xy[tail[1]])
        xy, cnt, std = np.vstack([xy, tp]), np.r_[cnt, cnt[-1:]], np.r_[std, std[-1:]]
    if fill_spacing_m > 0 and len(xy) > 2:
        xy, cnt, std = _fill_gaps(xy, cnt, std, fill_spacing_m)
    return xy, cnt, std


def _run_feature(
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    fid: int,
    ftype: FeatureType,
    predecessors: tuple[int, ...],
    successors: tuple[int, ...],
) -> MapFeature:
    """One polyline of a run of chains (``parts``: their geometry in driving direction)."""
    xy = parts[0][0]
    cnt, std = parts[0][1], parts[0][2]
    for pxy, pcnt, pstd in parts[1:]:
        # 1: the next part starts where this one ends (the shared point is kept once)
        same = int(len(xy) > 0 and len(pxy) > 0 and float(np.hypot(*(xy[-1] - pxy[0]))) < 1e-6)
        xy, cnt, std = np.vstack([xy, pxy[same:]]), np.r_[cnt, pcnt[same:]], np.r_[std, pstd[same:]]
    return MapFeature(
        id=fid,
        type=ftype,
        points=np.ascontiguousarray(xy, dtype=float),
        drive_count=np.asarray(cnt, dtype=np.int64),
        lateral_std=np.asarray(std, dtype=float),
        predecessors=predecessors,
        successors=successors,
    )


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
