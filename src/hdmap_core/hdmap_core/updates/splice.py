"""A changed place rebuilt on its own and spliced into the first map, the rest of it untouched.

Following a change costs a build of the places it touches, not of the whole map:

1. The *region* is the changed places grown by a margin of places (``grow``): the drives are
   clipped to it (their pieces there) and mapped alone; the margin gives the pipeline its context
   and is thrown away.
2. The local map is *aligned* onto the first map by what did not change (``border_shift``): per
   changed place, the offset of the first map's road borders against the local map's, seen along
   the drives after the change (``updates.evidence.drive_evidence`` with the local map as the
   drive's detections). A map of a few drives keeps their common localisation error, and its
   offset adjustment has no tie to the first map's: both would show as error in the zone.
3. ``splice``: the first map's features lose their points in the changed places (a feature that
   crosses them is split into pieces; the first keeps the id), the local map's features give their
   points there (new ids), and the pieces are linked across each seam (same type, end within
   ``_SEAM_M``). A link between features stays where both its ends are kept: it goes to the
   pieces holding them (a lane split next to the changed places keeps its connection); a link to
   an end the changed places took is dropped. The topology graph the same way: the first map's
   nodes outside, the local map's inside, a successor lost at a seam replaced by the nearest node
   ahead on the other side.

A place belongs to a point by its position and the direction of its feature (``Places.keys``): a
feature runs in the driving direction, so the other carriageway in the same cell stays as it was.

Only what the drives after the change could see is replaced (``Reach``): a point of a changed place
farther than the sensors' reach from every pose the local map was built from (a ramp's far border
beside a carriageway the drives after the change kept to) has no evidence of the change, for or
against, and the first map keeps it there, on both sides of the splice alike (features and topology).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial import cKDTree

from hdmap_core.geometry import left_normal, point_headings, true_runs
from hdmap_core.model import Drive, FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.evidence import drive_evidence, map_lines, side_of_lines
from hdmap_core.updates.places import PlaceKey, Places

__all__ = ["Reach", "grow", "border_shift", "shifted", "splice"]

_SEAM_M = 4.0  # pieces on both sides of a seam whose ends are this close are linked [m]
_SEAM_COS = 0.7  # ... and run the same way (cos of the angle between them)
_TOPO_SEAM_M = 12.0  # a topology node's successor across a seam is sought this far ahead [m]
_SMOOTH_M = 100.0  # the alignment shift is smoothed along each feature over this [m]
_BORDER = int(FeatureType.ROAD_BORDER)
_SIDE_M = 1.0  # markings farther than this to each side of a first map's border: it is inside the road [m]


def grow(places: Places, keys: Iterable[PlaceKey], steps: int) -> set[PlaceKey]:
    """``keys`` and the places up to ``steps`` neighbours away (same driving direction)."""
    out = set(keys)
    frontier = set(out)
    for _ in range(max(0, steps)):
        nxt = {nb for k in frontier for nb in places.neighbours(k)} - out
        out |= nxt
        frontier = nxt
    return out


def _tangent_yaw(pts: np.ndarray) -> np.ndarray:
    return point_headings(pts) if len(pts) >= 2 else np.zeros(len(pts))


@dataclass(frozen=True)
class Reach:
    """What the drives after a change give evidence of: within ``reach_m`` of one of their poses;
    for the road borders, which a change leaves in place (``border_shift`` aligns on them), also
    only where the local map has a border within ``border_m``.

    Attributes:
        poses: (N, 2) the poses the rebuilt places were mapped from [m].
        reach_m: the sensors' lateral reach (``ChangeConfig.view_m``) [m].
        borders: (M, 2) the local map's road border points [m].
        border_m: a first map's border point with no local border point this close stays, unless
            ``markings`` (the local map's marking points) lie on both sides of it within
            ``reach_m`` (it crosses the road: not a border); 0: off [m].
        keep: (K, 2) first-map points that stay wherever they are (the first map's unseen
            markings moved by the change, ``updates.unseen``: in their new place).
        take: (T, 2) first-map points replaced wherever they are (those markings' old places).
    """

    poses: np.ndarray
    reach_m: float
    borders: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    border_m: float = 0.0
    markings: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    keep: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    take: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(np.asarray(self.poses, dtype=float).reshape(-1, 2))

    @cached_property
    def border_tree(self) -> cKDTree:
        return cKDTree(np.asarray(self.borders, dtype=float).reshape(-1, 2))

    def mask(self, pts: np.ndarray) -> np.ndarray:
        """(N,) True for the points ``pts`` (N, 2) within reach of a pose."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        if len(pts) == 0 or len(self.tree.data) == 0:
            return np.zeros(len(pts), dtype=bool)
        d, _ = self.tree.query(pts, distance_upper_bound=self.reach_m)
        return np.isfinite(d)

    @cached_property
    def marking_tree(self) -> cKDTree:
        return cKDTree(np.asarray(self.markings, dtype=float).reshape(-1, 2))

    def replaced(self, pts: np.ndarray, yaw: np.ndarray, ftype: int) -> np.ndarray:
        """(N,) True for the points ``pts`` (N, 2), heading ``yaw`` (N,), of a first map's feature
        of type ``ftype`` that the local map replaces (of those in a changed place)."""
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        out = self.mask(pts)
        if len(self.take) and len(pts):
            out |= _at(pts, self.take)
        if len(self.keep) and len(pts):
            out &= ~_at(pts, self.keep)
        if self.border_m <= 0 or int(ftype) != _BORDER or not out.any():
            return out
        idx = np.flatnonzero(out)
        if len(self.border_tree.data):
            d, _ = self.border_tree.query(pts[idx], distance_upper_bound=self.border_m)
            stays = ~np.isfinite(d)
        else:
            stays = np.ones(len(idx), dtype=bool)
        # ... unless the local map's markings lie on both sides of it: inside the road, no border
        if len(self.marking_tree.data) and stays.any():
            marks = self.marking_tree.data
            for i in np.flatnonzero(stays):
                near = self.marking_tree.query_ball_point(pts[idx[i]], self.reach_m)
                if near:
                    v = marks[near] - pts[idx[i]]
                    side = np.cos(yaw[idx[i]]) * v[:, 1] - np.sin(yaw[idx[i]]) * v[:, 0]
                    stays[i] = not (side.max() > _SIDE_M and side.min() < -_SIDE_M)
        out[idx[stays]] = False
        return out


def _at(pts: np.ndarray, where: np.ndarray) -> np.ndarray:
    """(N,) True for the points ``pts`` that are one of ``where`` (to 1 micrometre)."""
    d, _ = cKDTree(np.asarray(where, dtype=float).reshape(-1, 2)).query(pts, distance_upper_bound=1e-6)
    return np.isfinite(d)


def _in_keys(
    pts: np.ndarray, yaw: np.ndarray, places: Places, keys: set[PlaceKey], reach: Reach | None, ftype: int | None
) -> np.ndarray:
    inside = np.array([k in keys for k in places.keys(pts, yaw)], dtype=bool)
    if reach is not None and inside.any():
        inside[inside] = reach.mask(pts[inside]) if ftype is None else reach.replaced(pts[inside], yaw[inside], ftype)
    return inside


def _inside(
    pts: np.ndarray, places: Places, keys: set[PlaceKey], reach: Reach | None = None, ftype: int | None = None
) -> np.ndarray:
    return _in_keys(pts, _tangent_yaw(pts), places, keys, reach, ftype)


def border_shift(
    local: HDMap,
    first: HDMap,
    drives: Sequence[Drive],
    places: Places,
    keys: set[PlaceKey],
    *,
    config: ChangeConfig = ChangeConfig(),
) -> dict[PlaceKey, float]:
    """Per place of ``keys``: how far (left of the driving direction, m) ``local`` must move to
    lie on ``first``'s road borders; the median over ``drives``' paths (module docstring)."""
    lines, seen = map_lines(first), map_lines(local)
    per: dict[PlaceKey, list[float]] = {}
    for d in drives:
        if len(d.xy) < 2:
            continue
        for e in drive_evidence(d, lines, places, config=config, side=side_of_lines(d, seen, config)):
            if e.key in keys and e.anchored_on_borders and np.isfinite(e.anchor_m):
                per.setdefault(e.key, []).append(e.anchor_m)
    return {k: float(np.median(v)) for k, v in per.items()}


def shifted(hdmap: HDMap, shifts: dict[PlaceKey, float], places: Places) -> HDMap:
    """``hdmap`` with each feature and topology node moved left by the shift of its place
    (places without one take the nearest along the feature; smoothed over ``_SMOOTH_M``)."""
    if not shifts:
        return hdmap
    feats = []
    for f in hdmap.features:
        pts = np.asarray(f.points, dtype=float)
        if len(pts) < 2:
            feats.append(f)
            continue
        yaw = _tangent_yaw(pts)
        a = np.array([shifts.get(k, np.nan) for k in places.keys(pts, yaw)])
        ok = np.isfinite(a)
        if not ok.any():
            feats.append(f)
            continue
        idx = np.arange(len(a))
        a = np.interp(idx, idx[ok], a[ok])
        step = max(float(np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()), 1e-3)
        a = uniform_filter1d(a, size=max(1, int(round(_SMOOTH_M / step))) | 1, mode="nearest")
        left = left_normal(yaw)
        feats.append(replace(f, points=pts + a[:, None] * left))
    nodes = []
    for n in hdmap.topology:
        pos = np.asarray(n.position, dtype=float)
        s = shifts.get(places.keys(pos[None, :], np.array([n.heading]))[0])
        if s is None:
            nodes.append(n)
            continue
        nodes.append(replace(n, position=pos + s * left_normal(n.heading)))
    return replace(hdmap, features=tuple(feats), topology=tuple(nodes))


def _pieces(f: MapFeature, keep: np.ndarray) -> list[tuple[int, int]]:
    return [(a, b) for a, b in true_runs(keep) if b - a >= 2]


def splice(first: HDMap, local: HDMap, places: Places, keys: set[PlaceKey], *, reach: Reach | None = None) -> HDMap:
    """``first`` with its features and topology in the places ``keys`` taken from ``local``
    (module docstring). ``first``'s features that do not enter those places keep everything.
    With ``reach``, only the points of those places within it are taken from ``local``; the
    first map keeps the rest (no drive after the change could see there)."""
    next_id = 1 + max([int(f.id) for f in (*first.features, *local.features)] + [0])
    # (new feature, source ("first" / "local"), cut at start, cut at end)
    out: list[list] = []
    first_pieces: dict[int, list[int]] = {}
    local_pieces: dict[int, list[int]] = {}
    for src, source in (("first", first.features), ("local", local.features)):
        for f in source:
            pts = np.asarray(f.points, dtype=float)
            if len(pts) < 2:
                if src == "first":
                    out.append([f, src, False, False])
                continue
            inside = _inside(pts, places, keys, reach, int(f.type) if src == "first" else None)
            keep = ~inside if src == "first" else inside
            if keep.all():
                if src == "first":
                    out.append([f, src, False, False])
                    first_pieces.setdefault(int(f.id), []).append(len(out) - 1)
                    continue
            spans = _pieces(f, keep)
            for j, (a, b) in enumerate(spans):
                fid = int(f.id) if (src == "first" and j == 0) else next_id
                if fid == next_id:
                    next_id += 1
                piece = MapFeature(
                    id=fid,
                    type=f.type,
                    points=pts[a:b].copy(),
                    drive_count=np.asarray(f.drive_count)[a:b].copy(),
                    lateral_std=np.asarray(f.lateral_std)[a:b].copy(),
                    predecessors=tuple(f.predecessors) if a == 0 else (),
                    successors=tuple(f.successors) if b == len(pts) else (),
                )
                out.append([piece, src, a > 0, b < len(pts)])
                (first_pieces if src == "first" else local_pieces).setdefault(int(f.id), []).append(len(out) - 1)
    # Links: within a source, a link follows the end it names: a successor link goes to the piece
    # that kept the successor's first point, a predecessor link to the piece that kept the
    # predecessor's last point; a link to an end the changed places took is dropped (not moved
    # to a piece elsewhere). Seams are linked across below.
    feats: list[MapFeature] = [row[0] for row in out]
    pieces_of = {"first": first_pieces, "local": local_pieces}

    def relink(ids: tuple[int, ...], src: str, end: str) -> tuple[int, ...]:
        got = []
        for i in ids:
            rows = pieces_of[src].get(int(i), [])
            # out rows: [feature, source, cut at start, cut at end]
            holder = next((r for r in rows if not out[r][2 if end == "start" else 3]), None)
            if holder is not None:
                got.append(int(feats[holder].id))
        return tuple(dict.fromkeys(got))

    for row in out:
        f, src = row[0], row[1]
        if len(f.points) < 2:
            continue
        preds = relink(f.predecessors, src, "end")
        succs = relink(f.successors, src, "start")
        if preds != tuple(f.predecessors) or succs != tuple(f.successors):
            row[0] = replace(f, predecessors=preds, successors=succs)
    feats = [row[0] for row in out]
    ok = [i for i, f in enumerate(feats) if len(f.points) >= 2]
    if ok:
        starts = np.array([feats[i].points[0] for i in ok])
        tree = cKDTree(starts)
        succ: dict[int, list[int]] = {}
        pred: dict[int, list[int]] = {}
        for i in ok:
            f, src, _, cut_end = out[i][0], out[i][1], out[i][2], out[i][3]
            ends_at_seam = cut_end if src == "first" else True
            if not ends_at_seam or f.successors:
                continue
            dir_f = f.points[-1] - f.points[-2]
            for j in tree.query_ball_point(f.points[-1], _SEAM_M):
                g_i = ok[j]
                g = feats[g_i]
                if out[g_i][1] == src or g.type != f.type:
                    continue
                dir_g = g.points[1] - g.points[0]
                cos = float(dir_f @ dir_g) / max(float(np.linalg.norm(dir_f) * np.linalg.norm(dir_g)), 1e-9)
                if cos >= _SEAM_COS:
                    succ.setdefault(int(f.id), []).append(int(g.id))
                    pred.setdefault(int(g.id), []).append(int(f.id))
        feats = [
            replace(
                f,
                successors=tuple(dict.fromkeys([*f.successors, *succ.get(int(f.id), [])])),
                predecessors=tuple(dict.fromkeys([*f.predecessors, *pred.get(int(f.id), [])])),
            )
            if int(f.id) in succ or int(f.id) in pred
            else f
            for f in feats
        ]
    topology = _splice_topology(first, local, places, keys, feats, pieces_of, reach)
    return replace(
        first, features=tuple(feats), topology=topology, drive_ids=tuple(sorted({*first.drive_ids, *local.drive_ids}))
    )


def _splice_topology(
    first: HDMap,
    local: HDMap,
    places: Places,
    keys: set[PlaceKey],
    feats: list[MapFeature],
    pieces_of: dict[str, dict[int, list[int]]],
    reach: Reach | None = None,
) -> tuple[TopologyNode, ...]:
    def inside(nodes: Sequence[TopologyNode]) -> np.ndarray:
        if not nodes:
            return np.zeros(0, dtype=bool)
        pos = np.array([np.asarray(n.position, dtype=float) for n in nodes])
        head = np.array([float(n.heading) for n in nodes])
        return _in_keys(pos, head, places, keys, reach, None)

    next_id = 1 + max([int(n.id) for n in (*first.topology, *local.topology)] + [0])
    kept: list[tuple[TopologyNode, str]] = [
        (n, "first") for n, i in zip(first.topology, inside(first.topology)) if not i
    ]
    renum: dict[int, int] = {}
    for n, i in zip(local.topology, inside(local.topology)):
        if i:
            renum[int(n.id)] = next_id
            next_id += 1
            kept.append((n, "local"))
    alive = {int(n.id) if src == "first" else renum[int(n.id)] for n, src in kept}

    # a node's feature cut into pieces: the piece nearest to it, each piece's distances to the
    # nodes that ask for it queried at once
    asks: dict[int, dict[int, None]] = {}
    for i, (n, src) in enumerate(kept):
        for fid in n.features:
            rows = pieces_of[src].get(int(fid), [])
            if len(rows) > 1:
                for r in rows:
                    asks.setdefault(r, {})[i] = None
    dist: dict[tuple[int, int], float] = {}
    for r, at in asks.items():
        idx = list(at)
        d, _ = cKDTree(feats[r].points).query(np.array([np.asarray(kept[i][0].position, dtype=float) for i in idx]))
        dist.update(zip(((i, r) for i in idx), d.tolist()))

    def feature_ids(i: int, n: TopologyNode, src: str) -> tuple[int, ...]:
        got = []
        for fid in n.features:
            rows = pieces_of[src].get(int(fid), [])
            if len(rows) == 1:
                got.append(int(feats[rows[0]].id))
            elif rows:
                got.append(int(feats[min(rows, key=lambda r: dist[(i, r)])].id))
        return tuple(dict.fromkeys(got))

    nodes: list[TopologyNode] = []
    for i, (n, src) in enumerate(kept):
        nid = int(n.id) if src == "first" else renum[int(n.id)]
        succ = [int(s) if src == "first" else renum.get(int(s), -1) for s in n.successors]
        succ_t, feat_t = tuple(s for s in succ if s in alive), feature_ids(i, n, src)
        same = src == "first" and succ_t == tuple(n.successors) and feat_t == tuple(n.features)
        nodes.append(n if same else replace(n, id=nid, successors=succ_t, features=feat_t))
    # Successors lost at a seam: the nearest node of the other side ahead, running the same way.
    src_of = [src for _, src in kept]
    if nodes:
        pos = np.array([np.asarray(n.position, dtype=float) for n in nodes])
        tree = cKDTree(pos)
        for i, ((orig, src), n) in enumerate(zip(kept, nodes)):
            lost = len(orig.successors) > len(n.successors) or (src == "local" and not orig.successors)
            if not lost or (
                src == "local" and all(renum.get(int(s), -1) in alive for s in orig.successors) and orig.successors
            ):
                continue
            h = np.array([np.cos(n.heading), np.sin(n.heading)])
            best, best_d = -1, np.inf
            for j in tree.query_ball_point(pos[i], _TOPO_SEAM_M):
                if src_of[j] == src:
                    continue
                ahead = float((pos[j] - pos[i]) @ h)
                if ahead <= 0 or np.cos(nodes[j].heading - n.heading) < _SEAM_COS:
                    continue
                d = float(np.linalg.norm(pos[j] - pos[i]))
                if d < best_d:
                    best, best_d = j, d
            if best >= 0:
                nodes[i] = replace(n, successors=tuple(dict.fromkeys([*n.successors, nodes[best].id])))
    return tuple(nodes)
