"""Pure, vectorised array math shared by the pipeline stages.

Everything here works on numpy arrays in the metric map frame; nothing knows about drives or maps.
Polylines are (N, 2) float arrays. "Left" is +90 deg from a heading (ENU yaw, counter-clockwise).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np

__all__ = [
    "arc_length",
    "polyline_length",
    "segment_headings",
    "point_headings",
    "unit_tangents",
    "turn_left",
    "left_normal",
    "true_runs",
    "interp_angle",
    "wrap_angle",
    "heading_frame",
    "resample_by_distance",
    "resample_evenly",
    "dense_points",
    "rdp_mask_many",
    "split_long_segments",
    "cut_segment_intersections",
    "nearest_on_same_cut",
]


def arc_length(xy: np.ndarray) -> np.ndarray:
    """Cumulative distance along a polyline.

    Args:
        xy: (N, 2) points [m].

    Returns:
        (N,) distance from the first point [m]; s[0] = 0.
    """
    xy = np.asarray(xy, dtype=float)
    if len(xy) == 0:
        return np.zeros(0)
    d = np.hypot(*np.diff(xy, axis=0).T) if len(xy) > 1 else np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(d)])


def polyline_length(xy: np.ndarray) -> float:
    """Total length of a (N, 2) polyline [m]."""
    xy = np.asarray(xy, dtype=float)
    if len(xy) < 2:
        return 0.0
    return float(np.hypot(*np.diff(xy, axis=0).T).sum())


def segment_headings(xy: np.ndarray) -> np.ndarray:
    """(N-1,) ENU yaw of each segment of a (N, 2) polyline [rad]."""
    d = np.diff(np.asarray(xy, dtype=float), axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def point_headings(xy: np.ndarray) -> np.ndarray:
    """(N,) ENU yaw of a (N >= 2, 2) polyline at each point, along its tangent (central
    differences inside, one-sided at the ends: ``np.gradient``) [rad]."""
    t = np.gradient(np.asarray(xy, dtype=float), axis=0)
    return np.arctan2(t[:, 1], t[:, 0])


def unit_tangents(xy: np.ndarray) -> np.ndarray:
    """(N, 2) unit tangent of a (N, 2) polyline at each point (``np.gradient``, as
    ``point_headings``); zero where it stands still, and for a single point."""
    xy = np.asarray(xy, dtype=float)
    t = np.gradient(xy, axis=0) if len(xy) > 1 else np.zeros_like(xy)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)


def turn_left(v: np.ndarray) -> np.ndarray:
    """(N, 2) the vectors ``v`` (N, 2) turned +90 deg: the left normals of unit tangents."""
    v = np.asarray(v, dtype=float)
    return np.stack([-v[:, 1], v[:, 0]], axis=1)


def left_normal(heading: float | np.ndarray) -> np.ndarray:
    """Unit normal pointing left of an ENU heading [rad]: (2,) for a scalar, else (N, 2)."""
    h = np.asarray(heading, dtype=float)
    return np.stack([-np.sin(h), np.cos(h)], axis=-1)


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index ranges of the True runs of a boolean (N,) mask, in order."""
    m = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]]).astype(np.int8)
    d = np.diff(m)
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def heading_frame(heading_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vector along a heading and its left normal: two (2,) arrays."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return np.array([c, s]), np.array([-s, c])


def interp_angle(x: np.ndarray, xp: np.ndarray, angle_p: np.ndarray) -> np.ndarray:
    """Linear interpolation of angles [rad] (through the unwrapped sequence), result wrapped."""
    return wrap_angle(np.interp(x, xp, np.unwrap(np.asarray(angle_p, dtype=float))))


def resample_by_distance(xy: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step_m`` along a polyline.

    Args:
        xy: (N, 2) polyline [m], N >= 2.
        step_m: spacing [m] > 0.

    Returns:
        (points (K, 2), s (K,)) with s = 0, step, 2 step, ... <= total length.
    """
    s = arc_length(xy)
    # Duplicate points make s non-increasing; np.interp needs increasing xp.
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    s, xy = s[keep], np.asarray(xy, dtype=float)[keep]
    if len(s) < 2:
        return xy[:1].copy(), np.zeros(1)
    q = np.arange(0.0, s[-1] + 1e-9, step_m)
    pts = np.stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])], axis=1)
    return pts, q


def resample_evenly(xy: np.ndarray, max_step_m: float) -> np.ndarray:
    """Points spaced evenly along a polyline, both ends kept, at most ``max_step_m`` apart.

    Unlike ``resample_by_distance`` (a fixed step from the start, the last point dropped unless
    it falls on the grid) the spacing is the polyline's length over ceil(length / max_step_m).

    Args:
        xy: (N, 2) polyline [m].
        max_step_m: largest spacing [m] > 0.

    Returns:
        (K, 2) points, K >= 2; a polyline of fewer than two distinct points gives its first
        point alone (K = 1, or 0 for no points).
    """
    xy = np.asarray(xy, dtype=float)
    if len(xy) < 2:
        return xy.copy()
    s = arc_length(xy)
    # Duplicate points make s non-increasing; np.interp needs increasing xp.
    keep = np.concatenate([[True], np.diff(s) > 1e-9])
    s, xy = s[keep], xy[keep]
    if len(s) < 2:
        return xy[:1].copy()
    q = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / max_step_m)) + 1))
    return np.stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])], axis=1)


def dense_points(lines: Iterable[np.ndarray], max_step_m: float) -> np.ndarray:
    """(K, 2) the points of every polyline of ``lines`` at most ``max_step_m`` apart along it
    (:func:`resample_evenly`, both ends kept); polylines of no length are left out."""
    out = [np.zeros((0, 2))]
    for xy in lines:
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if len(xy) >= 2 and polyline_length(xy) > 0:
            out.append(resample_evenly(xy, max_step_m))
    return np.concatenate(out)


def rdp_mask_many(xy: np.ndarray, starts: np.ndarray, epsilon_m: float) -> np.ndarray:
    """Ramer-Douglas-Peucker on many polylines at once.

    The polylines are stored back to back in ``xy``; polyline ``i`` is
    ``xy[starts[i]:starts[i+1]]`` (the last one runs to the end). All open intervals are refined
    together, one numpy pass per recursion level, instead of one Python call per polyline.

    Args:
        xy: (N, 2) points of all polylines [m].
        starts: (P,) increasing start indices, starts[0] == 0; every polyline has >= 2 points.
        epsilon_m: RDP tolerance [m]; points closer than this to the simplified line are dropped.

    Returns:
        (N,) bool mask of the points to keep (first and last point of every polyline kept).
    """
    xy = np.asarray(xy, dtype=float)
    n = len(xy)
    keep = np.zeros(n, dtype=bool)
    if n == 0:
        return keep
    starts = np.asarray(starts, dtype=np.int64)
    ends = np.concatenate([starts[1:], [n]]) - 1
    keep[starts] = True
    keep[ends] = True
    lo, hi = starts.copy(), ends.copy()
    while True:
        open_ = hi - lo > 1
        lo, hi = lo[open_], hi[open_]
        if len(lo) == 0:
            return keep
        inner = hi - lo - 1
        owner = np.repeat(np.arange(len(lo)), inner)
        first = np.concatenate([[0], np.cumsum(inner)[:-1]])
        idx = lo[owner] + 1 + (np.arange(len(owner)) - first[owner])
        # Distance to the chord = |cross| / chord length; the length is one per interval, so the
        # farthest point is the largest |cross| and the test is |cross| > eps * length. A chord of
        # length 0 (a closed polyline) measures the distance to its end point instead.
        ab_i = xy[hi] - xy[lo]
        lab = np.hypot(ab_i[:, 0], ab_i[:, 1])
        ab = ab_i[owner]
        ap = xy[idx] - xy[lo[owner]]
        dist = np.abs(ab[:, 0] * ap[:, 1] - ab[:, 1] * ap[:, 0])
        flat = lab <= 1e-12
        if flat.any():
            on = flat[owner]
            dist[on] = np.hypot(ap[on, 0], ap[on, 1])
        # Per interval (its inner points are contiguous here): the farthest one, first on ties.
        dmax = np.maximum.reduceat(dist, first)
        pos = np.arange(len(dist))
        firsts = np.minimum.reduceat(np.where(dist == dmax[owner], pos, len(dist)), first)
        split = dmax > epsilon_m * np.where(flat, 1.0, lab)
        mid = idx[firsts][split]
        keep[mid] = True
        # interleaved, so the intervals stay in point order and the gathers above run through
        # memory in order
        lo = np.stack([lo[split], mid], axis=1).ravel()
        hi = np.stack([mid, hi[split]], axis=1).ravel()


def split_long_segments(
    xy: np.ndarray, starts: np.ndarray, max_len_m: float, *, max_pieces: int = 1 << 20
) -> tuple[np.ndarray, np.ndarray]:
    """Insert points so that no segment of any polyline is longer than ``max_len_m``.

    Args:
        xy: (N, 2) back-to-back polylines, ``starts`` as in :func:`rdp_mask_many`.
        max_len_m: longest allowed segment [m].
        max_pieces: no segment is split into more pieces than this (nor is a segment of non-finite
            length split): a defective point far away must not size the output (one point at 1e12 m
            would ask for 1e11 points).

    Returns:
        (xy_out (N', 2), starts_out (P,)).
    """
    xy = np.asarray(xy, dtype=float)
    n = len(xy)
    if n == 0:
        return xy.copy(), np.asarray(starts, dtype=np.int64).copy()
    seg_len = np.hypot(*np.diff(xy, axis=0).T)
    last = np.zeros(n, dtype=bool)
    last[np.asarray(starts[1:], dtype=np.int64) - 1] = True
    last[-1] = True
    # pieces[i]: how many sub-segments the segment starting at point i becomes (0 after a last point).
    pieces = np.zeros(n, dtype=np.int64)
    with np.errstate(invalid="ignore", over="ignore"):
        want = np.ceil(seg_len / max_len_m)
    pieces[:-1] = np.where(np.isfinite(want), np.clip(want, 1, max(1, int(max_pieces))), 1).astype(np.int64)
    pieces[last] = 0
    count = np.where(last, 1, pieces)  # points emitted per input point
    owner = np.repeat(np.arange(n), count)
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    k = np.arange(len(owner)) - first[owner]
    nxt = np.minimum(owner + 1, n - 1)
    frac = np.where(last[owner], 0.0, k / np.maximum(pieces[owner], 1))
    out = xy[owner] + frac[:, None] * (xy[nxt] - xy[owner])
    new_starts = first[np.asarray(starts, dtype=np.int64)]
    return out, new_starts


def cut_segment_intersections(
    cut_origin: np.ndarray,
    cut_dir: np.ndarray,
    half_len_m: np.ndarray,
    seg_a: np.ndarray,
    seg_b: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersect cut lines with segments, pairwise.

    Cut line q runs through ``cut_origin[q]`` along the unit vector ``cut_dir[q]`` over the
    parameter range [-half_len_m[q], +half_len_m[q]]. All arrays are given per pair (row j is one
    cut line / segment pair), so callers broadcast candidate pairs beforehand.

    Args:
        cut_origin: (P, 2) [m]; cut_dir: (P, 2) unit vectors; half_len_m: (P,) [m].
        seg_a, seg_b: (P, 2) segment end points [m].

    Returns:
        (hit (P,) bool, t (P,) position along the cut [m], u (P,) position along the segment in
        [0, 1]). A segment end point on the cut counts for u in [0, 1), so a polyline crossing
        exactly at a vertex is sampled once. Parallel pairs never hit.
    """
    d = seg_b - seg_a
    w = seg_a - cut_origin
    den = cut_dir[:, 0] * d[:, 1] - cut_dir[:, 1] * d[:, 0]
    ok = np.abs(den) > 1e-12
    den_s = np.where(ok, den, 1.0)
    t = (w[:, 0] * d[:, 1] - w[:, 1] * d[:, 0]) / den_s
    u = (w[:, 0] * cut_dir[:, 1] - w[:, 1] * cut_dir[:, 0]) / den_s
    hit = ok & (u >= 0.0) & (u < 1.0) & (np.abs(t) <= half_len_m)
    return hit, t, u


def nearest_on_same_cut(
    q_cut: np.ndarray, q_s: np.ndarray, r_cut: np.ndarray, r_s: np.ndarray, *, width: float
) -> tuple[np.ndarray, np.ndarray]:
    """For each query point, the nearest reference point on the same cut.

    Both sets are keyed ``cut * width + s`` (``width`` > the longest cut) and searched by bisection.
    Returns (Q,) index into the reference set (-1 if the cut has none) and (Q,) distance (inf).
    """
    idx = np.full(len(q_cut), -1, dtype=np.int64)
    dist = np.full(len(q_cut), np.inf)
    if len(q_cut) == 0 or len(r_cut) == 0:
        return idx, dist
    r_key = r_cut * width + r_s
    order = np.argsort(r_key, kind="stable")
    sorted_key = r_key[order]
    pos = np.searchsorted(sorted_key, q_cut * width + q_s)
    for cand in (pos - 1, pos):
        valid = (cand >= 0) & (cand < len(order))
        c = order[np.clip(cand, 0, len(order) - 1)]
        valid &= r_cut[c] == q_cut
        d = np.where(valid, np.abs(r_s[c] - q_s), np.inf)
        better = d < dist
        idx[better] = c[better]
        dist[better] = d[better]
    return idx, dist
