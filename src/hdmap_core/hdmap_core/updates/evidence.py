"""One drive compared with the map, place by place: the evidence of a changed road.

On a cut across the drive's path every ``cut_step_m`` the drive's own lines and the map's lines
are intersected (the evaluator's vectorised cut machinery). Per place (``updates.places``):

* **offset**: the mode of the density of (map - drive) lateral differences of marking pairs:
  where the drive's markings lie against the map's. It holds the drive's localisation error
  plus any move of the markings;
* **anchor**: the same over the road borders (barrier, shoulder border), which a construction
  zone leaves in place; where the drive saw too few, the mean of those of the places up to two
  before and after it along the drive (else its border offset over all its places, else its
  marking offset over all its places);
* **displacement** = offset - anchor: the markings' move relative to what did not move. A drive
  that is merely badly localised is off by the same amount in both: displacement ~ 0. A move
  near a lane's width is followed cut by cut along the drive (``_follow_move``), else each moved
  marking pairs with its neighbour's old place; ``unwrap_aliases`` reconciles the drives;
* **type**: of the drive's markings near it that match a map marking (after its offset), how
  many have the other type (dashed <-> solid);
* **negative**: of the map's markings near the drive, how many it did not see at all;
* **positive**: of the drive's markings near it, how many have no map marking.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from hdmap_core.evaluation.cuts import (
    SegmentIndex,
    Segments,
    index_segments,
    intersect_cuts,
    intersect_indexed,
    segments_of,
)
from hdmap_core.geometry import arc_length
from hdmap_core.model import Drive, FeatureType, HDMap
from hdmap_core.updates.config import ChangeConfig
from hdmap_core.updates.places import PlaceKey, Places

__all__ = [
    "PlaceEvidence",
    "MapLines",
    "map_lines",
    "drive_evidence",
    "DriveSide",
    "drive_side",
    "side_of_lines",
    "drive_cuts",
    "lines_on_cuts",
    "fleet_evidence",
    "unwrap_aliases",
    "density_mode",
]

_BORDER = int(FeatureType.ROAD_BORDER)
_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))
_COS_MIN = 0.7  # a line runs with the drive on a cut when cos(angle) >= this
_GRID_M = 0.02
_ANCHOR_REACH = 2  # places along the drive whose border offsets stand in for a place without
_ALIAS_M = 0.5  # a drive's move within this of the place's lane-sized move (or its alias) agrees
_BORDER_REACH_M = 1.0  # a place's border offset within this of the drive's (below half the barriers' 2.5 m)
_PEAK_SHARE = 0.5  # a peak of a drive's border pairs this share of the highest is a candidate offset
_SUPPORT_RATIO = 2.0  # ... taken over the highest with this many times its marking pairs


@dataclass(frozen=True)
class PlaceEvidence:
    """What one drive says about one place (module docstring). Offsets in metres, + = left of
    the drive; NaN where the drive saw too little."""

    drive_id: str
    time_ns: int
    key: PlaceKey
    n_cuts: int
    offset_m: float
    anchor_m: float
    anchored_on_borders: bool
    displacement_m: float
    n_pairs: int
    n_typed: int
    n_wrong_type: int
    n_map_near: int
    n_missed: int
    n_drive_near: int
    n_extra: int


@dataclass(frozen=True)
class MapLines:
    """The map's features as segments with their spatial index, ready to be cut by every drive;
    ``types`` (M,) per segment."""

    index: SegmentIndex
    types: np.ndarray

    @property
    def segments(self) -> Segments:
        return self.index.segments


def map_lines(hdmap: HDMap) -> MapLines:
    feats = [f for f in hdmap.features if len(f.points) >= 2]
    segs = segments_of([np.asarray(f.points, dtype=float) for f in feats])
    types = np.array([int(f.type) for f in feats], dtype=np.int64)[segs.owner] if feats else np.zeros(0, np.int64)
    return MapLines(index_segments(segs), types)


@functools.lru_cache(maxsize=8)
def _kernel(kernel_m: float) -> np.ndarray:
    """The Gaussian kernel on the grid, +- 3 widths (read-only: cached)."""
    half = int(np.ceil(3 * kernel_m / _GRID_M))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * _GRID_M / kernel_m) ** 2)
    k.setflags(write=False)
    return k


def density_mode(values: np.ndarray, *, reach_m: float, kernel_m: float, center: float = 0.0) -> tuple[float, int]:
    """(mode, support) of the Gaussian kernel density of ``values`` in ``center`` +- ``reach_m``:
    the mode refined as the mean of the values within 2 kernels of it, and their number."""
    v = values[np.abs(values - center) <= reach_m]
    if len(v) == 0:
        return float("nan"), 0
    edges = center + np.arange(-reach_m, reach_m + _GRID_M, _GRID_M)
    hist, _ = np.histogram(v, bins=edges)
    dens = np.convolve(hist.astype(float), _kernel(kernel_m), mode="same")
    mode = 0.5 * (edges[:-1] + edges[1:])[int(np.argmax(dens))]
    near = v[np.abs(v - mode) <= 2 * kernel_m]
    return float(near.mean()), len(near)


def drive_cuts(drive: Drive, step_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(center (K, 2), unit tangent (K, 2), yaw (K,)) every ``step_m`` along the drive."""
    xy = np.asarray(drive.xy, dtype=float)
    s = arc_length(xy)
    q = np.arange(0.0, s[-1], step_m) if s[-1] > 0 else np.zeros(1)
    i = np.clip(np.searchsorted(s, q), 0, len(xy) - 1)
    yaw = np.asarray(drive.yaw, dtype=float)[i]
    return xy[i], np.stack([np.cos(yaw), np.sin(yaw)], axis=1), yaw


