"""The markings no drive after a shift saw along its tapers, moved as the lines they saw there.

A construction zone's tapers move the lines gradually, from 0 to the shift over some 100 m. Of the
lines no drive after the change saw, ``updates.unseen`` moves those of the places where every
seen line moved alike by the shift (``unseen_moved``); a taper's place is no such place (most of
its lines moved less, or no drive after the change passed through it). ``unseen_at_ends`` kept
the first map's lines from the rebuilt places' outer ends up to where the seen lines had moved
0.8 m; beyond, along the taper, the rebuilt places held nothing of them: on ``motorway_ramps``
seed 1 (1.5 m shift, 3 drives after, all in the left lane) the three right lines were missing
over 55 m of the first taper and a divider over 100 m of the last.

Here each such point moves as the lines the drives saw beside it moved (``taper_moved``, before
``unseen_at_ends``, which keeps what is left at the ends where it was):

1. **The move field** (``_field``): every local marking point (the aligned rebuild, every
   ``_STEP_M``) paired with the first map's marking of its type it moved from: the lines it lies
   beside (a first-map point of the type whose foot is within half a step) by a move in the
   shift's direction (the change's displacement ``D``, the median of its geometry places'; up to
   half the smallest shift the other way, the scatter about a line that stayed) and no farther
   than ``|D|`` + ``unseen_match_m``; paired with more than one line (their moves more than
   ``_ONE_LINE_M`` apart), it gives nothing. The direction tells a line's own old place from its
   neighbour's: a 3 m shift on 3.5 m lanes brings each moved line within 1 m of its right
   neighbour's old place past the taper's middle (paired with the nearest line instead, the 3 m
   shift's zone precision after 10 drives through fell from 99.5 to 94.6 %, seed 0).
2. **Unseen points**: the first map's marking points in the rebuilt places with no paired point
   within ``_SEEN_M`` (no drive after the change saw their line there), not moved by
   ``unseen_moved`` already, not in a place where the drives after the change measured the
   lines moved (a geometry place of the change, its effect at least ``min_shift_m``), and not
   on a piece shorter than a place (``cell_m``) that begins and ends in the rebuilt places. Once
   several drives after the change passed, the first map (the consensus of every drive) holds
   blends of both roads in the zone, half-moved lines and such pieces (8-50 m on the 3 m shift,
   seed 1, 10 drives through); moved by the field they were lines of neither road (zone
   precision 98.1 -> 94.7 %, ghost share 0 -> 1.3 %).
3. **Their move**: the median of the field's ``_NEAREST`` nearest points within ``view_m`` on the
   point's carriageway (no first-map road border between), at least half of them found, within
   the same bounds as the pairing. A point with a local marking within ``unseen_seen_m`` of its
   new place was seen after all and is left to the rebuild.

The moved points are modelled, as ``unseen_moved``'s (``ModelledMarking``: ``drive_count`` 0,
``lateral_std`` grown by the field's spread). Nothing is invented where no line was: only the
first map's own markings move.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.evaluation.cuts import segments_of
from hdmap_core.geometry import left_normal, point_headings, polyline_length, resample_evenly
from hdmap_core.model import FeatureType, HDMap
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange
from hdmap_core.updates.places import PlaceKey, Places, markings_in
from hdmap_core.updates.unseen import UnseenMove, across_border, is_shift, measured_moved, with_modelled

__all__ = ["taper_moved"]

_BORDER = int(FeatureType.ROAD_BORDER)
_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))
_STEP_M = 0.5  # the local map's markings are looked at this spacing [m]
_CANDIDATES = 24  # first-map points a local marking point may pair with ...
_ONE_LINE_M = 0.5  # ... all of one line: their moves this close [m]
_SEEN_M = 1.0  # a first-map point with a paired one this close was seen [m]
_NEAREST = 16  # field points a move is the median of ...


def _shifts(changes: Sequence[DetectedChange], places: Places) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Of the shift changes (geometry, no lane or type change), per geometry place its cell
    centre (P, 2), its change's displacement D (P,: the median effect of the change's geometry
    places) and the change's id (P,)."""
    centres, ds, ids = [], [], []
    for c in changes:
        if not is_shift(c):
            continue
        geo = [p for p in c.places if p.kind == "geometry"]
        if not geo:
            continue
        d = float(np.median([p.effect for p in geo]))
        for p in geo:
            centres.append((np.array(p.key[:2], dtype=float) + 0.5) * places.cell_m)
            ds.append(d)
            ids.append(c.id)
    return np.array(centres).reshape(-1, 2), np.array(ds), np.array(ids, dtype=np.int64)


