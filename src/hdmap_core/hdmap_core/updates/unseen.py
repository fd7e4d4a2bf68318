"""The first map's markings no drive after a shift saw, moved by the shift the drives measured.

A construction zone moves a carriageway's markings alike (all lanes toward the shoulder or the
median); its road borders stay. The few drives after the change see their own and the next lanes,
not every line: a rebuilt place would lose the lines they did not see (the right edge line beside
the far lane), or keep them where they were (beyond their reach). Where the drives' evidence says
every line they saw moved alike, the lines they did not see are taken from the first map and moved
by the same displacement: a model of the change, not an observation, flagged as such (their points'
``drive_count`` is 0, their ``lateral_std`` holds the measured moves' spread) and counted in the
history (``ModelledMarking``).

1. **Candidate places**: the rebuilt places that belong to a change with a geometry kind and no
   lane closed or opened (those move one line, not the carriageway), a place's own kind being
   ``geometry`` (not re-striping or a gone / new marking) or it being a taper next to one; its
   displacement ``D`` is the median of the drives after the change there (``PlaceEvidence``).
2. **Seen lines**: each first-map marking point in such a place is looked for in the (aligned)
   local map at its place moved by ``D``; a local marking of its type there gives the point's
   measured move (one of the other type excludes the point).
   A first-map marking piece in the place with enough such points is a line seen moved, its move
   the median; with enough points found where it was and not where it would have moved to, a
   line seen staying.
3. **The place agrees** when it has at least ``min_lines`` lines seen moved, all within
   ``alike_m`` of their median, that median within ``alike_m`` of D and at least half the
   smallest shift, no line seen staying (with ``|D|`` large enough to tell), and the local map's
   markings there are (``unseen_explained``) first-map markings moved by D: a shift near a
   lane's width is measured as the rest (each line pairs with its neighbour) and leaves the edge
   lines over.
4. **Unseen points**: the first-map marking points of agreeing places that the local map has no
   marking for within ``seen_m`` of their moved place, on the moved carriageway (within
   ``view_m`` of a seen-moved point, with no first-map road border between them), move by the
   median of the measured moves of the seen points within ``radius_m`` (so the move follows
   the tapers along the road).

Nothing is invented where no line was: only the first map's own markings move.

``unseen_at_ends`` keeps the other unseen lines of a shift: at the tapers' ends, where the lines
the drives saw had not moved yet, the first map's lines they did not see stay where they were.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.evaluation.cuts import Segments, intersect_cuts, segments_of
from hdmap_core.geometry import dense_points, left_normal, point_headings, true_runs
from hdmap_core.model import FeatureType, HDMap, MapFeature
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange
from hdmap_core.updates.evidence import PlaceEvidence
from hdmap_core.updates.places import PlaceKey, Places, markings_in

__all__ = [
    "ModelledMarking",
    "UnseenMove",
    "unseen_at_ends",
    "unseen_moved",
    "is_shift",
    "measured_moved",
    "across_border",
    "with_modelled",
]

_BORDER = int(FeatureType.ROAD_BORDER)
_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))
_NOT_A_SHIFT = ("lane_closed", "lane_opened", "type")  # one line moved, or re-striping
_RESAMPLE_M = 0.5  # the local map's markings are looked up at this spacing [m]
_STD_FLOOR_M = 0.1  # least lateral uncertainty added to a moved point [m]
# unseen_at_ends: seen within _TAPER_KEEP_M; lines moved past _TAPER_SAME_M (the median over the
# _TAPER_NEAREST nearest local marking points within _TAPER_VIEW_M) [m]
_TAPER_KEEP_M = 1.75
_TAPER_SAME_M = 0.8
_TAPER_NEAREST = 8
_TAPER_VIEW_M = 12.0


@dataclass(frozen=True)
class ModelledMarking:
    """A piece of a first-map marking moved by the displacement of the change, unseen after it.

    Attributes:
        change_id: the change it belongs to.
        feature_id: the first-map feature it is part of.
        type: its FeatureType code.
        points: (N, 2) where the model puts it [m].
        from_points: (N, 2) where the first map had it [m].
        move_m: (N,) the move applied, + = left of the feature's direction [m].
    """

    change_id: int
    feature_id: int
    type: int
    points: np.ndarray
    from_points: np.ndarray
    move_m: np.ndarray


@dataclass(frozen=True)
class UnseenMove:
    """The first map with its unseen markings moved (``map``), and what moved (``pieces``)."""

    map: HDMap
    pieces: tuple[ModelledMarking, ...]

    @property
    def moved_to(self) -> np.ndarray:
        """(N, 2) every moved point's new place."""
        return np.concatenate([np.zeros((0, 2)), *(p.points for p in self.pieces)])

    @property
    def moved_from(self) -> np.ndarray:
        """(N, 2) every moved point's place in the first map."""
        return np.concatenate([np.zeros((0, 2)), *(p.from_points for p in self.pieces)])