def lines_on_cuts(
    center: np.ndarray, tangent: np.ndarray, view_m: float, lines: Segments | SegmentIndex
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cut, segment, lateral position) of the ``lines`` crossing the cuts within ``view_m`` and
    running with the drive (cos of the angle >= _COS_MIN). The map's lines come indexed
    (``MapLines``, ``edges.solid_lines``): a drive's cuts query them, at a cost that grows with
    the drive, not with the map."""
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    k = len(center)
    lo, hi = np.full(k, -view_m), np.full(k, view_m)
    if isinstance(lines, SegmentIndex):
        segs = lines.segments
        ci, si, s, _ = intersect_indexed(center, normal, lo, hi, lines)
    else:
        segs = lines
        ci, si, s, _ = intersect_cuts(center, normal, lo, hi, segs)
    d = segs.b[si] - segs.a[si]
    ok = (d * tangent[ci]).sum(axis=1) >= _COS_MIN * np.linalg.norm(d, axis=1)
    return ci[ok], si[ok], s[ok]


def _on_cuts(center: np.ndarray, tangent: np.ndarray, view_m: float, lines: Segments | SegmentIndex, types: np.ndarray):
    """``lines_on_cuts`` with each line's type, ordered by cut, then segment."""
    ci, si, s = lines_on_cuts(center, tangent, view_m, lines)
    order = np.argsort(ci, kind="stable")
    return ci[order], s[order], types[si][order]


