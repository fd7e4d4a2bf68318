"""Cut lines for the evaluator (Sec. VII): reference cuts along ground-truth lanes, limited to the
carriageway, de-duplicated where routes and lanes overlap, and the vectorised intersection of many
cut lines with many polyline segments.

Conventions: a cut ``k`` is the segment ``center[k] + s * normal[k]`` for ``s`` in
``[lo[k], hi[k]]`` (``lo <= 0 <= hi``), where ``normal`` is the left normal of the forward unit
``tangent`` (driving direction of the reference lane). ``s`` is the signed lateral coordinate along
the cut, + = left [m].
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely

from hdmap_core.evaluation.config import EvalConfig
from hdmap_core.geometry import nearest_on_same_cut, turn_left
from hdmap_core.groundtruth import GroundTruth
from hdmap_core.model import FeatureType

__all__ = [
    "Cuts",
    "Segments",
    "CutPoints",
    "segments_of",
    "intersect_cuts",
    "SegmentIndex",
    "index_segments",
    "intersect_indexed",
    "reference_cuts",
    "configured_cuts",
    "points_on_cuts",
    "nearest_on_same_cut",
    "nearest_same_type",
]

_EPS = 1e-9
_CHUNK = 200_000  # segments per spatial-index query (bounds the memory of candidate pairs)
_JOIN_TOL_M = 0.05  # successor gaps in the shared maps are <= 0.002 m


@dataclass(frozen=True)
class Cuts:
    """K cut lines.

    Attributes:
        center: (K, 2) reference point on the reference lane centerline [m].
        tangent: (K, 2) unit forward direction of the reference lane.
        normal: (K, 2) unit left normal of ``tangent``.
        lo: (K,) right end of the cut, <= 0 [m].
        hi: (K,) left end of the cut, >= 0 [m].
        station_m: (K,) distance along the (de-duplicated) reference, in evaluation order [m].
    """

    center: np.ndarray
    tangent: np.ndarray
    normal: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    station_m: np.ndarray

    def __len__(self) -> int:
        return len(self.center)

    def take(self, index: np.ndarray) -> Cuts:
        """The cuts at ``index`` (bool mask or int indices); stations are kept."""
        return Cuts(*(np.asarray(getattr(self, f))[index] for f in self.__dataclass_fields__))


@dataclass(frozen=True)
class Segments:
    """The M segments of a set of polylines, flattened.

    Attributes:
        a, b: (M, 2) segment start and end [m].
        owner: (M,) index of the polyline each segment belongs to.
        vertex: (M,) index of the segment start within its polyline.
        last: (M,) True for the last segment of its polyline (closed at its end).
    """

    a: np.ndarray
    b: np.ndarray
    owner: np.ndarray
    vertex: np.ndarray
    last: np.ndarray

    def __len__(self) -> int:
        return len(self.a)


def segments_of(polylines: Sequence[np.ndarray]) -> Segments:
    """Flatten polylines ((N_i, 2) arrays, N_i >= 2) into their segments; zero-length segments dropped."""
    a, b, owner, vertex, last = [], [], [], [], []
    for i, pts in enumerate(polylines):
        n = len(pts) - 1
        if n < 1:
            continue
        a.append(pts[:-1])
        b.append(pts[1:])
        owner.append(np.full(n, i, dtype=np.int64))
        vertex.append(np.arange(n, dtype=np.int64))
        lst = np.zeros(n, dtype=bool)
        lst[-1] = True
        last.append(lst)
    if not a:
        z2 = np.zeros((0, 2))
        zi = np.zeros(0, dtype=np.int64)
        return Segments(z2, z2, zi, zi, np.zeros(0, dtype=bool))
    seg = Segments(*(np.concatenate(x) for x in (a, b, owner, vertex, last)))
    keep = np.linalg.norm(seg.b - seg.a, axis=1) > _EPS
    if keep.all():
        return seg
    # A dropped zero-length last segment hands "last" to its predecessor.
    last_arr = seg.last.copy()
    drop_last = ~keep & seg.last
    idx = np.flatnonzero(drop_last) - 1
    ok = idx >= 0
    last_arr[idx[ok]] |= seg.owner[idx[ok]] == seg.owner[idx[ok] + 1]
    return Segments(seg.a[keep], seg.b[keep], seg.owner[keep], seg.vertex[keep], last_arr[keep])


def intersect_cuts(
    center: np.ndarray,
    normal: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    segs: Segments,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Intersect K cut lines with M segments at once.

    A spatial index (shapely STRtree over the cut lines, bounding boxes only) yields the candidate
    pairs; the exact intersection is solved with numpy, in chunks of segments to bound memory. A
    segment's parameter ``u`` is taken half-open, [0, 1), except for the last segment of a
    polyline, so a polyline crossing a cut at a vertex counts once.

    Args:
        center, normal: (K, 2) cut reference points and unit left normals.
        lo, hi: (K,) cut extent along the normal [m].
        segs: the segments.

    Returns:
        cut_idx (P,), seg_idx (P,), s (P,) lateral coordinate along the cut [m], u (P,) parameter
        along the segment in [0, 1]; ordered by segment.
    """
    out: list[tuple[np.ndarray, ...]] = []
    if len(center) and len(segs):
        p0 = center + lo[:, None] * normal
        p1 = center + hi[:, None] * normal
        tree = shapely.STRtree(shapely.linestrings(np.stack([p0, p1], axis=1)))
        for start in range(0, len(segs), _CHUNK):
            sl = slice(start, start + _CHUNK)
            seg_lines = shapely.linestrings(np.stack([segs.a[sl], segs.b[sl]], axis=1))
            si, ci = tree.query(seg_lines)
            out.append(_solve(center, normal, lo, hi, segs, ci, si + start))
    if not out:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
    return tuple(np.concatenate(parts) for parts in zip(*out))  # type: ignore[return-value]