def _field(
    first: HDMap, local: HDMap, expect: Callable[[np.ndarray], np.ndarray], config: ChangeConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1: the local marking points (K, 2), their displacement vectors (K, 2) from the
    first map's marking of their type they moved from (NaN where none or more than one line),
    and the first-map points so paired (the lines seen).

    ``expect(points)``: the change's move there (along the left normal, the first map's lines'
    direction). A local point pairs with the first-map points of its type that it lies beside
    (their foot within half a step) by a move in the change's direction (up to half the smallest
    shift the other way) and no farther than it plus ``unseen_match_m``."""
    pts, vec, seen = [np.zeros((0, 2))], [np.zeros((0, 2))], [np.zeros((0, 2))]
    for t in _MARKINGS:
        ref_p, ref_n = [np.zeros((0, 2))], [np.zeros((0, 2))]
        for f in first.features:
            if int(f.type) == t and len(f.points) >= 2:
                p = resample_evenly(np.asarray(f.points, dtype=float), _STEP_M)
                ref_p.append(p)
                ref_n.append(left_normal(point_headings(p)))
        mine = [
            resample_evenly(np.asarray(f.points, dtype=float), _STEP_M)
            for f in local.features
            if int(f.type) == t and len(f.points) >= 2
        ]
        if not mine or len(ref_p) == 1:
            continue
        q = np.concatenate(mine)
        rp, rn = np.concatenate(ref_p), np.concatenate(ref_n)
        e = expect(q)
        reach = float(np.max(np.abs(e))) + config.unseen_match_m + _STEP_M
        d, j = cKDTree(rp).query(q, k=_CANDIDATES, distance_upper_bound=reach)
        found = np.isfinite(d)
        jj = np.minimum(j, len(rp) - 1)
        w = q[:, None, :] - rp[jj]
        lat = (w * rn[jj]).sum(axis=2)
        lon = w[..., 0] * rn[jj][..., 1] - w[..., 1] * rn[jj][..., 0]
        along = lat * np.sign(e)[:, None]
        ok = found & (np.abs(lon) <= _STEP_M / 2 + 1e-9)
        ok &= (along >= -config.min_shift_m / 2) & (along <= np.abs(e)[:, None] + config.unseen_match_m)
        lo = np.where(ok, lat, np.inf).min(axis=1)
        hi = np.where(ok, lat, -np.inf).max(axis=1)
        one = ok.any(axis=1) & (hi - lo <= _ONE_LINE_M)  # beside one line only
        s_med = np.full(len(q), np.nan)
        if one.any():
            s_med[one] = np.nanmedian(np.where(ok[one], lat[one], np.nan), axis=1)
        at = jj[np.arange(len(q)), np.argmax(ok, axis=1)]
        v = np.where(one[:, None], s_med[:, None] * rn[at], np.nan)
        pts.append(q)
        vec.append(v)
        seen.append(rp[at[one]])
    return np.concatenate(pts), np.concatenate(vec), np.concatenate(seen)


def taper_moved(
    first: HDMap,
    moved: UnseenMove,
    local: HDMap,
    places: Places,
    changes: Sequence[DetectedChange],
    rebuilt: set[PlaceKey],
    *,
    config: ChangeConfig = ChangeConfig(),
) -> UnseenMove:
    """``moved`` (``unseen_moved`` of ``first``) with the unseen marking points of the shifts'
    tapers in the ``rebuilt`` places moved as the lines seen beside them (module docstring);
    ``moved`` itself when nothing qualifies."""
    centres, ds, ids = _shifts(changes, places)
    if not len(ds) or not config.model_unseen:
        return moved
    local_marks = [
        np.asarray(f.points, dtype=float) for f in local.features if int(f.type) in _MARKINGS and len(f.points) >= 2
    ]
    if not local_marks:
        return moved
    marks_tree = cKDTree(np.concatenate([resample_evenly(p, _STEP_M) for p in local_marks]))
    centre_tree = cKDTree(centres)

    def expect(points: np.ndarray) -> np.ndarray:  # the change's move along the left normal
        return -ds[centre_tree.query(points)[1]]

    field_p, field_v, paired = _field(first, local, expect, config)
    good = np.isfinite(field_v[:, 0])
    if not good.any():
        return moved
    field_p, field_v = field_p[good], field_v[good]
    seen_tree = cKDTree(paired) if len(paired) else None
    field_tree = cKDTree(field_p)
    done = moved.moved_from
    done_tree = cKDTree(done) if len(done) else None
    borders = [np.asarray(f.points, float) for f in first.features if int(f.type) == _BORDER and len(f.points) >= 2]
    bsegs = segments_of(borders) if borders else None
    feats = list(moved.map.features)
    pieces = list(moved.pieces)
    n_before = len(pieces)
    # not in the places where the drives measured the lines moved (``unseen_moved``'s, where a
    # consensus that took part of the new road leaves blends no move can explain)
    for fi, _, pts, keys, inside in markings_in(first, places, set(rebuilt) - measured_moved(changes, config)):
        # step 2: a line of the road as it was (a piece shorter than a place that begins and
        # ends in the rebuilt places is what the consensus made of both roads), unseen, not
        # moved already
        if polyline_length(pts) < places.cell_m and all(k in rebuilt for k in keys):
            continue
        cand = inside.copy()
        if seen_tree is not None:
            d_seen, _ = seen_tree.query(pts, distance_upper_bound=_SEEN_M)
            cand &= ~np.isfinite(d_seen)
        if done_tree is not None and cand.any():
            d_done, _ = done_tree.query(pts, distance_upper_bound=1e-6)
            cand &= ~np.isfinite(d_done)
        idx = np.flatnonzero(cand)
        if len(idx) == 0:
            continue
        p = pts[idx]
        n = left_normal(point_headings(pts))[idx]
        # step 3: the field's nearest points on the same carriageway
        dn, jn = field_tree.query(p, k=_NEAREST, distance_upper_bound=config.view_m)
        found = np.isfinite(dn)
        if bsegs is not None and found.any():  # every (point, field point) pair at once
            rows, cols = np.nonzero(found)
            crossed = across_border(p[rows], field_p[jn[rows, cols]], bsegs)
            found[rows[crossed], cols[crossed]] = False
        s = np.where(found, (field_v[np.minimum(jn, len(field_v) - 1)] * n[:, None, :]).sum(axis=2), np.nan)
        enough = np.count_nonzero(found, axis=1) >= _NEAREST // 2
        mv = np.full(len(idx), np.nan)
        spread = np.full(len(idx), np.nan)
        if enough.any():
            mv[enough] = np.nanmedian(s[enough], axis=1)
            spread[enough] = 1.4826 * np.nanmedian(np.abs(s[enough] - mv[enough, None]), axis=1)
        # within the pairing's bounds: in the shift's direction, no farther than it
        _, near = centre_tree.query(p)
        want = -ds[near]
        along = mv * np.sign(want)
        ok = (along >= -config.min_shift_m / 2) & (along <= np.abs(want) + config.unseen_match_m)
        new = p + np.where(ok, mv, 0.0)[:, None] * n
        if ok.any():  # seen after all: a local marking near its new place
            d_new, _ = marks_tree.query(new[ok], distance_upper_bound=config.unseen_seen_m)
            ok[np.flatnonzero(ok)[np.isfinite(d_new)]] = False
        if not ok.any():
            continue
        at = idx[ok]
        ids_at = ids[near[ok]]
        feats[fi], made = with_modelled(feats[fi], at, new[ok], mv[ok], spread[ok], ids_at, pts[at])
        pieces += made
    if len(pieces) == n_before:
        return moved
    return UnseenMove(replace(moved.map, features=tuple(feats)), tuple(pieces))
