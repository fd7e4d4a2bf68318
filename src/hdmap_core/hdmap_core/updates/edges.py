"""A lane closed or opened: the road's right edge line moved by about a lane.

A closed lane moves the right edge marking onto the divider left of it; an opened shoulder moves
it out. Drives see it as a solid line where the map has a dashed one (or none) and miss the old
edge, which needs ``min_after_shares`` drives after the change to confirm as shares
(``updates.detect``). Measured directly it is one number per drive and place:

* **edge move**: on a cut across the drive every ``_STEP_M``, the rightmost solid marking the
  drive saw on its right against the map's rightmost solid marking on its right, after the drive's
  anchor (its offset on the road borders, ``updates.evidence``): ~0 on the unchanged road,
  about plus a lane (to the left) after a close, minus the shoulder after an open. Only on the
  cuts where the map's edge line lies within ``_SEEN_M`` right of the drive (whether a drive in
  the far lane sees it depends on its lane and its sensor, not on the road: such drives made the
  series two-valued at ramps); the median over the place's cuts where both exist (at least
  ``_MIN_CUTS``).
* **the old edge a divider**: an opened shoulder moves the edge out of the next lane's sensor band
  (0.25 visibility in the simulator's far band against 0.7 in the next) and draws a dashed divider
  where the edge was, which the drives of the next lane see. A cut where the drive saw a dashed
  marking within ``_TURN_M`` of the map's edge line and no solid one there counts with the cuts
  that measured the move (at least ``_MIN_CUTS_TURNED`` of them, their median at least half the
  smallest move outward); a place where the drive saw no solid there and a dashed one on at least
  ``_MIN_CUTS`` cuts, but the moved edge on too few, reads the smallest move that is a lane
  (``-MIN_EDGE_MOVE_M``: a lane lies beyond the divider), marked not ``measured``. Without it an
  opened shoulder needed two drives after it in the right lane itself (9 drives through the zone
  on ``motorway_ramps`` seed 0, where a third of the drives keep to the right lane).

A change point of that series (``detect.change_point``, as for the displacement, but with at
least ``_MIN_BEFORE`` drives before (a few drives that saw the edge on a handful of cuts made a
change back on carla_town06), >= ``min_after`` after, at least ``MIN_EDGE_MOVE_M``, and at least
one drive after it that measured the move, not only saw a divider: a misread type is no lane)
confirms the place; touching confirmed places of one direction are one change, ``lane_closed`` (edge moved left) or
``lane_opened``; it grows into neighbouring places where a drive after it shows at least half
the move the same way and none the other (the tapers). A shift of the markings by less than
``MIN_EDGE_MOVE_M`` is no lane change (it is the displacement's), nor a drive badly localised
(the anchor takes that out). A larger shift the displacement does not see shows as one; one it
sees is no lane change either: where the edge moved with the markings, the move left after their
displacement is less than ``MIN_EDGE_MOVE_M`` (``merge_changes``; a 3 m shift read as a lane
opened by the next lane's drives lost the shift's model of the lines they did not see).
"""

from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from collections.abc import Collection, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.evaluation.cuts import (
    index_segments,
    segments_of,
)
from hdmap_core.geometry import dense_points, turn_left, unit_tangents
from hdmap_core.model import Drive, FeatureType, HDMap
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.detect import DetectedChange, PlaceChange, change_point, grow_changes
from hdmap_core.updates.evidence import PlaceEvidence, drive_cuts, lines_on_cuts
from hdmap_core.updates.places import PlaceKey, Places
from hdmap_core.updates.unseen import ModelledMarking, UnseenMove

__all__ = [
    "EdgeEvidence",
    "edge_evidence",
    "EdgeSide",
    "edge_side",
    "detect_edge_changes",
    "merge_changes",
    "opened_edge_moved",
    "MIN_EDGE_MOVE_M",
]