@dataclass(frozen=True)
class SegmentIndex:
    """Segments with a spatial index over them (bounding boxes), built once and cut many times
    (``intersect_indexed``): a map compared with every drive of a fleet."""

    segments: Segments
    tree: shapely.STRtree

    def __len__(self) -> int:
        return len(self.segments)


def index_segments(segs: Segments) -> SegmentIndex:
    """``segs`` with their spatial index."""
    return SegmentIndex(segs, shapely.STRtree(shapely.linestrings(np.stack([segs.a, segs.b], axis=1))))


def intersect_indexed(
    center: np.ndarray,
    normal: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    index: SegmentIndex,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``intersect_cuts`` against indexed segments: the same intersections (the same candidate
    pairs, bounding box against bounding box, solved alike), ordered by cut, then segment.

    The cuts query the segments' index, so the cost grows with the cuts and what lies near them,
    not with every segment (``intersect_cuts`` builds an index of the cuts and queries it with
    every segment).
    """
    segs = index.segments
    if not len(center) or not len(segs):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
    p0 = center + lo[:, None] * normal
    p1 = center + hi[:, None] * normal
    ci, si = index.tree.query(shapely.linestrings(np.stack([p0, p1], axis=1)))
    order = np.lexsort((si, ci))
    return _solve(center, normal, lo, hi, segs, ci[order], si[order])


def _solve(
    center: np.ndarray,
    normal: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    segs: Segments,
    ci: np.ndarray,
    si: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact intersection of candidate pairs (cut ci, segment si): c + s n = a + u (b - a)."""
    c, n = center[ci], normal[ci]
    a, d = segs.a[si], segs.b[si] - segs.a[si]
    ac = a - c
    denom = n[:, 0] * d[:, 1] - n[:, 1] * d[:, 0]
    ok = np.abs(denom) > _EPS
    denom = np.where(ok, denom, 1.0)
    s = (ac[:, 0] * d[:, 1] - ac[:, 1] * d[:, 0]) / denom
    u = (ac[:, 0] * n[:, 1] - ac[:, 1] * n[:, 0]) / denom
    u_ok = (u >= 0.0) & ((u < 1.0) | (segs.last[si] & (u <= 1.0 + 1e-12)))
    ok &= u_ok & (s >= lo[ci] - 1e-9) & (s <= hi[ci] + 1e-9)
    return ci[ok], si[ok], s[ok], np.clip(u[ok], 0.0, 1.0)


def _unit(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(norm > _EPS, norm, 1.0)


def _reference_lines(gt: GroundTruth) -> list[tuple[np.ndarray, np.ndarray]]:
    """Contiguous reference lines: (N, 2) joined lane centerlines and (N - 1,) highway flag per segment.

    Routes are split where consecutive lanes do not meet (lane changes), so no reference segment
    crosses lanes diagonally. Without routes every lane is its own reference line.
    """
    seqs = [r.lanes for r in gt.routes] if gt.routes else [(lid,) for lid in gt.lanes]
    lines = []
    for lane_ids in seqs:
        pts: list[np.ndarray] = []
        flags: list[np.ndarray] = []
        for lid in lane_ids:
            lane = gt.lanes[lid]
            cl = np.asarray(lane.centerline, dtype=float)
            if pts and np.linalg.norm(cl[0] - pts[-1][-1]) > _JOIN_TOL_M:
                lines.append(_join(pts, flags))
                pts, flags = [], []
            if pts:
                cl = cl[1:]
            pts.append(cl)
            flags.append(np.full(len(cl), lane.highway))
        if pts:
            lines.append(_join(pts, flags))
    return [ln for ln in lines if len(ln[0]) >= 2]


def _join(pts: list[np.ndarray], flags: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    p = np.concatenate(pts)
    f = np.concatenate(flags)
    # Segment j (p[j] -> p[j+1]) belongs to the lane of its end point.
    return p, f[1:]


def _candidates(gt: GroundTruth, *, step_m: float, highway_only: bool) -> tuple[np.ndarray, np.ndarray]:
    """Stations every ``step_m`` along each reference line: (C, 2) points and (C, 2) unit tangents."""
    centers, tangents = [], []
    for pts, hw in _reference_lines(gt):
        seg_len = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg_len)])
        if cum[-1] < step_m / 2:
            continue
        st = np.arange(step_m / 2, cum[-1], step_m)
        j = np.clip(np.searchsorted(cum, st, side="right") - 1, 0, len(seg_len) - 1)
        good = seg_len[j] > _EPS
        if highway_only:
            good &= hw[j]
        j, st = j[good], st[good]
        frac = (st - cum[j]) / seg_len[j]
        d = pts[j + 1] - pts[j]
        centers.append(pts[j] + frac[:, None] * d)
        tangents.append(_unit(d))
    if not centers:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(centers), np.concatenate(tangents)