def is_shift(change: DetectedChange) -> bool:
    """A change of geometry that closes, opens or re-stripes nothing: the carriageway moved."""
    return "geometry" in change.kinds and not any(k in change.kinds for k in _NOT_A_SHIFT)


def measured_moved(changes: Sequence[DetectedChange], config: ChangeConfig) -> frozenset[PlaceKey]:
    """The geometry places of ``changes`` where the drives after them measured the lines moved
    (their effect at least ``min_shift_m``)."""
    return frozenset(
        p.key for c in changes for p in c.places if p.kind == "geometry" and abs(p.effect) >= config.min_shift_m
    )


def across_border(p: np.ndarray, q: np.ndarray, borders: Segments) -> np.ndarray:
    """(N,) True where the segment from ``p`` to ``q`` (both (N, 2)) crosses one of ``borders``."""
    v = q - p
    length = np.linalg.norm(v, axis=1)
    u = v / np.maximum(length, 1e-9)[:, None]
    crossed, _, _, _ = intersect_cuts(p, u, np.zeros(len(p)), length, borders)
    out = np.zeros(len(p), dtype=bool)
    out[crossed] = True
    return out


def with_modelled(
    f: MapFeature,
    at: np.ndarray,
    new: np.ndarray,
    moves: np.ndarray,
    spread: np.ndarray,
    change_ids: Sequence[int],
    from_points: np.ndarray,
) -> tuple[MapFeature, list[ModelledMarking]]:
    """``f`` with its points ``at`` (sorted indices) moved to ``new`` by ``moves``: a model, not an
    observation (``drive_count`` 0, ``lateral_std`` grown by ``spread``, at least
    ``_STD_FLOOR_M``), and one ``ModelledMarking`` per run of consecutive moved points (the change
    of its first point; ``from_points``: where they were)."""
    pts = np.asarray(f.points, dtype=float).copy()
    pts[at] = new
    count = np.asarray(f.drive_count).copy()
    count[at] = 0
    std = np.asarray(f.lateral_std, dtype=float).copy()
    std[at] = np.hypot(std[at], np.maximum(np.nan_to_num(spread), _STD_FLOOR_M))
    pieces = [
        ModelledMarking(
            change_id=int(change_ids[r[0]]),
            feature_id=int(f.id),
            type=int(f.type),
            points=new[r].copy(),
            from_points=from_points[r].copy(),
            move_m=moves[r].copy(),
        )
        for r in np.split(np.arange(len(at)), np.flatnonzero(np.diff(at) != 1) + 1)
    ]
    return replace(f, points=pts, drive_count=count, lateral_std=std), pieces