MIN_EDGE_MOVE_M = 1.8  # the smallest move of the edge line that is a lane closed / opened (a 2 m shoulder) [m]
_STEP_M = 8.0  # cut spacing [m]
_SOLID = int(FeatureType.SOLID)
_DASHED = int(FeatureType.DASHED)
_SEEN_M = 6.0  # the map's edge line counts where it lies this close right of the drive (the next lane's) [m]
_MIN_CUTS = 6  # cuts a drive needs in a place for its edge move there (a place is ~12 cuts long)
_MIN_CUTS_TURNED = 2  # cuts that measured the opened edge, when cuts where its old line turned dashed make up the rest
_TURN_M = 0.5  # a dashed marking this close to the map's edge line, and no solid one, is the edge turned divider [m]
_MARKINGS = (_SOLID, _DASHED)
_EDGE_APART_M = 0.5  # a first-map marking this far right of a solid one makes it no edge line [m]
_SAME_LINE_M = 1.0  # a first-map marking point with a local-map marking this close was seen [m]
_EDGE_STD_M = 0.2  # lateral uncertainty added to an opened edge moved by the confirmed move [m]
_MIN_BEFORE = 5  # drives a place needs before a change point of the edge (it is noisier than the displacement)
_MIN_PLACE_DRIVES = 2  # drives after the change that measured a place's move, else it must be the change's move
_BORDER = int(FeatureType.ROAD_BORDER)


@dataclass(frozen=True)
class EdgeEvidence:
    """One drive's edge move at one place (module docstring); NaN where it saw too little."""

    drive_id: str
    time_ns: int
    key: PlaceKey
    move_m: float
    n_cuts: int
    measured: bool = True  # False: the old edge line seen as a divider, the move taken as the least one


def _rightmost(cut: np.ndarray, s: np.ndarray, k: int, reach: float) -> np.ndarray:
    """Per cut, the smallest s in [-reach, 0) (NaN where none)."""
    out = np.full(k, np.inf)
    sel = (s < 0) & (s >= -reach)
    np.minimum.at(out, cut[sel], s[sel])
    out[~np.isfinite(out)] = np.nan
    return out


@dataclass(frozen=True)
class EdgeSide:
    """The drive's own side of ``edge_evidence``, which no map changes: its cuts every
    ``_STEP_M`` (center (K, 2), unit tangent (K, 2), yaw (K,)), ``view_m`` to each side, and its
    solid and dashed markings on them (cut, lateral position; None: it saw none; the dashed ones
    only where it saw a solid one)."""

    view_m: float
    center: np.ndarray
    tangent: np.ndarray
    yaw: np.ndarray
    solid: tuple[np.ndarray, np.ndarray] | None
    dashed: tuple[np.ndarray, np.ndarray] | None


def edge_side(drive: Drive, config: ChangeConfig = ChangeConfig()) -> EdgeSide:
    """``drive``'s own side of its edge evidence (``EdgeSide``); a drive of at least 2 poses."""
    center, tangent, yaw = drive_cuts(drive, _STEP_M)

    def on_cuts(kind: int) -> tuple[np.ndarray, np.ndarray] | None:
        dets = [d for d in drive.detections if int(d.type) == kind and len(d.points) >= 2]
        if not dets:
            return None
        cut, _, s = lines_on_cuts(
            center, tangent, config.view_m, segments_of([np.asarray(d.points, dtype=float) for d in dets])
        )
        return cut, s

    solid = on_cuts(_SOLID)
    return EdgeSide(config.view_m, center, tangent, yaw, solid, on_cuts(_DASHED) if solid is not None else None)


