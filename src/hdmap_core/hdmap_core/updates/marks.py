"""The lines a re-striping or a removed / new marking left alone: kept from the first map.

A change of the shares' kinds (``type``: a marking re-striped; ``marking_gone``; ``marking_new``)
acts on one marking or a few of a carriageway; the others stay where and what they were. The few
drives after the change see the markings of their own lane nearly always and farther ones now and
then, so a changed place rebuilt from them alone loses far lines that nothing changed (the right
edge line beside the far lane, a ramp's lines). In the rebuilt places of such changes (not those
of a change with a geometry or lane kind, nor the places next to those) a first-map marking point
is replaced only where the drives after the change said something of it:

1. **seen**: the aligned local map has a marking within ``_SAME_LINE_M`` of it: the local map's
   line is taken there (with the type the drives after the change saw);
2. **gone**: in the places of a change with ``marking_gone`` (and their neighbours), a point
   that the local map lacks and no drive after the change detected within ``_DETECTED_M``, and
   that lay within ``ChangeConfig.near_m`` of such a drive (its own lane's markings, seen ~95 %
   of the time), or within twice that (the next lane's, seen ~70 %, in dropouts up to hundreds
   of metres long) when its type is one that went in a drive's own lane (``_MIN_GONE_POINTS``):
   dropped. A removed line left there would be a ghost of the old road. One drive that did not
   see a line in its next band is weak evidence: it tells a removed dashed divider from the
   unchanged solid edge line beside it only by the type (before this, every line of that band
   went: the right edge line beside the far lane kept 46 % of its zone after 3 drives through a
   removed marking on ``motorway_ramps`` seed 0, the zone's recall 89.9 %, now 95.5 %);
3. otherwise the drives after the change have no evidence of it, for or against: it **stays**
   (``updates.splice.Reach.keep``): a far line beside the drives' lanes, and on a re-striped
   place any line the local map lacks (re-striping removes none).

Road borders are not touched here (``updates.splice.Reach`` keeps a first-map border the local
map lacks).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.geometry import dense_points
from hdmap_core.model import Drive, FeatureType, HDMap
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange
from hdmap_core.updates.places import PlaceKey, Places, markings_in

__all__ = ["SHARE_KINDS", "share_places", "unchanged_marks"]

#: The change kinds of one marking's type or presence (the shares of ``updates.evidence``).
SHARE_KINDS = ("type", "marking_gone", "marking_new")
_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))
# A first-map marking point and an (aligned) local-map marking this close are the same line: well
# within half a lane (3.5 m), beyond what is left of the alignment's error [m].
_SAME_LINE_M = 1.0
# ... a first-map marking point with a detection of a drive after the change (anchored) this close
# was seen by it, though too few drives saw it for the local map: it is no gone line. Half the
# alignment tolerance: a drive whose anchor took the other carriageway's barrier (2.5 m off)
# puts its lines 1 m beside the first map's [m].
_DETECTED_M = 0.5
_STEP_M = 0.5  # lines are looked up at this spacing [m]
# first-map points of one type missed in the ego band of the drives after the change that make it
# a type that went (a few points are a line's end or a misread) [count]
_MIN_GONE_POINTS = 20


def share_places(changes: Sequence[DetectedChange], places: Places, rebuilt: set[PlaceKey]) -> set[PlaceKey]:
    """The rebuilt places whose change is only of the shares' kinds: ``rebuilt`` less the places
    of a change with another kind (geometry, lane closed / opened) and their neighbours."""
    other = {p.key for c in changes if any(k not in SHARE_KINDS for k in c.kinds) for p in c.places}
    other |= {nb for k in other for nb in places.neighbours(k)}
    return set(rebuilt) - other


def unchanged_marks(
    first: HDMap,
    local: HDMap,
    places: Places,
    changes: Sequence[DetectedChange],
    after: Sequence[Drive],
    rebuilt: set[PlaceKey],
    *,
    config: ChangeConfig = ChangeConfig(),
) -> np.ndarray:
    """(K, 2) the first map's marking points in the share-only places of ``rebuilt`` that stay
    (module docstring): neither seen in ``local`` (the aligned rebuild) nor gone next to the
    drives ``after`` the change (anchored on the first map)."""
    keys = share_places(changes, places, rebuilt)
    none = np.zeros((0, 2))
    if not keys or not after:
        return none
    went = {pc.key for c in changes if "marking_gone" in c.kinds for pc in c.places}
    went |= {nb for k in went for nb in places.neighbours(k)}
    cand: list[np.ndarray] = [none]
    in_went: list[np.ndarray] = [np.zeros(0, dtype=bool)]
    ptype: list[np.ndarray] = [np.zeros(0, dtype=np.int64)]
    for _, f, pts, fkeys, inside in markings_in(first, places, keys):
        cand.append(pts[inside])
        in_went.append(np.array([k in went for k, i in zip(fkeys, inside) if i], dtype=bool))
        ptype.append(np.full(int(inside.sum()), int(f.type), dtype=np.int64))
    p = np.concatenate(cand)
    types = np.concatenate(ptype)
    local_marks = dense_points([f.points for f in local.features if int(f.type) in _MARKINGS], _STEP_M)
    if len(p) == 0:
        return none
    seen = np.zeros(len(p), dtype=bool)
    if len(local_marks):
        d, _ = cKDTree(local_marks).query(p, distance_upper_bound=_SAME_LINE_M)
        seen = np.isfinite(d)
    # next to a drive after the change: in its lane (ego band) or the next
    dist = np.full(len(p), np.inf)
    detected = np.zeros(len(p), dtype=bool)
    for dr in after:
        if len(dr.xy):
            dp, _ = cKDTree(np.asarray(dr.xy, dtype=float)).query(p, distance_upper_bound=2 * config.near_m)
            dist = np.minimum(dist, dp)
            marks = dense_points([det.points for det in dr.detections if int(det.type) in _MARKINGS], _STEP_M)
            if len(marks):
                dd, _ = cKDTree(marks).query(p, distance_upper_bound=_DETECTED_M)
                detected |= np.isfinite(dd)
    unseen = ~seen & ~detected & np.concatenate(in_went)
    ego = unseen & (dist <= config.near_m)
    # a line in the next band only (seen there ~70 % of the time, in blocks of up to hundreds of
    # metres) is gone when its type went in some drive's ego band (seen ~95 %): one drive that
    # missed a line in its next band tells a removed divider from the unchanged edge line beside
    # it by no more than that
    went_types = [t for t in _MARKINGS if np.count_nonzero(ego & (types == t)) >= _MIN_GONE_POINTS]
    gone = ego | (unseen & np.isfinite(dist) & np.isin(types, went_types))
    return p[~seen & ~gone]
