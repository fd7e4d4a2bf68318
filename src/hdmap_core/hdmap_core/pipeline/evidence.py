"""Negative evidence: where drives passed with a line well inside their sensors' range and saw nothing.

The paper's map only ever adds what drives detected; the gaps it bridges (connection, stitching,
loose-end joins) are filled with points no drive saw (``drive_count`` 0). Where a road really has no
line -- the mouth of a junction, where the through road's edge line stops for 30 m -- every drive
that passed saw nothing there, while a line that exists is detected by most drives that pass it
close by (series sensors: ~95 % of the ego lane's markings, ~70 % of the next ones). This module
turns that into a test that the stitched map's fills must pass:

1. per sampling step of a pivot (``step_profiles``): along the cut line, in bins, the number of
   detections expected if a line were there -- the sum over the same-direction drives crossing the
   cut of the detection rate at that lateral distance from the drive (``BANDS_M`` /
   ``RATES``, conservative) -- and the number of those drives that detected anything (any type)
   within ``SEEN_WINDOW_M`` of it. Bins expecting >= ``EvidenceConfig.min_expected`` detections with fewer than
   ``max_seen_ratio`` of them seen are *empty*; each step keeps its empty intervals
   (``StepResult.empty_m``), which travel with the segment like its maxima;
2. at export (``refuted_edges``): a feature-graph edge long enough to be filled is dropped when
   most of its sample points lie in empty intervals of the steps whose cuts cross them: its two
   ends stay loose ends.

Measured on carla_town06_100_s3 before this rule (docs/pipeline.md, "Negative evidence"): of 323
filled points the ground truth has, 1 lay where >= 3 detections were expected and < 20 % seen;
of 527 filled points it does not have, 52 % did (window 1.5 m, uncorrected drives).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from hdmap_core.checks import check_range

__all__ = [
    "BANDS_M",
    "PROFILE_HALF_LENGTH_M",
    "RATES",
    "SEEN_WINDOW_M",
    "EvidenceConfig",
    "refuted_edges",
    "step_profiles",
]

#: The intervals of a judged step without any (shared, read-only).
_NO_INTERVALS = np.zeros((0, 2))
_NO_INTERVALS.flags.writeable = False


# The rules below were measured and adopted with the negative-evidence test (docs/pipeline.md,
# "Negative evidence"); they are fixed, only how much evidence a judgement needs is a setting.
#: Lateral distances from a drive's trajectory bounding its sensor bands [m] ...
BANDS_M = (3.0, 6.5, 10.0)
#: ... and the share of the lines in each band a drive is assumed to detect: below the fleet
#: simulator's 0.95 / 0.70 / 0.25, so the expectation errs low [0..1].
RATES = (0.9, 0.6, 0.2)
#: A detection within this of a position counts as something seen there (samples and crossings
#: are both corrected by the offset model when there is one) [m].
SEEN_WINDOW_M = 1.0
#: Bin size of a step's profile along its cut [m].
_BIN_M = 0.5
#: A profile spans this far either side of the pivot [m].
PROFILE_HALF_LENGTH_M = 15.0
#: Narrower empty intervals are not kept: between two lines seen 3.5 m apart the lane's middle is
#: empty too (3.5 - 2 windows), a missing line makes two lanes' middles one interval of >= 2 lane
#: widths minus the windows [m].
_MIN_INTERVAL_M = 2.5
#: An edge is dropped when at least this share of its sample points are empty (each point: most
#: of the steps crossing it say empty).
_REFUTE_SHARE = 0.5
#: Sample spacing along an edge; the ends' first and last half spacing are not sampled (a line
#: ending there is seen up to its end) [m].
_SAMPLE_M = 2.0
#: Shorter edges are not tested (they get no filled points) [m].
_MIN_EDGE_M = 3.0
#: A step's cut crosses a point when its midpoint lies within this along the step's heading [m] ...
_ALONG_M = 1.0
#: ... and the step heads within this of the edge [deg].
_HEADING_DEG = 30.0


@dataclass(frozen=True)
class EvidenceConfig:
    """Negative evidence for filled stretches (module docstring).

    Attributes:
        min_expected: a bin of a step's profile is judged only when this many detections are
            expected there (the sum of the passing drives' detection rates); fewer: no verdict.
        max_seen_ratio: a judged bin is empty when fewer than this share of the expected
            detections were seen (0..1].
    """

    min_expected: float = 2.0
    max_seen_ratio: float = 0.2

    def __post_init__(self) -> None:
        check_range(self, ("min_expected",), low=0.0, finite=True)
        check_range(self, ("max_seen_ratio",), low=0.0, high=1.0, low_open=True)


def _rate(d: np.ndarray) -> np.ndarray:
    """Assumed detection rate of a line at lateral distance(s) ``d`` from a drive."""
    k = np.searchsorted(np.asarray(BANDS_M), np.abs(d), side="left")
    rates = np.concatenate([np.asarray(RATES, dtype=float), [0.0]])
    return rates[k]


def step_profiles(
    n_steps: int,
    cross_q: np.ndarray,
    cross_t: np.ndarray,
    cross_drive: np.ndarray,
    hit_q: np.ndarray,
    hit_t: np.ndarray,
    hit_drive: np.ndarray,
    *,
    config: EvidenceConfig = EvidenceConfig(),
) -> list[np.ndarray]:
    """Empty intervals along the cut lines of one pivot's steps.

    Args:
        n_steps: number of steps (cut lines).
        cross_q, cross_t, cross_drive: (C,) the same-direction drives' trajectory crossings of the
            cuts: step, position along the cut (+ = left of the pivot, from the pivot point) [m],
            drive index. A drive crossing a cut twice counts once (its crossing nearest the pivot).
        hit_q, hit_t, hit_drive: (H,) the same-direction detections' crossings, likewise (any type).

    Returns:
        Per step a (K, 2) array of empty intervals [lo, hi] along the cut, from the pivot point
        [m], each at least ``min_interval_m`` wide (steps without one share one empty array).
    """
    x = np.arange(-PROFILE_HALF_LENGTH_M, PROFILE_HALF_LENGTH_M + 1e-9, _BIN_M)
    nb = len(x)
    out = [_NO_INTERVALS] * n_steps
    cross_q = np.asarray(cross_q, dtype=np.int64)
    if n_steps == 0 or len(cross_q) == 0:
        return out
    cross_t = np.asarray(cross_t, dtype=float)
    cross_drive = np.asarray(cross_drive, dtype=np.int64)
    # one crossing per (step, drive): the one nearest the pivot
    order = np.lexsort((np.abs(cross_t), cross_drive, cross_q))
    cq, ct, cd = cross_q[order], cross_t[order], cross_drive[order]
    first = np.ones(len(cq), dtype=bool)
    first[1:] = (cq[1:] != cq[:-1]) | (cd[1:] != cd[:-1])
    cq, ct = cq[first], ct[first]
    expected = np.zeros((n_steps, nb))
    for a, b in _chunks(cq):  # (rows x bins) matrices a chunk of steps at a time: bounded memory
        uq, at = np.unique(cq[a:b], return_index=True)  # cq is sorted
        expected[uq] += np.add.reduceat(_rate(x[None, :] - ct[a:b, None]), at, axis=0)
    seen = np.zeros((n_steps, nb))
    hit_q = np.asarray(hit_q, dtype=np.int64)
    if len(hit_q):
        hit_t = np.asarray(hit_t, dtype=float)
        hit_drive = np.asarray(hit_drive, dtype=np.int64)
        n_drv = int(max(hit_drive.max(), cross_drive.max())) + 1
        key = hit_q * n_drv + hit_drive
        order = np.argsort(key, kind="stable")
        key, ht = key[order], hit_t[order]
        for a, b in _chunks(key // n_drv):
            near = (np.abs(x[None, :] - ht[a:b, None]) <= SEEN_WINDOW_M).astype(np.int8)
            ukey, at = np.unique(key[a:b], return_index=True)
            by_pair = np.maximum.reduceat(near, at, axis=0)  # per (step, drive): anything seen there
            uq, at = np.unique(ukey // n_drv, return_index=True)  # sorted with the keys
            seen[uq] += np.add.reduceat(by_pair, at, axis=0, dtype=np.float64)
    empty = (expected >= config.min_expected) & (seen < config.max_seen_ratio * expected)
    pad = np.zeros((n_steps, nb + 2), dtype=np.int8)
    pad[:, 1:-1] = empty
    d = np.diff(pad, axis=1)
    rows, lo_i = np.nonzero(d == 1)  # row-major: the i-th start pairs with the i-th end
    _, hi_i = np.nonzero(d == -1)
    lo, hi = x[lo_i] - 0.5 * _BIN_M, x[hi_i - 1] + 0.5 * _BIN_M
    wide = hi - lo >= _MIN_INTERVAL_M
    rows, iv = rows[wide], np.stack([lo[wide], hi[wide]], axis=1)
    bounds = np.searchsorted(rows, np.arange(n_steps + 1))
    for q in np.flatnonzero(np.diff(bounds)).tolist():
        out[q] = iv[bounds[q] : bounds[q + 1]]
    return out


def _chunks(group: np.ndarray, rows: int = 4096) -> list[tuple[int, int]]:
    """Row ranges of about ``rows`` rows of a sorted group-id array, each ending at a group's end."""
    n = len(group)
    out, a = [], 0
    while a < n:
        b = min(a + rows, n)
        if b < n:
            b = int(np.searchsorted(group, group[b], side="left"))
            if b <= a:  # one group longer than ``rows``: take all of it
                b = int(np.searchsorted(group, group[a], side="right"))
        out.append((a, b))
        a = b
    return out


def refuted_edges(
    node_xy: np.ndarray,
    edges: np.ndarray,
    step_xy: np.ndarray,
    step_heading: np.ndarray,
    empty_start: np.ndarray,
    empty: np.ndarray,
) -> np.ndarray:
    """(E,) bool: which feature-graph edges run through stretches the drives saw empty (at
    least ``_REFUTE_SHARE`` of an edge's sample points, every ``_SAMPLE_M``).

    Args:
        node_xy: (N, 2) feature node positions [m]; edges: (E, 2) node index pairs.
        step_xy, step_heading: (S, 2) / (S,) midpoints and headings of the sampling steps that
            carry a profile (any pivot, used or not).
        empty_start: (S + 1,) offsets into ``empty``; empty: (M, 2) intervals [lo, hi] along each
            step's cut, from its midpoint (+ = left) [m].
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    out = np.zeros(len(edges), dtype=bool)
    n_prof = np.diff(np.asarray(empty_start, dtype=np.int64)) if len(step_xy) else np.zeros(0, np.int64)
    if len(edges) == 0 or not n_prof.any():
        return out
    a, b = node_xy[edges[:, 0]], node_xy[edges[:, 1]]
    length = np.hypot(*(b - a).T)
    cand = np.flatnonzero(length >= max(_MIN_EDGE_M, _SAMPLE_M))
    if len(cand) == 0:
        return out
    # sample points along each candidate edge, the ends' half spacing left out
    n_s = np.maximum(1, np.floor(length[cand] / _SAMPLE_M).astype(np.int64))
    owner = np.repeat(np.arange(len(cand)), n_s)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(n_s) - n_s, n_s)
    frac = (k + 0.5) / n_s[owner]
    p = a[cand][owner] + frac[:, None] * (b[cand] - a[cand])[owner]
    u = (b[cand] - a[cand])[owner] / length[cand][owner][:, None]
    # every (sample point, step) pair within reach, then the steps whose cut crosses the point
    reach = PROFILE_HALF_LENGTH_M + _ALONG_M
    pairs = cKDTree(p).sparse_distance_matrix(cKDTree(step_xy), reach, output_type="ndarray")
    i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    su = np.stack([np.cos(step_heading[j]), np.sin(step_heading[j])], axis=1)
    rel = p[i] - step_xy[j]
    along = np.einsum("ij,ij->i", rel, su)
    lat = rel[:, 1] * su[:, 0] - rel[:, 0] * su[:, 1]  # + = left of the step's heading
    ok = np.einsum("ij,ij->i", su, u[i]) >= math.cos(math.radians(_HEADING_DEG))
    ok &= (np.abs(along) <= _ALONG_M) & (np.abs(lat) <= PROFILE_HALF_LENGTH_M)
    i, j, lat = i[ok], j[ok], lat[ok]
    judged = np.bincount(i, minlength=len(p)).astype(float)
    votes = np.bincount(i[_in_intervals(j, lat, empty_start, empty)], minlength=len(p)).astype(float)
    point_empty = (judged > 0) & (votes > 0.5 * judged)
    share = np.bincount(owner, weights=point_empty.astype(float), minlength=len(cand)) / n_s
    out[cand[share >= _REFUTE_SHARE]] = True
    return out


def _in_intervals(step: np.ndarray, lat: np.ndarray, empty_start: np.ndarray, empty: np.ndarray) -> np.ndarray:
    """(P,) bool: whether ``lat[k]`` lies in one of the empty intervals of step ``step[k]``
    (``empty[empty_start[s]:empty_start[s + 1]]``, disjoint [lo, hi] along the cut)."""
    empty_start = np.asarray(empty_start, dtype=np.int64)
    n_iv = np.diff(empty_start)
    if len(step) == 0 or not n_iv.any():
        return np.zeros(len(step), dtype=bool)
    iv_step = np.repeat(np.arange(len(n_iv)), n_iv)
    rows = empty[empty_start[0] : empty_start[-1]]
    lo, hi = rows[:, 0], rows[:, 1]
    # one sorted key per interval, (step, lo) in lexicographic order: steps ``width`` apart
    base = min(float(lo.min()), float(lat.min()))
    width = max(float(hi.max()), float(lat.max())) - base + 1.0
    key = iv_step * width + (lo - base)
    order = np.argsort(key, kind="stable")
    key, iv_step, lo, hi = key[order], iv_step[order], lo[order], hi[order]
    # the last interval starting at or before the point, on the point's own step or not
    k = np.maximum(np.searchsorted(key, step * width + (lat - base), side="right") - 1, 0)
    return (iv_step[k] == step) & (lo[k] <= lat) & (lat <= hi[k])