def edge_evidence(
    drive: Drive,
    solids: HDMap | tuple,
    places: Places,
    anchors: dict[PlaceKey, float],
    *,
    config: ChangeConfig = ChangeConfig(),
    side: EdgeSide | None = None,
) -> list[EdgeEvidence]:
    """The edge move of ``drive`` per place it crossed; ``solids``: the map, or its solid
    markings as ``(segments or their index, types)`` (``solid_lines``); ``anchors``: its anchor per
    place; ``side``: ``edge_side(drive, config)`` made before (else made here)."""
    segs, types = solid_lines(solids) if isinstance(solids, HDMap) else solids
    if len(drive.xy) < 2 or len(types) == 0:
        return []
    if side is None or side.view_m != config.view_m:
        side = edge_side(drive, config)
    if side.solid is None:
        return []
    center, tangent, yaw = side.center, side.tangent, side.yaw
    k = len(center)
    d_cut, d_s = side.solid
    m_cut, _, m_s = lines_on_cuts(center, tangent, config.view_m, segs)
    keys = places.keys(center, yaw)
    a = np.array([anchors.get(key, np.nan) for key in keys])
    drive_right = _rightmost(d_cut, d_s, k, config.view_m)
    # the map's lines in the drive's frame: map - drive = anchor where nothing moved
    map_right = _rightmost(m_cut, m_s - np.nan_to_num(a)[m_cut], k, config.view_m)
    move = drive_right - map_right  # + = the edge moved left of where the map has it
    # only where the drive would have seen the map's edge line: farther out, whether a drive sees
    # it depends on its lane and the sensor's reach, not on the road
    seen = (map_right >= -_SEEN_M) & np.isfinite(a)
    move[~seen] = np.nan
    turned, solid_there = _at_edge(k, side.dashed, map_right, d_cut, d_s)
    turned &= seen
    ids = {key: i for i, key in enumerate(dict.fromkeys(keys))}
    place = np.array([ids[key] for key in keys], dtype=np.int64)
    good = np.isfinite(move)
    n_good = np.bincount(place[good], minlength=len(ids))
    # an opened edge seen from the next lane: its old line turned dashed on the cuts where the
    # moved one (in the sensor's far band) was not seen
    n_turned = np.bincount(place[turned & ~good], minlength=len(ids))
    n_solid = np.bincount(place[solid_there & seen], minlength=len(ids))
    out = []
    for key, p in ids.items():
        n, measured = int(n_good[p]), True
        value = float(np.median(move[good & (place == p)])) if n else math.nan
        if n < _MIN_CUTS and n + int(n_turned[p]) >= _MIN_CUTS:
            if n >= _MIN_CUTS_TURNED and value <= -MIN_EDGE_MOVE_M / 2:
                n += int(n_turned[p])  # the move measured on a few cuts, the old line a divider on the others
            elif n_turned[p] >= _MIN_CUTS and not n_solid[p]:
                # the old edge line is a divider all along the place: a lane lies beyond it, the
                # edge moved out by at least the smallest move that is a lane (how far, the drive
                # did not see); such a drive supports a change another drive measured
                n, value, measured = int(n_turned[p]), -MIN_EDGE_MOVE_M, False
        if n < _MIN_CUTS:
            value = math.nan
        out.append(EdgeEvidence(drive.drive_id, drive.start_ns, key, value, n, measured))
    return out


def _at_edge(
    k: int,
    dashed: tuple[np.ndarray, np.ndarray] | None,
    map_right: np.ndarray,
    d_cut: np.ndarray,
    d_s: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Per cut of the ``k``, (the drive saw a dashed marking (``dashed``: cut, lateral position)
    within ``_TURN_M`` of the map's edge line (``map_right``, in the drive's frame) and no solid
    one (``d_cut``, ``d_s``) there: the edge line became a divider, the drive saw a solid one
    there)."""
    near_solid = np.zeros(k, dtype=bool)
    near_solid[d_cut[np.abs(d_s - map_right[d_cut]) <= _TURN_M]] = True
    if dashed is None:
        return np.zeros(k, dtype=bool), near_solid
    t_cut, t_s = dashed
    near_dashed = np.zeros(k, dtype=bool)
    near_dashed[t_cut[np.abs(t_s - map_right[t_cut]) <= _TURN_M]] = True
    return near_dashed & ~near_solid, near_solid


def solid_lines(hdmap: HDMap) -> tuple:
    """The map's solid markings as ``(SegmentIndex, types)``, indexed once for every drive."""
    feats = [f for f in hdmap.features if int(f.type) == _SOLID and len(f.points) >= 2]
    segs = segments_of([np.asarray(f.points, dtype=float) for f in feats])
    return index_segments(segs), np.full(len(segs.owner), _SOLID, dtype=np.int64)


