"""An exported map read back into a hierarchical graph, so that new segments can be stitched to it (Sec. VI)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.graph.segment_graph import ConnectionStats, SegmentGraph, stable_uid
from hdmap_core.model import FeatureType, HDMap, MapFeature

__all__ = ["graph_from_hdmap"]

_BORDER_CODE = int(FeatureType.ROAD_BORDER)


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