def _explained(
    local_lines: Sequence[tuple[int, np.ndarray]],
    predicted: dict[int, list[np.ndarray]],
    places: Places,
    moves: dict[PlaceKey, tuple[int, float]],
    tol: float,
) -> dict[PlaceKey, float]:
    """Per candidate place: the share of the local map's marking points there with a first-map
    marking of their type moved by the place's D within ``tol``."""
    trees = {t: cKDTree(np.concatenate(v)) for t, v in predicted.items() if v}
    hit: dict[PlaceKey, int] = {}
    total: dict[PlaceKey, int] = {}
    for t, pts in local_lines:
        pts = dense_points([pts], _RESAMPLE_M)
        if len(pts) < 2:
            continue
        keys = places.keys_along(pts)
        inside = np.array([k in moves for k in keys], dtype=bool)
        if not inside.any():
            continue
        ok = np.zeros(len(pts), dtype=bool)
        if t in trees:
            d, _ = trees[t].query(pts[inside], distance_upper_bound=tol)
            ok[inside] = np.isfinite(d)
        for k, good in zip([k for k, i in zip(keys, inside) if i], ok[inside]):
            total[k] = total.get(k, 0) + 1
            hit[k] = hit.get(k, 0) + int(good)
    return {k: hit.get(k, 0) / n for k, n in total.items()}


def _place_moves(
    changes: Sequence[DetectedChange],
    evidence: Sequence[PlaceEvidence],
    places: Places,
    rebuilt: set[PlaceKey],
) -> dict[PlaceKey, tuple[int, float]]:
    """Per candidate place (step 1): (change id, displacement D, + = the markings moved right)."""
    out: dict[PlaceKey, tuple[int, float]] = {}
    for c in changes:
        if not is_shift(c):
            continue
        geo = {p.key for p in c.places if p.kind == "geometry"}
        other = {p.key for p in c.places if p.kind != "geometry"}
        tapers = {nb for k in geo for nb in places.neighbours(k)} & rebuilt
        after = set(c.drives_after)
        for key in (geo | tapers) - other:
            if key not in rebuilt or key in out:
                continue
            d = [e.displacement_m for e in evidence if e.key == key and e.drive_id in after]
            d = [v for v in d if np.isfinite(v)]
            if d:
                out[key] = (c.id, float(np.median(d)))
    return out