def fleet_edge_evidence(
    drives: Sequence[Drive], hdmap: HDMap, places: Places, evidence: Sequence[PlaceEvidence], *, config: ChangeConfig
) -> list[EdgeEvidence]:
    """``edge_evidence`` of every drive, anchored as in ``evidence`` (``updates.evidence``)."""
    anchors: dict[str, dict[PlaceKey, float]] = defaultdict(dict)
    for e in evidence:
        if np.isfinite(e.anchor_m):
            anchors[e.drive_id][e.key] = e.anchor_m
    lines = solid_lines(hdmap)
    return [x for d in drives for x in edge_evidence(d, lines, places, anchors[d.drive_id], config=config)]


def detect_edge_changes(
    evidence: Sequence[EdgeEvidence], places: Places, *, config: ChangeConfig = ChangeConfig()
) -> list[DetectedChange]:
    """The lanes closed and opened the edge evidence confirms (module docstring), in time order."""
    by_place: dict[PlaceKey, list[EdgeEvidence]] = defaultdict(list)
    for e in evidence:
        if np.isfinite(e.move_m):
            by_place[e.key].append(e)
    confirmed: dict[PlaceKey, PlaceChange] = {}
    for key, rows in sorted(by_place.items()):
        rows.sort(key=lambda e: (e.time_ns, e.drive_id))
        vals = np.array([e.move_m for e in rows])
        found = change_point(
            vals,
            min_effect=MIN_EDGE_MOVE_M,
            floor=config.displacement_floor_m,
            z_min=config.z_min,
            min_before=max(config.min_before, _MIN_BEFORE),
            min_after=config.min_after,
        )
        if found is None:
            continue
        i, effect, z = found
        if not any(e.measured for e in rows[i:]):
            continue  # the old edge line seen as a divider only supports a move some drive measured
        kind = "lane_closed" if effect > 0 else "lane_opened"
        confirmed[key] = PlaceChange(
            key,
            kind,
            rows[i].time_ns,
            rows[i - 1].time_ns,
            effect,
            z,
            tuple(e.drive_id for e in rows[:i]),
            tuple(e.drive_id for e in rows[i:]),
        )
    # Grow along the road into the tapers: a neighbour where a drive after the change shows at
    # least half the smallest move the same way against the place's drives before, none the other.
    confirmed = grow_changes(confirmed, places, lambda nb, c: _extends(by_place[nb], nb, c) if nb in by_place else None)
    out: list[DetectedChange] = []

    def same_kind(seed: PlaceKey, nb: PlaceKey) -> bool:
        return confirmed[nb].kind == confirmed[seed].kind

    for keys in places.components(confirmed, joins=same_kind):
        comp = [confirmed[k] for k in sorted(keys)]
        if all(p.extended for p in comp):
            continue
        times = sorted(p.time_ns for p in comp if not p.extended)
        t = times[(len(times) - 1) // 2]
        digest = hashlib.sha1(repr(([p.key for p in comp], t, "edge")).encode()).digest()
        out.append(
            DetectedChange(
                id=int.from_bytes(digest[:8], "little") & ((1 << 63) - 1),
                time_ns=t,
                kinds=(comp[0].kind,),
                places=tuple(comp),
                drives_after=tuple(sorted({d for p in comp for d in p.drives_after})),
                confidence=1.0 - 1.0 / max(p.z for p in comp if not p.extended),
            )
        )
    return sorted(out, key=lambda c: (c.time_ns, c.id))


def _extends(rows: list[EdgeEvidence], key: PlaceKey, change: PlaceChange) -> PlaceChange | None:
    before = [e for e in rows if e.time_ns < change.time_ns]
    after = [e for e in rows if e.time_ns >= change.time_ns]
    if len(before) < 3 or not after:
        return None
    med = float(np.median([e.move_m for e in before]))
    sign = 1.0 if change.effect > 0 else -1.0
    dev = np.array([(e.move_m - med) * sign for e in after])
    if np.any(dev <= -MIN_EDGE_MOVE_M / 2) or not np.any(dev >= MIN_EDGE_MOVE_M / 2):
        return None
    showing = [e for e, d in zip(after, dev) if d >= MIN_EDGE_MOVE_M / 2]
    return PlaceChange(
        key,
        change.kind,
        change.time_ns,
        change.last_before_ns,
        float(np.mean([e.move_m - med for e in showing])),
        math.nan,
        tuple(e.drive_id for e in before),
        tuple(e.drive_id for e in showing),
        extended=True,
    )


def merge_changes(
    changes: Sequence[DetectedChange], edges: Sequence[DetectedChange], places: Places
) -> list[DetectedChange]:
    """``changes`` with the lane changes ``edges``: one that shares or touches a place of a change
    joins it (its places there are the change's; its kinds and drives are added), else it is a
    change of its own. One whose edge moved with the markings of the change it touches (the
    displacement of its geometry places takes all but less than ``MIN_EDGE_MOVE_M`` of the
    edge's move) is that shift, no lane change: it is left out."""
    out = list(changes)
    for e in edges:
        near = {nb for p in e.places for nb in (p.key, *places.neighbours(p.key))}
        hit = next((i for i, c in enumerate(out) if near & c.keys), None)
        if hit is None:
            out.append(e)
            continue
        c = out[hit]
        shift = [p.effect for p in c.places if p.kind == "geometry"]
        # signs: the displacement is + to the right, the edge's move + to the left
        if shift and abs(float(np.median([p.effect for p in e.places])) + float(np.median(shift))) < MIN_EDGE_MOVE_M:
            continue
        have = c.keys
        out[hit] = DetectedChange(
            id=c.id,
            time_ns=c.time_ns,
            kinds=tuple(sorted({*c.kinds, *e.kinds})),
            places=tuple(sorted([*c.places, *(p for p in e.places if p.key not in have)], key=lambda p: p.key)),
            drives_after=tuple(sorted({*c.drives_after, *e.drives_after})),
            confidence=max(c.confidence, e.confidence),
        )
    return sorted(out, key=lambda c: (c.time_ns, c.id))


def opened_edge_moved(
    first: HDMap,
    local: HDMap,
    places: Places,
    changes: Sequence[DetectedChange],
    rebuilt: set[PlaceKey],
    *,
    evidence: Sequence[EdgeEvidence] | None = None,
    config: ChangeConfig = ChangeConfig(),
) -> tuple[UnseenMove, np.ndarray]:
    """The first map with the right edge line of an opened shoulder moved out by the confirmed
    move, where no drive after the change saw it (module docstring of ``updates.unseen`` for the
    record kept of it).

    The drives after a ``lane_opened`` change mostly keep to the lanes they drove before, left of
    the new lane: the moved edge lies in their far band or beyond (seen a quarter of the time, or
    never), so the rebuilt places lack it where none of them saw it. The change measured how far
    the edge moved per place (``PlaceChange.effect``: + left); each first-map solid marking point
    of a rebuilt ``lane_opened`` place that is the carriageway's rightmost marking there (no
    first-map marking within ``_SEEN_M`` to its right that more drives saw than drove after the
    change: the first map holds the new line too where a few drives saw it) moves out by it,
    unless the aligned local map has a solid marking within ``unseen_seen_m`` of where it moves
    to (seen: the local map's line is taken). Its points get ``drive_count`` 0 and a ``lateral_std`` grown by the move's
    spread over the place's drives after the change (at least ``_EDGE_STD_M``). With ``evidence``
    (the drives' edge moves) the move of a place is what its drives after the change measured
    (``EdgeEvidence.measured``, their median against the median of the drives before): a drive
    that saw only the old edge turned divider reads the least move that is a lane, not the move;
    a place none of them measured (a taper one drive passed) gets no model, nor one where fewer
    than ``_MIN_PLACE_DRIVES`` measured a move more than ``unseen_seen_m`` from the change's
    move (the median over its places confirmed on their own; there the edge runs from the old
    line to the moved one: a taper). A point of a line no more drives saw than drove after the
    change that lies the move out from an old-road marking (within ``unseen_seen_m``) is the
    moved edge already: it is not moved again; and no point moves beyond the first map's road
    border right of it (``_to_border``).

    An opened lane moves that line only: every other first-map marking point of the rebuilt
    places of such a change (and their neighbours) that the local map lacks (no marking within
    ``_SAME_LINE_M``), but for the edge line itself, stays where it was (second value, for
    ``updates.splice.Reach.keep``): three
    drives after the change see their own and the next lanes' lines, and near the ends of the
    rebuilt stretch the lines they missed were lost (the left edge line and the first divider
    over 100-200 m on ``motorway_ramps`` seed 0). Only for a change that is a lane opened alone
    (merged with a shift, the lines moved).
    """
    moves: dict[PlaceKey, tuple[int, float]] = {}
    region: set[PlaceKey] = set()
    opened: set[PlaceKey] = set()
    n_after = 0
    for c in changes:
        if tuple(c.kinds) != ("lane_opened",):
            continue
        n_after = max(n_after, len(c.drives_after))
        # without evidence the confirmed effect stands (as if measured by enough drives)
        measured = {
            p.key: (float(p.effect), _MIN_PLACE_DRIVES) if evidence is None else _measured_move(p, evidence)
            for p in c.places
        }
        # the change's move: that of the places it confirmed on their own
        own = np.array([measured[p.key][0] for p in c.places if not p.extended])
        full = float(np.median(own[np.isfinite(own)])) if np.isfinite(own).any() else math.nan
        for p in c.places:
            region |= {p.key, *places.neighbours(p.key)}
            if p.kind == "lane_opened" and p.key in rebuilt and p.effect < 0:
                opened.add(p.key)
                move, n = measured[p.key]
                if n < _MIN_PLACE_DRIVES and abs(move - full) > config.unseen_seen_m:
                    # one drive's median over a place where the edge runs from the old line to
                    # the moved one (a taper) is no move of its points
                    continue
                if move <= -MIN_EDGE_MOVE_M / 2:  # NaN: none measured; less: a taper's start
                    moves[p.key] = (c.id, move)
    region &= set(rebuilt)
    none = UnseenMove(first, ())
    no_pts = np.zeros((0, 2))
    if not opened:
        return none, no_pts
    marks = [(i, f) for i, f in enumerate(first.features) if int(f.type) in _MARKINGS and len(f.points) >= 2]
    if not marks:
        return none, no_pts
    all_pts = np.concatenate([np.asarray(f.points, dtype=float) for _, f in marks])
    # a first-map line no more drives saw than drove after the change may be the new one (the
    # first map is built from every drive): it does not make the old edge line a divider
    old_road = np.concatenate([np.asarray(f.drive_count) > n_after for _, f in marks])
    all_tree = cKDTree(all_pts)
    old_tree = cKDTree(all_pts[old_road]) if old_road.any() else None
    borders = _dense_tree(first, {_BORDER})
    local_solid = _dense_tree(local, {_SOLID})
    local_marks = _dense_tree(local, _MARKINGS)
    feats = list(first.features)
    pieces: list[ModelledMarking] = []
    kept: list[np.ndarray] = [no_pts]
    for fi, f in marks:
        pts = np.asarray(f.points, dtype=float)
        keys = places.keys_along(pts)
        stay = np.array([k in region for k in keys], dtype=bool)
        if local_marks is not None and stay.any():
            d, _ = local_marks[1].query(pts[stay], distance_upper_bound=_SAME_LINE_M)
            stay[np.flatnonzero(stay)[np.isfinite(d)]] = False
        at = np.array([k in opened for k in keys], dtype=bool)
        if int(f.type) != _SOLID or not (at | stay).any():
            kept.append(pts[stay])
            continue
        t = unit_tangents(pts)
        left = turn_left(t)
        ok = at | stay
        # the rightmost marking: no first-map marking to its right within _SEEN_M
        for i in np.flatnonzero(ok):
            near = all_tree.query_ball_point(pts[i], _SEEN_M)
            if near:
                near = [j for j in near if old_road[j]]
                v = all_pts[near] - pts[i]
                lat, lon = v @ left[i], v @ t[i]
                if np.any((lat < -_EDGE_APART_M) & (np.abs(lon) < _SEEN_M)):
                    ok[i] = False
        # the edge line's points do not stay where they were, nor beside the opened places (the
        # tapers the change left out: kept there, the old edge was a ghost of the old road)
        kept.append(pts[stay & ~ok])
        ok &= at & np.array([k in moves for k in keys], dtype=bool)
        if not ok.any():
            continue
        mv = np.array([moves[k][1] if k in moves else 0.0 for k in keys])
        # a point of a line only the drives after the change may have seen that lies the move
        # out from an old-road marking is the moved edge already: not moved again
        young = ok & (np.asarray(f.drive_count) <= n_after)
        if old_tree is not None and young.any():
            yi = np.flatnonzero(young)
            d, _ = old_tree.query(pts[yi] - mv[yi, None] * left[yi], distance_upper_bound=config.unseen_seen_m)
            ok[yi[np.isfinite(d)]] = False
        # no further out than the road border right of it
        mv = np.where(ok, _to_border(pts, t, left, mv, borders), mv)
        ok &= mv <= -MIN_EDGE_MOVE_M / 2
        if not ok.any():
            continue
        new = pts + mv[:, None] * left
        if local_solid is not None:
            d, _ = local_solid[1].query(new[ok], distance_upper_bound=config.unseen_seen_m)
            ok[np.flatnonzero(ok)[np.isfinite(d)]] = False
        if not ok.any():
            continue
        idx = np.flatnonzero(ok)
        new_pts = pts.copy()
        new_pts[idx] = new[idx]
        count = np.asarray(f.drive_count).copy()
        count[idx] = 0
        std = np.asarray(f.lateral_std, dtype=float).copy()
        std[idx] = np.hypot(std[idx], _EDGE_STD_M)
        feats[fi] = replace(f, points=new_pts, drive_count=count, lateral_std=std)
        for r in np.split(idx, np.flatnonzero(np.diff(idx) != 1) + 1):
            if len(r):
                pieces.append(
                    ModelledMarking(
                        change_id=moves[keys[r[0]]][0],
                        feature_id=int(f.id),
                        type=int(f.type),
                        points=new[r].copy(),
                        from_points=pts[r].copy(),
                        move_m=mv[r].copy(),
                    )
                )
    stays = np.concatenate(kept)
    if not pieces:
        return none, stays
    return UnseenMove(replace(first, features=tuple(feats)), tuple(pieces)), stays


def _dense_tree(hdmap: HDMap, types: Collection[int]) -> tuple[np.ndarray, cKDTree] | None:
    """The points of ``hdmap``'s features of ``types`` every 0.5 m and their tree (None: none)."""
    pts = dense_points([f.points for f in hdmap.features if int(f.type) in types], 0.5)
    return (pts, cKDTree(pts)) if len(pts) else None


def _to_border(
    pts: np.ndarray, t: np.ndarray, left: np.ndarray, mv: np.ndarray, borders: tuple[np.ndarray, cKDTree] | None
) -> np.ndarray:
    """``mv`` (+ left, per point of ``pts``; tangents ``t``, their left normals ``left``) limited
    to the nearest road border of ``borders`` (points, their tree) right of each point, beside it
    (within ``_SAME_LINE_M`` along): no marking moves beyond the road's border (a move that ends
    more than ``_EDGE_STD_M`` beyond it, the modelled edge's own uncertainty, ends on it). A
    border less than ``_EDGE_APART_M`` left of a point counts too (the point lies on it: it moves
    nowhere)."""
    out = np.asarray(mv, dtype=float).copy()
    if borders is None:
        return out
    b_pts, b_tree = borders
    for i in np.flatnonzero(out < 0):
        near = b_tree.query_ball_point(pts[i], -out[i] + _SAME_LINE_M)
        if not near:
            continue
        v = b_pts[near] - pts[i]
        lat, lon = v @ left[i], v @ t[i]
        right = (lat < _EDGE_APART_M) & (np.abs(lon) < _SAME_LINE_M)
        if right.any():
            limit = float(lat[right].max())
            if out[i] < limit - _EDGE_STD_M:
                out[i] = limit
    return out


def _measured_move(p: PlaceChange, evidence: Sequence[EdgeEvidence]) -> tuple[float, int]:
    """The edge move at ``p`` its drives after the change measured: the median of their measured
    moves less the median of the drives before (NaN when none measured it), and how many
    measured it."""
    after, before = set(p.drives_after), set(p.drives_before)
    rows = [e for e in evidence if e.key == p.key and np.isfinite(e.move_m)]
    got = [e.move_m for e in rows if e.drive_id in after and e.measured]
    was = [e.move_m for e in rows if e.drive_id in before]
    if not got or not was:
        return math.nan, 0
    return float(np.median(got) - np.median(was)), len(got)
