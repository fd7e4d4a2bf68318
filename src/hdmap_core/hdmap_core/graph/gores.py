"""Gore splits and merges placed where the lane line ends (beyond the paper; Sec. VI export).

At a gore a lane line ends and two solid lines start from its end and diverge slowly; the
aggregation resolves them as two only once they are ~1 m apart, so the split comes tens of
metres late. These functions move it back (merges forward) on the exported features; they
return new lists and leave their inputs unchanged.
"""

from __future__ import annotations

from dataclasses import replace as _replace

import numpy as np

from hdmap_core.geometry import polyline_length
from hdmap_core.model import MapFeature, TopologyNode

__all__ = ["gore_branches", "gore_junctions"]


def gore_branches(
    features: list[MapFeature], topology: list[TopologyNode], branches: list[tuple[int, int, str]], *, max_m: float
) -> tuple[list[MapFeature], list[TopologyNode]]:
    """``gore_junctions`` for through lines: a branch of the through line's own type that starts
    on it at most ``max_m`` after the through line began at a type change (a gore: the lane line
    ends, two solid lines start and are resolved as two only tens of metres on) gets the common
    piece prepended and the lane line as its predecessor, so the split sits where the lane line
    ends. Merges mirror this.

    Args:
        branches: (through feature id, branch feature id, "split" | "merge").
    """
    byid = {f.id: f for f in features}
    changed = False
    for tid, bid, kind in sorted(branches):
        c, b = byid.get(tid), byid.get(bid)
        if c is None or b is None or b.type != c.type or len(c.points) < 2 or len(b.points) < 2:
            continue
        outer = c.predecessors if kind == "split" else c.successors
        if len(outer) != 1 or outer[0] not in byid or byid[outer[0]].type == c.type:
            continue
        if b.predecessors if kind == "split" else b.successors:
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
            if i == 0 or i + 1 >= len(cp) or polyline_length(cp[: i + 1]) > max_m:
                continue
            arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(cp[: i + 2], axis=0).T))]
            half = 0.5 * (np.asarray(b.points[1], dtype=float) - cp[i + 1])
            shift = ((arc[: i + 1] / max(arc[i + 1], 1e-9)) ** 2)[:, None] * half
            common, rest = slice(0, i + 1), np.asarray(b.points[1:], dtype=float)
            b = _replace(
                b,
                points=np.vstack([cp[common] + shift, rest]),
                drive_count=np.r_[c.drive_count[: i + 1], b.drive_count[1:]],
                lateral_std=np.r_[c.lateral_std[: i + 1], b.lateral_std[1:]],
                predecessors=(p.id,),
            )
            p = _replace(p, successors=tuple(sorted(set(p.successors) | {b.id})))
        else:
            if i == len(cp) - 1 or i == 0 or polyline_length(cp[i:]) > max_m:
                continue
            arc = np.r_[0.0, np.cumsum(np.hypot(*np.diff(cp[i - 1 :][::-1], axis=0).T))][::-1]  # to the end
            half = 0.5 * (np.asarray(b.points[-2], dtype=float) - cp[i - 1])
            shift = ((arc[1:] / max(arc[0], 1e-9)) ** 2)[:, None] * half
            common, rest = slice(i, len(cp)), np.asarray(b.points[:-1], dtype=float)
            b = _replace(
                b,
                points=np.vstack([rest, cp[common] + shift]),
                drive_count=np.r_[b.drive_count[:-1], c.drive_count[i:]],
                lateral_std=np.r_[b.lateral_std[:-1], c.lateral_std[i:]],
                successors=(p.id,),
            )
            p = _replace(p, predecessors=tuple(sorted(set(p.predecessors) | {b.id})))
        cp = cp.copy()
        cp[common] -= shift
        c = _replace(c, points=cp)
        byid[b.id], byid[p.id], byid[c.id] = b, p, c
        changed = True
    if not changed:
        return features, topology
    return [byid[f.id] for f in features], topology


def gore_junctions(
    features: list[MapFeature], topology: list[TopologyNode], *, max_m: float
) -> tuple[list[MapFeature], list[TopologyNode]]:
    """Move splits (merges) of gore lines back (forward) to where the lane line's type changes.

    At a gore a lane line (dashed) ends and two solid lines start from its end and diverge slowly;
    the aggregation resolves them as two only once they are ~1 m apart, so the connection yields
    dashed -> one solid -> split into two solids, the split tens of metres late. The common solid
    piece is both lines at once: when it is at most ``max_m`` long, starts at a type change and
    splits into two polylines of its own type, it is prepended to both branches, which become the
    lane line's two successors. Merges mirror this.
    """
    byid = {f.id: f for f in features}
    gone: dict[int, tuple[int, ...]] = {}  # removed common piece -> the branches that absorbed it
    for c in sorted(features, key=lambda f: f.id):
        if c.id in gone or polyline_length(c.points) > max_m:
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
            if mode == "split":
                byid[p.id] = _replace(p, successors=new_links)
            else:
                byid[p.id] = _replace(p, predecessors=new_links)
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