def _pairs(d_cut, d_s, m_cut, m_s, k: int, reach: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(drive point index, map point index, map - drive) of the pairs on the same cut within reach."""
    start = np.searchsorted(m_cut, np.arange(k), side="left")
    end = np.searchsorted(m_cut, np.arange(k), side="right")
    n = (end - start)[d_cut] if len(d_cut) else np.zeros(0, np.int64)
    di = np.repeat(np.arange(len(d_cut)), n)
    first = np.repeat(start[d_cut] if len(d_cut) else np.zeros(0, np.int64), n)
    offs = np.arange(len(di)) - np.repeat(np.cumsum(n) - n, n)
    mi = first + offs
    r = m_s[mi] - d_s[di] if len(mi) else np.zeros(0)
    keep = np.abs(r) <= reach
    return di[keep], mi[keep], r[keep]


def _by_place(place: np.ndarray, n_places: int):
    """place index -> the indices of ``place`` equal to it, in their order (one sort, not a mask
    per place)."""
    order = np.argsort(place, kind="stable")
    bounds = np.searchsorted(place[order], np.arange(n_places + 1))
    return lambda p: order[bounds[p] : bounds[p + 1]]


def _paired(
    o_cut: np.ndarray, drive: tuple[np.ndarray, np.ndarray], mapl: tuple[np.ndarray, np.ndarray], match_m: float
) -> np.ndarray:
    """Per cut, the markings an offset per cut ``o_cut`` (map - drive) pairs: the drive's
    ``(cut, lateral)`` markings with a map marking within ``match_m`` after it, and the map's
    with such a drive marking. Counted, not as a share of the lines in view: an offset that moves
    lines out of each other's view pairs fewer."""
    d_cut, d_s = drive
    m_cut, m_s = mapl
    k = len(o_cut)
    ti, tj, _ = _pairs(d_cut, d_s + o_cut[d_cut], m_cut, m_s, k, match_m)
    return np.bincount(d_cut[np.unique(ti)], minlength=k) + np.bincount(m_cut[np.unique(tj)], minlength=k)


def _border_offset(border: np.ndarray, marking: np.ndarray, config: ChangeConfig) -> float:
    """The drive's border offset over all its places: the mode of the density of its border pairs
    (map - drive), unless another peak of it (at least ``_PEAK_SHARE`` of the highest) has at
    least ``_SUPPORT_RATIO`` times the marking pairs (within 2 kernels). A drive sees the opposite
    carriageway's median barrier too, which pairs with the map's median barrier 2.5 m off (the
    map's opposite barrier runs the other way, unpaired): for a drive whose localisation error
    puts the true pair near the end of ``pair_max_m`` that pair can outnumber the true one, and
    every place then reads the markings' move 2.5 m off, or their lane alias. The markings pair
    at the true offset (and a lane's width off), not a barrier's gap off. NaN without borders."""
    reach, kernel = config.pair_max_m, config.kernel_m
    mode = density_mode(border, reach_m=reach, kernel_m=kernel)[0]
    v = border[np.abs(border) <= reach]
    if len(v) == 0:
        return mode
    edges = np.arange(-reach, reach + _GRID_M, _GRID_M)
    dens = np.convolve(np.histogram(v, bins=edges)[0].astype(float), _kernel(kernel), mode="same")
    mid = 0.5 * (edges[:-1] + edges[1:])
    inner = dens[1:-1]
    peaks = 1 + np.flatnonzero((inner > dens[:-2]) & (inner >= dens[2:]) & (inner >= _PEAK_SHARE * dens.max()))

    def support(at: float) -> int:
        return int(np.count_nonzero(np.abs(marking - at) <= 2 * kernel))

    top = support(mode)
    alt = max(
        (float(mid[i]) for i in peaks), key=lambda at: (support(at), dens[np.searchsorted(mid, at)]), default=None
    )
    if alt is None or abs(alt - mode) <= 2 * kernel or support(alt) < _SUPPORT_RATIO * max(top, 1):
        return mode
    return density_mode(border, reach_m=2 * kernel, kernel_m=kernel, center=alt)[0]


def _follow_move(cut: np.ndarray, move: np.ndarray, k: int, reach_m: float) -> np.ndarray:
    """The markings' move (the pairs' ``move`` per ``cut``, sorted by cut) followed cut by cut
    along the drive from 0 at its first cut: on each cut the median of its moves within
    ``reach_m`` of the move so far pulls it half way (a shift zone starts with a taper, which a
    4 m cut step follows in steps of a few cm; a cut with none keeps it). (k,) per cut."""
    out = np.zeros(k)
    ok = np.isfinite(move)
    cut, move = cut[ok], move[ok]
    bounds = np.searchsorted(cut, np.arange(k + 1)).tolist()
    m = 0.0
    for c in range(k):
        a, b = bounds[c], bounds[c + 1]
        if a < b:
            v = np.sort(move[a:b][np.abs(move[a:b] - m) <= reach_m])
            n = len(v)
            if n:  # np.median's value, without its overhead on a few values (a drive has ~1000 cuts)
                med = float(v[n // 2]) if n % 2 else float(0.5 * (v[n // 2 - 1] + v[n // 2]))
                m += 0.5 * (med - m)
        out[c] = m
    return out


@dataclass(frozen=True)
class DriveSide:
    """The drive's own side of ``drive_evidence``, which no map changes: its cuts every
    ``step_m`` (center (K, 2), unit tangent (K, 2), yaw (K,)) and its detections on them
    (``_on_cuts``: cut, lateral position, type), for cuts ``view_m`` to each side."""

    step_m: float
    view_m: float
    center: np.ndarray
    tangent: np.ndarray
    yaw: np.ndarray
    d_cut: np.ndarray
    d_s: np.ndarray
    d_t: np.ndarray

    def fits(self, config: ChangeConfig) -> bool:
        """Made with ``config``'s cuts."""
        return self.step_m == config.cut_step_m and self.view_m == config.view_m


def drive_side(drive: Drive, config: ChangeConfig = ChangeConfig()) -> DriveSide:
    """``drive``'s own side of its evidence (``DriveSide``); a drive of at least 2 poses."""
    dets = [d for d in drive.detections if len(d.points) >= 2]
    dsegs = segments_of([np.asarray(d.points, dtype=float) for d in dets])
    dtypes = np.array([int(d.type) for d in dets], dtype=np.int64)[dsegs.owner] if dets else np.zeros(0, np.int64)
    return _side(drive, dsegs, dtypes, config)


def side_of_lines(drive: Drive, lines: MapLines, config: ChangeConfig = ChangeConfig()) -> DriveSide:
    """``drive``'s side of its evidence with ``lines`` as its detections: the ``DriveSide`` that
    ``drive_side`` makes of the drive with the lines' features (``map_lines``) as detections, the
    same arrays, but the lines indexed once for every drive that takes them (``border_shift``:
    a rebuilt map seen from each drive through it) instead of every drive's cuts indexed and
    queried with every segment of them (``intersect_indexed``, the same pairs in the same order
    once sorted by cut)."""
    return _side(drive, lines.index, lines.types, config)


def _side(drive: Drive, lines: Segments | SegmentIndex, types: np.ndarray, config: ChangeConfig) -> DriveSide:
    """The drive's cuts and ``lines`` (``types`` per segment) on them, as its detections."""
    center, tangent, yaw = drive_cuts(drive, config.cut_step_m)
    d_cut, d_s, d_t = _on_cuts(center, tangent, config.view_m, lines, types)
    return DriveSide(config.cut_step_m, config.view_m, center, tangent, yaw, d_cut, d_s, d_t)


def drive_evidence(
    drive: Drive,
    lines: MapLines,
    places: Places,
    *,
    config: ChangeConfig = ChangeConfig(),
    side: DriveSide | None = None,
) -> list[PlaceEvidence]:
    """The evidence of ``drive`` against the map ``lines``, one record per place it crossed;
    ``side``: ``drive_side(drive, config)`` made before (else made here)."""
    if len(drive.xy) < 2 or len(lines.types) == 0:
        return []
    if side is None or not side.fits(config):
        side = drive_side(drive, config)
    center, tangent, yaw = side.center, side.tangent, side.yaw
    k = len(center)
    d_cut, d_s, d_t = side.d_cut, side.d_s, side.d_t
    m_cut, m_s, m_t = _on_cuts(center, tangent, config.view_m, lines.index, lines.types)
    keys = places.keys(center, yaw)
    ids = {key: i for i, key in enumerate(dict.fromkeys(keys))}
    place_of_cut = np.array([ids[key] for key in keys], dtype=np.int64)

    d_mark, m_mark = np.isin(d_t, _MARKINGS), np.isin(m_t, _MARKINGS)
    dm = np.flatnonzero(d_mark)
    mm = np.flatnonzero(m_mark)
    pi, pj, pr = _pairs(d_cut[dm], d_s[dm], m_cut[mm], m_s[mm], k, config.pair_max_m)
    db = np.flatnonzero(d_t == _BORDER)
    mb = np.flatnonzero(m_t == _BORDER)
    bi, _, br = _pairs(d_cut[db], d_s[db], m_cut[mb], m_s[mb], k, config.pair_max_m)
    pair_place = place_of_cut[d_cut[dm][pi]]
    border_place = place_of_cut[d_cut[db][bi]]
    drive_offset, _ = density_mode(pr, reach_m=config.pair_max_m, kernel_m=config.kernel_m)
    # The borders' offset over the whole drive picks the right one of two barriers side by side
    # (a divided road's median: 2.5 m apart); each place then looks only near it (drift is slow).
    drive_border = _border_offset(br, pr, config)

    # Border offset per place; a place with too few borders takes the mean of its neighbours
    # along the drive (within ``_ANCHOR_REACH`` places) that have enough: the drift is slow.
    n_places = len(ids)
    border_of = _by_place(border_place, n_places)
    pairs_of = _by_place(pair_place, n_places)
    borders = np.full(n_places, np.nan)
    for p in range(n_places):
        if np.isfinite(drive_border):
            b, n_b = density_mode(
                br[border_of(p)], reach_m=_BORDER_REACH_M, kernel_m=config.kernel_m, center=drive_border
            )
            if n_b >= config.min_border_pairs:
                borders[p] = b
    anchors = np.full(n_places, np.nan)
    offsets = np.full(n_places, np.nan)
    n_pairs = np.zeros(n_places, dtype=np.int64)
    on_borders = np.isfinite(borders)
    for p in range(n_places):
        near = borders[max(0, p - _ANCHOR_REACH) : p + _ANCHOR_REACH + 1]
        if on_borders[p]:
            anchors[p] = borders[p]
        elif np.isfinite(near).any():
            anchors[p] = float(np.nanmean(near))
        else:
            anchors[p] = drive_border if np.isfinite(drive_border) else drive_offset
    # A move near a lane's width is sought where the drive followed it along the road (the
    # markings' pairs farther apart than ``pair_max_m`` too), not near the anchor, where each
    # moved marking pairs with its neighbour's old place (3 m on 3.5 m lanes reads -0.5 m).
    lane = 2 * config.max_shift_m
    wi, _, wr = _pairs(d_cut[dm], d_s[dm], m_cut[mm], m_s[mm], k, config.pair_max_m + lane)
    w_cut = d_cut[dm][wi]
    w_move = wr - anchors[place_of_cut[w_cut]]
    ahead = _follow_move(w_cut, w_move, k, config.max_shift_m / 2)
    back = _follow_move(k - 1 - w_cut[::-1], w_move[::-1], k, config.max_shift_m / 2)[::-1]
    # From its start a drive that began inside a shift zone follows the alias (and then reads a
    # lane's move past the zone's end); from its end, one that ends inside. Where the two
    # disagree: the one that comes back to no move at its other end (most road did not move),
    # if only one does, else the one that pairs more of the drive's markings with the map's
    # (the alias leaves the outermost moved line and one old line unpaired).
    far = config.max_shift_m
    differ = np.abs(ahead - back) > far
    followed = ahead
    if differ.any() and (abs(ahead[-1]) <= far) != (abs(back[0]) <= far):
        followed = ahead if abs(ahead[-1]) <= far else back
    elif differ.any():
        lines_d, lines_m = (d_cut[dm], d_s[dm]), (m_cut[mm], m_s[mm])
        fit_a = _paired(anchors[place_of_cut] + ahead, lines_d, lines_m, config.match_m)[differ].sum()
        fit_b = _paired(anchors[place_of_cut] + back, lines_d, lines_m, config.match_m)[differ].sum()
        followed = ahead if fit_a >= fit_b else back
    wide_of = _by_place(place_of_cut[w_cut], n_places)
    cuts_of = _by_place(place_of_cut, n_places)
    for p in range(n_places):
        move = float(np.median(followed[cuts_of(p)])) if len(cuts_of(p)) else 0.0
        if abs(move) > config.max_shift_m and np.isfinite(anchors[p]):
            offsets[p], n_pairs[p] = density_mode(
                wr[wide_of(p)], reach_m=config.max_shift_m, kernel_m=config.kernel_m, center=float(anchors[p]) + move
            )
            continue
        # The markings' offset near the anchor: farther than half a lane a marking pairs with its
        # neighbour line.
        if np.isfinite(anchors[p]):
            offsets[p], n_pairs[p] = density_mode(
                pr[pairs_of(p)], reach_m=config.max_shift_m, kernel_m=config.kernel_m, center=float(anchors[p])
            )
    enough = n_pairs >= config.min_pairs
    displacement = np.where(enough, offsets - anchors, np.nan)
    # the drive's offset per cut (its place's): its markings against the map's after it
    o_cut = np.where(enough, offsets, np.where(np.isfinite(anchors), anchors, 0.0))[place_of_cut]
    # Type, negative and positive evidence, near the drive, after its offset: on every cut at
    # once (a cut lies in one place), counted per place.
    dsel = dm[np.abs(d_s[dm]) <= config.near_m]
    msel = mm[np.abs(m_s[mm] - o_cut[m_cut[mm]]) <= config.near_m]
    d_place, m_place = place_of_cut[d_cut[dsel]], place_of_cut[m_cut[msel]]
    n_drive_near = np.bincount(d_place, minlength=n_places)
    n_map_near = np.bincount(m_place, minlength=n_places)
    # nearest map marking on the same cut to each drive marking (after the offset)
    ti, tj, tr = _pairs(d_cut[dsel], d_s[dsel] + o_cut[d_cut[dsel]], m_cut[mm], m_s[mm], k, config.match_m)
    order = np.lexsort((np.abs(tr), ti))
    first = order[np.r_[True, ti[order][1:] != ti[order][:-1]]] if len(order) else order
    matched = np.zeros(len(dsel), dtype=bool)
    matched[ti[first]] = True
    wrong = np.zeros(len(dsel), dtype=bool)
    wrong[ti[first]] = d_t[dsel][ti[first]] != m_t[mm][tj[first]]
    n_typed = np.bincount(d_place[matched], minlength=n_places)
    n_wrong = np.bincount(d_place[wrong], minlength=n_places)
    ui, _, _ = _pairs(m_cut[msel], m_s[msel] - o_cut[m_cut[msel]], d_cut, d_s, k, config.match_m)
    seen = np.zeros(len(msel), dtype=bool)
    seen[ui] = True
    n_missed = n_map_near - np.bincount(m_place[seen], minlength=n_places)
    n_cuts = np.bincount(place_of_cut, minlength=n_places)
    out: list[PlaceEvidence] = []
    for key, p in ids.items():
        out.append(
            PlaceEvidence(
                drive_id=drive.drive_id,
                time_ns=drive.start_ns,
                key=key,
                n_cuts=int(n_cuts[p]),
                offset_m=float(offsets[p]),
                anchor_m=float(anchors[p]),
                anchored_on_borders=bool(on_borders[p]),
                displacement_m=float(displacement[p]),
                n_pairs=int(n_pairs[p]),
                n_typed=int(n_typed[p]),
                n_wrong_type=int(n_wrong[p]),
                n_map_near=int(n_map_near[p]),
                n_missed=int(n_missed[p]),
                n_drive_near=int(n_drive_near[p]),
                n_extra=int(n_drive_near[p] - n_typed[p]),
            )
        )
    return out


def fleet_evidence(
    drives: Sequence[Drive], hdmap: HDMap, places: Places, *, config: ChangeConfig
) -> list[PlaceEvidence]:
    """``drive_evidence`` of every drive against ``hdmap``."""
    lines = map_lines(hdmap)
    return unwrap_aliases([e for d in drives for e in drive_evidence(d, lines, places, config=config)], config)


def unwrap_aliases(evidence: list[PlaceEvidence], config: ChangeConfig) -> list[PlaceEvidence]:
    """``evidence`` with the aliases of a lane-sized move read as the move: per place, where at
    least 2 drives read a move beyond half a lane (``max_shift_m``; nothing else reads one)
    within ``_ALIAS_M`` of their median M, every drive there from the first of them on that
    reads M's alias (M less a lane, within ``_ALIAS_M``) reads M: it missed the taper it would
    have followed the move on. Drives after a change that disagree lose the change."""
    lane, far = 2 * config.max_shift_m, config.max_shift_m
    by_key: dict[PlaceKey, list[int]] = {}
    for i, e in enumerate(evidence):
        if math.isfinite(e.displacement_m):
            by_key.setdefault(e.key, []).append(i)
    out = list(evidence)
    for idx in by_key.values():
        big = [i for i in idx if abs(evidence[i].displacement_m) > far]
        if len(big) < 2:
            continue
        m = float(np.median([evidence[i].displacement_m for i in big]))
        agree = [i for i in big if abs(evidence[i].displacement_m - m) <= _ALIAS_M]
        if len(agree) < 2:
            continue
        t0 = min(evidence[i].time_ns for i in agree)
        alias = m - math.copysign(lane, m)
        for i in idx:
            e = evidence[i]
            if e.time_ns >= t0 and abs(e.displacement_m - alias) <= _ALIAS_M:
                step = math.copysign(lane, m)
                out[i] = replace(e, offset_m=e.offset_m + step, displacement_m=e.displacement_m + step)
    return out
