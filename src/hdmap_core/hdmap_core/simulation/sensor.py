"""Detection model of the fleet simulator (``simulate.py``): what a drive's sensors report.

For one drive, given its true poses, it finds the ground-truth feature points beside the path
(a grid lookup, then the nearest pose by KD-tree), keeps those of the ego carriageway (and the
opposite median barrier), decides visibility by lateral band with on/off blocks along each
feature, misclassifies stretches, cuts the visible runs into connected polylines, resamples them,
adds measurement noise and moves every point by the drive's pose error. All vectorised over the
drive's points; ``docs/simulator.md`` describes the model and every parameter.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter1d
from scipy.signal import lfilter
from scipy.spatial import cKDTree

from hdmap_core.geometry import arc_length, left_normal, unit_tangents
from hdmap_core.groundtruth import GroundTruth
from hdmap_core.model import Detection, FeatureType
from hdmap_core.simulation.config import SimConfig

__all__ = [
    "FeatureIndex",
    "feature_index",
    "detections",
    "seen_per_feature",
    "false_positives",
    "smoothstep",
    "gauss_markov",
]

_MARKINGS = (int(FeatureType.SOLID), int(FeatureType.DASHED))
_BORDER = int(FeatureType.ROAD_BORDER)
_NONE_SEEN = np.zeros(0, dtype=np.int64)


def smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def gauss_markov(n: int, step_m: float, sigma: float, corr_m: float, rng: np.random.Generator) -> np.ndarray:
    """(n,) stationary first-order Gauss-Markov sequence with std ``sigma`` and correlation
    length ``corr_m`` at ``step_m`` spacing (white for corr_m = 0)."""
    w = rng.standard_normal(n)
    if sigma <= 0 or n == 0:
        return np.zeros(n)
    phi = float(np.exp(-step_m / corr_m)) if corr_m > 0 else 0.0
    e = sigma * np.sqrt(1.0 - phi * phi) * w
    e[0] = sigma * w[0]
    return lfilter([1.0], [1.0, -phi], e)


# ------------------------------------------------------------------------------ features


_CELL_M = 8.0  # grid cell of the feature-point lookup


def _cell_ids(xy: np.ndarray) -> np.ndarray:
    c = np.floor(xy / _CELL_M).astype(np.int64) + (1 << 20)
    return c[:, 0] * (1 << 21) + c[:, 1]


@dataclass(frozen=True)
class FeatureIndex:
    """All ground-truth feature points: xy (P, 2), feature index fid (P,), point index pid (P,),
    arc length s (P,) along its feature, unit tangent (P, 2) in the feature's order, type (P,);
    a grid lookup: point indices ``order`` sorted by their cell id ``cells``."""

    xy: np.ndarray
    fid: np.ndarray
    pid: np.ndarray
    s: np.ndarray
    tangent: np.ndarray
    type: np.ndarray
    order: np.ndarray
    cells: np.ndarray


def feature_index(gt: GroundTruth) -> FeatureIndex:
    feats = [f for f in gt.features if len(f.points) >= 2]
    if not feats:
        z = np.zeros(0, np.int64)
        return FeatureIndex(np.zeros((0, 2)), z, z, np.zeros(0), np.zeros((0, 2)), z, z, z)
    xy = np.concatenate([f.points for f in feats])
    fid = np.concatenate([np.full(len(f.points), i) for i, f in enumerate(feats)])
    pid = np.concatenate([np.arange(len(f.points)) for f in feats])
    s = np.concatenate([arc_length(f.points) for f in feats])
    tan = np.concatenate([unit_tangents(f.points) for f in feats])
    typ = np.concatenate([np.full(len(f.points), int(f.type)) for f in feats])
    cells = _cell_ids(xy)
    order = np.argsort(cells, kind="stable")
    return FeatureIndex(xy, fid, pid, s, tan, typ, order, cells[order])


def seen_per_feature(gt: GroundTruth, idx: FeatureIndex, count: np.ndarray) -> dict[int, np.ndarray]:
    """Per ground-truth feature id, (N_f,) int64: ``count`` (P,), one value per point of
    ``idx``, split back into the features' points (in their order). Features left out of the
    index (fewer than 2 points) get zeros; ids that occur more than once are left out."""
    n_indexed = sum(len(f.points) >= 2 for f in gt.features)
    bounds = np.searchsorted(idx.fid, np.arange(n_indexed + 1))  # idx.fid counts the indexed features
    n_of = Counter(int(f.id) for f in gt.features)
    out, j = {}, 0
    for f in gt.features:
        values = np.zeros(len(f.points), dtype=np.int64)
        if len(f.points) >= 2:
            values, j = np.asarray(count[bounds[j] : bounds[j + 1]], dtype=np.int64), j + 1
        if n_of[int(f.id)] == 1:
            out[int(f.id)] = values
    return out


def _block_uniform(s: np.ndarray, group: np.ndarray, bmin: float, bmax: float, rng: np.random.Generator) -> np.ndarray:
    """(P,) a uniform value per point, constant over blocks of length ~U(bmin, bmax) along ``s``,
    independent per ``group`` (one feature): the latent variable of on/off processes."""
    out = np.empty(len(s))
    for g in np.unique(group):
        m = group == g
        lo, hi = s[m].min(), s[m].max()
        n = int(np.ceil((hi - lo) / bmin)) + 2
        lengths = rng.uniform(bmin, bmax, size=n)
        edges = lo - rng.uniform(0.0, lengths[0]) + np.cumsum(lengths)
        values = rng.random(n + 1)
        out[m] = values[np.searchsorted(edges, s[m], side="right")]
    return out


def _visibility(cfg: SimConfig, typ: np.ndarray, abs_lat: np.ndarray) -> np.ndarray:
    """(P,) detection probability of a feature point of type ``typ`` at lateral distance ``abs_lat``.

    Piecewise constant per band, with linear ramps of ``visibility_edge_m`` across the band
    edges: a feature running right at an edge then does not flicker in and out.
    """
    bands = [cfg.ego_marking_max_lateral_m, cfg.next_marking_max_lateral_m, cfg.far_marking_max_lateral_m]
    gaps = np.diff([0.0] + bands)
    h = min(cfg.visibility_edge_m / 2.0, 0.5 * float(np.min(gaps[gaps > 0])) if np.any(gaps > 0) else 0.0)
    values = [cfg.visibility_ego_marking, cfg.visibility_next_marking, cfg.visibility_far_marking, 0.0]
    xp, fp = [0.0], [values[0]]
    for i, edge in enumerate(bands):
        xp += [edge - h, edge + h + 1e-9 * (i + 1)]
        fp += [values[i], values[i + 1]]
    p_mark = np.interp(abs_lat, np.maximum.accumulate(xp), fp)
    hb = min(cfg.visibility_edge_m / 2.0, cfg.border_max_lateral_m)
    p_border = np.interp(
        abs_lat,
        [0.0, cfg.border_max_lateral_m - hb, cfg.border_max_lateral_m + hb + 1e-9],
        [cfg.visibility_border, cfg.visibility_border, 0.0],
    )
    marking = np.isin(typ, _MARKINGS)
    return np.where(marking, p_mark, np.where(typ == _BORDER, p_border, 0.0))


def _candidates(idx: FeatureIndex, xy: np.ndarray, yaw_last: float, reach_m: float, cfg: SimConfig) -> np.ndarray:
    """Indices of feature points in grid cells within ``reach_m`` of the trajectory or of the
    sensor range ahead of its last pose (a superset; callers filter by distance)."""
    if len(idx.xy) == 0:
        return np.zeros(0, np.int64)
    stride = max(1, int(round(_CELL_M / 2.0 / cfg.pose_spacing_m)))
    ahead = xy[-1] + np.outer(
        np.arange(0.0, cfg.range_ahead_m + _CELL_M, _CELL_M / 2.0), [np.cos(yaw_last), np.sin(yaw_last)]
    )
    q = np.concatenate([xy[::stride], xy[-1:], ahead])
    r = int(np.ceil(reach_m / _CELL_M)) + 1
    d = np.arange(-r, r + 1)
    base = np.floor(q / _CELL_M).astype(np.int64) + (1 << 20)
    cx = (base[:, 0, None, None] + d[None, :, None]) * (1 << 21)
    ids = np.unique((cx + base[:, 1, None, None] + d[None, None, :]).ravel())
    lo = np.searchsorted(idx.cells, ids, side="left")
    n = np.searchsorted(idx.cells, ids, side="right") - lo
    lo, n = lo[n > 0], n[n > 0]
    within = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    return idx.order[np.repeat(lo, n) + within]


def detections(
    idx: FeatureIndex,
    xy: np.ndarray,
    yaw: np.ndarray,
    disp: np.ndarray,
    cfg: SimConfig,
    rng: np.random.Generator,
) -> tuple[list[Detection], np.ndarray]:
    """The drive's detections of ground-truth features (true poses ``xy``/``yaw``; every reported
    point is moved by ``disp`` (M, 2) of the pose it was seen from).

    Returns:
        the detections, and (S,) the indices into ``idx`` of the ground-truth feature points they
        were made of (visible and in a reported piece, whatever type they were reported as; each
        point once, sorted).
    """
    reach = max(cfg.far_marking_max_lateral_m, cfg.border_max_lateral_m) + 1.0
    c = _candidates(idx, xy, float(yaw[-1]), reach, cfg)
    dist, k = cKDTree(xy).query(idx.xy[c], distance_upper_bound=max(reach, cfg.range_ahead_m + 1.0))
    c, k = c[np.isfinite(dist)], k[np.isfinite(dist)]
    if len(c) == 0:
        return [], _NONE_SEEN
    m = len(xy)
    head = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    left = np.stack([-head[:, 1], head[:, 0]], axis=1)
    v = idx.xy[c] - xy[k]
    along = np.sum(v * head[k], axis=1)
    lat = np.sum(v * left[k], axis=1)
    half = 0.75 * cfg.pose_spacing_m
    in_long = (along >= -half) & ((along <= half) | ((k == m - 1) & (along <= cfg.range_ahead_m)))
    cos = np.sum(idx.tangent[c] * head[k], axis=1)
    typ = idx.type[c]
    same = in_long & (cos >= cfg.same_direction_cos_min)
    opp = in_long & (cos <= -cfg.same_direction_cos_min) & (lat > 0)
    p = np.where(same, _visibility(cfg, typ, np.abs(lat)), 0.0)
    if cfg.opposite_barrier and opp.any():
        # RULE: of the opposite carriageway only its nearest feature on the left is seen: the
        # median barrier (as a road border), or a shared centre line (a marking with no feature
        # of our own direction between it and us).
        near_opp = _per_pose_min(k[opp], lat[opp], m)
        near_same = _per_pose_min(k[same & (lat > 0)], lat[same & (lat > 0)], m)
        nearest = opp & (lat <= near_opp[k] + 1.0)
        border = nearest & (typ == _BORDER)
        centre = nearest & np.isin(typ, _MARKINGS) & (lat < near_same[k] - 0.3)
        p = np.where(border | centre, _visibility(cfg, typ, np.abs(lat)), p)
    fid = idx.fid[c]
    live = p > 0
    u_vis = np.ones(len(c))
    u_vis[live] = _block_uniform(idx.s[c][live], fid[live], cfg.visibility_block_min_m, cfg.visibility_block_max_m, rng)
    vis = live & (u_vis < p)
    if not vis.any():
        return [], _NONE_SEEN
    c, k, lat, typ, fid, reverse = c[vis], k[vis], lat[vis], typ[vis], fid[vis], (cos[vis] < 0)
    u_cls = _block_uniform(idx.s[c], fid, cfg.misclass_block_min_m, cfg.misclass_block_max_m, rng)
    marking = np.isin(typ, _MARKINGS)
    swap = marking & (u_cls < cfg.misclass_rate)
    to_border = marking & ~swap & (u_cls < cfg.misclass_rate + cfg.marking_to_border_rate)
    typ = np.where(swap, np.where(typ == int(FeatureType.SOLID), int(FeatureType.DASHED), int(FeatureType.SOLID)), typ)
    typ = np.where(to_border, _BORDER, typ)
    return _pieces(idx, c, k, lat, typ, fid, reverse, disp, cfg, rng)


def _per_pose_min(k: np.ndarray, value: np.ndarray, m: int) -> np.ndarray:
    """(m,) minimum of ``value`` per pose index, spread over +-3 poses (inf where none)."""
    out = np.full(m, np.inf)
    np.minimum.at(out, k, value)
    return minimum_filter1d(out, size=7, mode="nearest")


def _pieces(
    idx: FeatureIndex,
    c: np.ndarray,
    k: np.ndarray,
    lat: np.ndarray,
    typ: np.ndarray,
    fid: np.ndarray,
    reverse: np.ndarray,
    disp: np.ndarray,
    cfg: SimConfig,
    rng: np.random.Generator,
) -> tuple[list[Detection], np.ndarray]:
    """Connected visible runs -> resampled, noisy, displaced detection polylines (vectorised over
    all pieces of the drive), and (S,) the sorted indices into ``idx`` of the ground-truth points
    of the reported pieces."""
    key = np.where(reverse, -idx.pid[c], idx.pid[c])
    order = np.lexsort((key, fid))
    c, k, lat, typ, fid, reverse, key = (a[order] for a in (c, k, lat, typ, fid, reverse, key))
    brk = np.ones(len(c), dtype=bool)
    brk[1:] = (np.diff(fid) != 0) | (np.diff(key) != 1) | (np.diff(typ) != 0) | (np.diff(reverse.astype(int)) != 0)
    start = np.flatnonzero(brk)
    piece = np.cumsum(brk) - 1
    pts = idx.xy[c]
    seg = np.zeros(len(c))
    seg[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    seg[brk] = 0.0
    s_in = np.cumsum(seg)
    s_in -= s_in[start][piece]
    length = np.zeros(len(start))
    np.maximum.at(length, piece, s_in)
    ok = length >= max(cfg.min_detection_length_m, 1e-6)
    seen = np.unique(c[ok[piece]])
    # One increasing coordinate over all pieces (1 m apart) lets np.interp resample them at once.
    offset = np.concatenate([[0.0], np.cumsum(length + 1.0)[:-1]])
    g = s_in + offset[piece]
    n_out = np.where(ok, np.maximum(2, np.ceil(length / cfg.detection_spacing_m).astype(int) + 1), 0)
    out_piece = np.repeat(np.arange(len(start)), n_out)
    if len(out_piece) == 0:
        return [], seen
    first = np.concatenate([[0], np.cumsum(n_out)[:-1]])
    j = np.arange(len(out_piece)) - first[out_piece]
    q = offset[out_piece] + length[out_piece] * j / np.maximum(n_out[out_piece] - 1, 1)
    xy = np.stack([np.interp(q, g, pts[:, 0]), np.interp(q, g, pts[:, 1])], axis=1)
    pose = np.clip(np.rint(np.interp(q, g, k)).astype(int), 0, len(disp) - 1)
    if cfg.noise_sigma_m > 0 or cfg.noise_growth_per_m > 0:
        dist = np.hypot(np.interp(q, g, np.abs(lat)), cfg.noise_ahead_m)
        sigma = cfg.noise_sigma_m + cfg.noise_growth_per_m * dist
        xy = xy + (_piecewise_gauss_markov(out_piece, first, cfg, rng) * sigma)[:, None] * _normals(xy, out_piece)
    xy = xy + disp[pose]
    piece_type = typ[start]
    bounds = np.concatenate([first, [len(out_piece)]])
    dets = []
    for p in np.flatnonzero(ok):
        dets.append(Detection(FeatureType(int(piece_type[p])), xy[bounds[p] : bounds[p] + n_out[p]]))
    return dets, seen


def _piecewise_gauss_markov(
    piece: np.ndarray, first: np.ndarray, cfg: SimConfig, rng: np.random.Generator
) -> np.ndarray:
    """(N,) unit-std Gauss-Markov noise, started afresh (stationary) at every piece start."""
    n = len(piece)
    w = rng.standard_normal(n)
    phi = float(np.exp(-cfg.detection_spacing_m / cfg.noise_corr_length_m)) if cfg.noise_corr_length_m > 0 else 0.0
    starts = first[piece]
    j = np.arange(n) - starts
    e = np.where(j == 0, w, np.sqrt(1.0 - phi * phi) * w)
    x = lfilter([1.0], [1.0, -phi], e)
    # One filter runs over all pieces; remove what leaked in from the previous piece.
    prev = np.where(starts > 0, x[np.maximum(starts - 1, 0)], 0.0)
    return x - prev * phi ** (j + 1)


def _normals(xy: np.ndarray, piece: np.ndarray) -> np.ndarray:
    """(N, 2) unit left normals of the resampled pieces (central differences inside a piece)."""
    d = np.zeros_like(xy)
    same_next = np.zeros(len(xy), dtype=bool)
    same_next[:-1] = piece[1:] == piece[:-1]
    fwd = np.zeros_like(xy)
    fwd[:-1] = xy[1:] - xy[:-1]
    d += np.where(same_next[:, None], fwd, 0.0)
    same_prev = np.zeros(len(xy), dtype=bool)
    same_prev[1:] = same_next[:-1]
    bwd = np.zeros_like(xy)
    bwd[1:] = xy[1:] - xy[:-1]
    d += np.where(same_prev[:, None], bwd, 0.0)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.stack([-d[:, 1], d[:, 0]], axis=1)


def false_positives(
    xy: np.ndarray, yaw: np.ndarray, disp: np.ndarray, length_m: float, cfg: SimConfig, rng: np.random.Generator
) -> list[Detection]:
    """Short spurious polylines beside the trajectory, roughly parallel to it."""
    n = int(rng.poisson(cfg.false_positive_rate_per_km * length_m / 1000.0))
    types = np.array([int(FeatureType.SOLID), int(FeatureType.DASHED), _BORDER])
    out = []
    for _ in range(n):
        k = int(rng.integers(0, len(xy)))
        ln = rng.uniform(cfg.false_positive_length_min_m, cfg.false_positive_length_max_m)
        lat = rng.uniform(-cfg.false_positive_max_lateral_m, cfg.false_positive_max_lateral_m)
        ang = yaw[k] + rng.normal(0.0, 0.05)
        typ = int(rng.choice(types))
        npts = max(2, int(np.ceil(ln / cfg.detection_spacing_m)) + 1)
        d = np.array([np.cos(ang), np.sin(ang)])
        base = xy[k] + lat * left_normal(yaw[k])
        pts = base + np.outer(np.linspace(0.0, ln, npts), d) + disp[k]
        out.append(Detection(FeatureType(typ), pts))
    return out