def unseen_moved(
    first: HDMap,
    local: HDMap,
    places: Places,
    changes: Sequence[DetectedChange],
    evidence: Sequence[PlaceEvidence],
    rebuilt: set[PlaceKey],
    *,
    config: ChangeConfig = ChangeConfig(),
) -> UnseenMove:
    """``first`` with the markings of shifted places that ``local`` (the aligned rebuild of the
    places ``rebuilt`` from the drives after the change) lacks moved by the shift (module
    docstring); ``first`` itself when nothing qualifies."""
    moves = _place_moves(changes, evidence, places, rebuilt)
    none = UnseenMove(first, ())
    local_lines = [(int(f.type), np.asarray(f.points, float)) for f in local.features if int(f.type) in _MARKINGS]
    local_marks = dense_points([p for _, p in local_lines], _RESAMPLE_M)
    if not moves or len(local_marks) == 0 or not config.model_unseen:
        return none
    tree = cKDTree(local_marks)
    by_type = {t: dense_points([p for u, p in local_lines if u == t], _RESAMPLE_M) for t in _MARKINGS}
    trees = {t: cKDTree(v) if len(v) else None for t, v in by_type.items()}
    tol = config.unseen_match_m
    # Step 2: per first-map marking point in a candidate place, its move as the local map shows it.
    rows = []  # (feature index, point indices, keys, normals, measured move or NaN, stayed)
    predicted: dict[int, list[np.ndarray]] = {}  # per type: the first map's markings moved by D
    for fi, f, pts, keys, inside in markings_in(first, places, moves):
        nrm = left_normal(point_headings(pts))
        idx = np.flatnonzero(inside)
        d = np.array([moves[keys[i]][1] for i in idx])
        p, n = pts[idx], nrm[idx]
        q = p - d[:, None] * n  # D > 0: the markings moved right of the drives
        move = np.full(len(idx), np.nan)
        same = trees[int(f.type)]
        found = np.zeros(len(idx), dtype=bool)
        if same is not None:
            dist, j = same.query(q, distance_upper_bound=tol)
            found = np.isfinite(dist)
            move[found] = ((by_type[int(f.type)][j[found]] - p[found]) * n[found]).sum(axis=1)
        # seen staying: a marking where it was and none where it would have moved to; seen
        # otherwise: a marking of the other type where it would have moved to (not modelled)
        dq, _ = tree.query(q, distance_upper_bound=tol)
        d0, _ = tree.query(p, distance_upper_bound=config.unseen_stay_m)
        stayed = ~np.isfinite(dq) & np.isfinite(d0) & (np.abs(d) >= 2 * tol)
        stayed = np.where(np.isfinite(dq) & ~found, -1, stayed.astype(int))  # -1: seen as the other type
        rows.append((fi, idx, [keys[i] for i in idx], n, move, stayed))
        predicted.setdefault(int(f.type), []).append(q)
    # Every local marking must be a first-map marking moved by D: with a shift near a lane's
    # width the lines pair with their neighbours (D is the rest), and the edge lines are left over.
    explained = _explained(local_lines, predicted, places, moves, 2 * tol)
    # Step 3: the lines seen per place, and whether they moved alike.
    lines: dict[PlaceKey, list[float]] = {}
    stays: set[PlaceKey] = set()
    for _, _, keys, _, move, stayed in rows:
        for key in set(keys):
            sel = np.array([k == key for k in keys])
            if np.count_nonzero(np.isfinite(move[sel])) >= config.unseen_line_points:
                lines.setdefault(key, []).append(float(np.nanmedian(move[sel])))
            elif int(np.count_nonzero(stayed[sel] == 1)) >= max(
                config.unseen_line_points, int(np.count_nonzero(sel)) // 2
            ):
                stays.add(key)
    agree = set()
    for key, ms in lines.items():
        m = np.asarray(ms)
        alike = np.all(np.abs(m - np.median(m)) <= config.unseen_alike_m)
        # and as the drives measured it (the displacement is + for a move to the right)
        as_measured = abs(float(np.median(m)) + moves[key][1]) <= config.unseen_alike_m
        accounted = explained.get(key, 0.0) >= config.unseen_explained
        # a place whose lines stayed (a taper's end) is no shifted carriageway
        moved = abs(float(np.median(m))) >= config.min_shift_m / 2
        if len(m) >= config.unseen_min_lines and key not in stays and alike and as_measured and accounted and moved:
            agree.add(key)
    if not agree:
        return none
    # Step 4: the unseen points of agreeing places, moved by the seen points' moves near them.
    seen_p = np.concatenate(
        [np.zeros((0, 2))]
        + [
            np.asarray(first.features[fi].points, float)[idx][np.isfinite(mv) & np.array([k in agree for k in keys])]
            for fi, idx, keys, _, mv, _ in rows
        ]
    )
    seen_m = np.concatenate(
        [np.zeros(0)] + [mv[np.isfinite(mv) & np.array([k in agree for k in keys])] for _, _, keys, _, mv, _ in rows]
    )
    if len(seen_p) == 0:
        return none
    seen_tree = cKDTree(seen_p)
    borders = [np.asarray(f.points, float) for f in first.features if int(f.type) == _BORDER and len(f.points) >= 2]
    bsegs = segments_of(borders) if borders else None
    feats = list(first.features)
    pieces: list[ModelledMarking] = []
    for fi, idx, keys, n, move, stayed in rows:
        f = first.features[fi]
        pts = np.asarray(f.points, dtype=float)
        cand = np.flatnonzero(np.array([k in agree for k in keys]) & ~np.isfinite(move) & (stayed == 0))
        if len(cand) == 0:
            continue
        p = pts[idx[cand]]
        # the move: the median of the seen points' moves within radius_m
        near = seen_tree.query_ball_point(p, config.unseen_radius_m)
        mv = np.array([float(np.median(seen_m[nb])) if nb else np.nan for nb in near])
        spread = np.array(
            [1.4826 * float(np.median(np.abs(seen_m[nb] - np.median(seen_m[nb])))) if nb else np.nan for nb in near]
        )
        ok = np.isfinite(mv)
        # on the moved carriageway: a seen-moved point within view_m, no first-map border between
        dn, jn = seen_tree.query(p, distance_upper_bound=config.view_m)
        ok &= np.isfinite(dn)
        if bsegs is not None and ok.any():
            k_ok = np.flatnonzero(ok)
            ok[k_ok[across_border(p[k_ok], seen_p[jn[k_ok]], bsegs)]] = False
        # not seen after all: no local marking near where it would be now
        new = p + np.where(ok, mv, 0.0)[:, None] * n[cand]
        if ok.any():
            dseen, _ = tree.query(new[ok], distance_upper_bound=config.unseen_seen_m)
            ok[np.flatnonzero(ok)[np.isfinite(dseen)]] = False
        if not ok.any():
            continue
        at = idx[cand[ok]]
        ids = [moves[keys[i]][0] for i in cand[ok]]
        feats[fi], made = with_modelled(f, at, new[ok], mv[ok], spread[ok], ids, pts[at])
        pieces += made
    if not pieces:
        return none
    return UnseenMove(replace(first, features=tuple(feats)), tuple(pieces))