def _border_extents(
    center: np.ndarray,
    tangent: np.ndarray,
    border_segs: Segments,
    *,
    max_half_m: float,
    margin_m: float,
    cos_min: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cut ends: the first road border on each side plus ``margin_m``, at most ``max_half_m``.

    Borders crossing the cut at a steep angle (|cos| < ``cos_min``, e.g. an overpass) are ignored.
    """
    k = len(center)
    normal = turn_left(tangent)
    full = np.full(k, max_half_m)
    ci, si, s, _ = intersect_cuts(center, normal, -full, full, border_segs)
    seg_dir = _unit(border_segs.b[si] - border_segs.a[si])
    par = np.abs((seg_dir * tangent[ci]).sum(axis=1)) >= cos_min
    ci, s = ci[par], s[par]
    hi = full.copy()
    lo = -full.copy()
    left = s > 0
    np.minimum.at(hi, ci[left], s[left] + margin_m)
    np.maximum.at(lo, ci[~left], s[~left] - margin_m)
    return np.clip(lo, -max_half_m, 0.0), np.clip(hi, 0.0, max_half_m)


def _deduplicate(
    center: np.ndarray,
    tangent: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    *,
    step_m: float,
    cos_heading: float,
) -> np.ndarray:
    """Greedy, in reference order: drop a candidate that an earlier kept cut already covers.

    Cut j covers candidate i when their headings differ by less than the dedup angle and i lies in
    j's rectangle: within step_m / 2 of j along j's tangent (the same cross section) and within j's
    extent across it. Returns the (C,) bool mask of kept candidates.
    """
    c = len(center)
    keep = np.ones(c, dtype=bool)
    if c < 2:
        return keep
    half = step_m / 2 + 1e-6
    normal = turn_left(tangent)
    corners = np.stack(
        [
            center - half * tangent + lo[:, None] * normal,
            center + half * tangent + lo[:, None] * normal,
            center + half * tangent + hi[:, None] * normal,
            center - half * tangent + hi[:, None] * normal,
        ],
        axis=1,
    )
    tree = shapely.STRtree(shapely.polygons(corners))
    i, j = tree.query(shapely.points(center))  # bounding boxes; the exact test follows in numpy
    d = center[i] - center[j]
    along = np.abs((d * tangent[j]).sum(axis=1))
    across = (d * normal[j]).sum(axis=1)
    inside = (along <= half) & (across >= lo[j] - 1e-9) & (across <= hi[j] + 1e-9)
    covers = inside & (j < i) & ((tangent[i] * tangent[j]).sum(axis=1) >= cos_heading)
    i, j = i[covers], j[covers]
    if len(i) == 0:
        return keep
    # The greedy pass, vectorised as a fixed point: a candidate is dropped as soon as one of its
    # (earlier) coverers is kept, and kept once all its coverers are dropped. The earliest
    # undecided candidate is always decidable, so every round makes progress.
    unknown, kept, dropped = 0, 1, 2
    status = np.where(np.bincount(i, minlength=c) > 0, unknown, kept)
    while True:
        undecided = status == unknown
        if not undecided.any():
            break
        n_kept = np.bincount(i, weights=status[j] == kept, minlength=c)
        n_open = np.bincount(i, weights=status[j] == unknown, minlength=c)
        status = np.where(undecided & (n_kept > 0), dropped, status)
        status = np.where(undecided & (n_kept == 0) & (n_open == 0), kept, status)
    return status == kept


def reference_cuts(
    gt: GroundTruth,
    *,
    step_m: float,
    highway_only: bool,
    max_half_m: float,
    margin_m: float,
    cos_feature: float,
    cos_dedup: float,
) -> Cuts:
    """The evaluator's cut lines along the ground truth's route centerlines (see ``evaluate_map``).

    Stations every ``step_m`` along each route's lane centerlines (lanes with ``highway`` only
    unless ``highway_only`` is False), each cut limited to the carriageway by the first ground-truth
    road border on each side (+ ``margin_m``, at most ``max_half_m``), then de-duplicated so that
    every cross section of a carriageway is evaluated once although several routes and lanes pass it.
    """
    center, tangent = _candidates(gt, step_m=step_m, highway_only=highway_only)
    borders = segments_of([f.points for f in gt.features if f.type == FeatureType.ROAD_BORDER])
    lo, hi = _border_extents(center, tangent, borders, max_half_m=max_half_m, margin_m=margin_m, cos_min=cos_feature)
    keep = _deduplicate(center, tangent, lo, hi, step_m=step_m, cos_heading=cos_dedup)
    center, tangent, lo, hi = center[keep], tangent[keep], lo[keep], hi[keep]
    station = np.arange(len(center), dtype=float) * step_m
    return Cuts(center, tangent, turn_left(tangent), lo, hi, station)


# --------------------------------------------------------------------------------------------
# Points on cuts and matching


@dataclass(frozen=True)
class CutPoints:
    """P intersection points of polylines with cuts."""

    cut: np.ndarray  # (P,) cut index
    s: np.ndarray  # (P,) lateral coordinate on the cut, + = left [m]
    owner: np.ndarray  # (P,) polyline index
    vertex: np.ndarray  # (P,) segment start vertex within the polyline
    u: np.ndarray  # (P,) parameter along that segment


def configured_cuts(gt: GroundTruth, config: EvalConfig, *, cos_feature: float | None = None) -> Cuts:
    """``reference_cuts`` of ``gt`` with the settings of ``config`` (``cos_feature``: the cosine of
    ``config.max_feature_angle_deg`` unless given)."""
    if cos_feature is None:
        cos_feature = math.cos(math.radians(config.max_feature_angle_deg))
    return reference_cuts(
        gt,
        step_m=config.step_m,
        highway_only=config.highway_only,
        max_half_m=config.max_half_length_m,
        margin_m=config.border_margin_m,
        cos_feature=cos_feature,
        cos_dedup=math.cos(math.radians(config.dedup_heading_deg)),
    )


def points_on_cuts(cuts: Cuts, polylines: Sequence[np.ndarray], *, cos_min: float) -> CutPoints:
    """Where the polylines cross the cuts, keeping segments running with the cut's direction."""
    segs = segments_of(polylines)
    ci, si, s, u = intersect_cuts(cuts.center, cuts.normal, cuts.lo, cuts.hi, segs)
    d = segs.b[si] - segs.a[si]
    cos = (d * cuts.tangent[ci]).sum(axis=1) / np.linalg.norm(d, axis=1)
    ok = cos >= cos_min
    return CutPoints(ci[ok], s[ok], segs.owner[si][ok], segs.vertex[si][ok], u[ok])


def nearest_same_type(
    q_cut: np.ndarray,
    q_s: np.ndarray,
    q_type: np.ndarray,
    r_cut: np.ndarray,
    r_s: np.ndarray,
    r_type: np.ndarray,
    *,
    width: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``nearest_on_same_cut`` restricted to reference points of the query point's type."""
    idx = np.full(len(q_cut), -1, dtype=np.int64)
    dist = np.full(len(q_cut), np.inf)
    for t in np.unique(q_type):
        qm = np.flatnonzero(q_type == t)
        rm = np.flatnonzero(r_type == t)
        i, d = nearest_on_same_cut(q_cut[qm], q_s[qm], r_cut[rm], r_s[rm], width=width)
        ok = i >= 0
        idx[qm[ok]] = rm[i[ok]]
        dist[qm] = d
    return idx, dist