def unseen_at_ends(
    first: HDMap,
    local: HDMap,
    places: Places,
    rebuilt: set[PlaceKey],
    moved_places: frozenset[PlaceKey] = frozenset(),
) -> np.ndarray:
    """(N, 2) the first map's marking points in the ``rebuilt`` places that the drives after
    the change did not see (no local marking within ``_TAPER_KEEP_M``), walking in from where a
    run of them leaves the rebuilt places, up to where the lines the drives saw leave the first
    map's (the median distance of the nearest local marking points to a first-map marking
    exceeds ``_TAPER_SAME_M``) or the first place of ``moved_places`` (where the drives after
    the change measured the lines moved). A shift zone's tapers move the lines from 0: near
    their outer end the lines no drive after it saw are still where the first map has them, and
    the rebuild would drop them; past that point they moved (a move near a lane's width comes
    near the neighbour's old place again: hence the first such point ends the walk). The first
    map is the consensus of every drive, those after the change too: once several of them
    passed, it holds the moved lines along the tapers as well, the lines they saw lie on its
    own there, and only ``moved_places`` ends the walk before it runs through the zone."""
    if not rebuilt:
        return np.zeros((0, 2))
    first_marks = [np.asarray(f.points, dtype=float) for f in first.features if int(f.type) in _MARKINGS]
    marks = dense_points([f.points for f in local.features if int(f.type) in _MARKINGS], _RESAMPLE_M)
    if len(marks) == 0 or not first_marks:
        return np.zeros((0, 2))
    tree = cKDTree(marks)
    d_first, _ = cKDTree(dense_points(first_marks, _RESAMPLE_M)).query(marks)  # each local marking point: moved how far
    out = [np.zeros((0, 2))]
    for _, _, pts, keys, inside in markings_in(first, places, rebuilt):
        d, _ = tree.query(pts, distance_upper_bound=_TAPER_KEEP_M)
        dn, jn = tree.query(pts, k=_TAPER_NEAREST, distance_upper_bound=_TAPER_VIEW_M)
        # the median over the nearest local marking points found (inf: none)
        near = np.sort(np.where(np.isfinite(dn), d_first[np.minimum(jn, len(marks) - 1)], np.inf), axis=1)
        n = np.count_nonzero(np.isfinite(dn), axis=1)
        rows = np.arange(len(pts))
        moved = np.where(n > 0, 0.5 * (near[rows, np.maximum(n - 1, 0) // 2] + near[rows, n // 2]), np.inf)
        for a, b in true_runs(inside):
            # walk in from each end where the feature leaves the rebuilt places
            ends = [(a - 1, range(a, b)), (b, range(b - 1, a - 1, -1))]
            for end, order in ends:
                if not 0 <= end < len(keys):
                    continue
                for i in order:
                    if moved[i] > _TAPER_SAME_M or keys[i] in moved_places:  # (inf: none near) too
                        break
                    if not np.isfinite(d[i]):
                        out.append(pts[i : i + 1])
    return np.concatenate(out)
