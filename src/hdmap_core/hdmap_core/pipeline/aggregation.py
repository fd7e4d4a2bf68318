"""Sec. IV-C: aggregation of the aligned clusters of one step, and the processed-stretch store.

Each cluster is replaced by the maximum of its Gaussian kernel density estimate (bandwidth =
``kde_bandwidth_factor`` x the cluster's standard deviation; the paper writes 6). The maximum is
found on a grid and polished by mean-shift iterations (a fixed point of mean-shift is a stationary
point of the KDE), all clusters of a step at once. Clusters whose density functions overlap by
more than ``overlap_threshold`` (overlap coefficient: integral of min(p_i, p_j)) are the same
physical feature seen with two types (misclassification): the one with fewer samples is dropped.

The maxima are stored for every drive that took part, keyed by that drive's travelled distance
(``ProcessedStore``), so that stretches already processed through another pivot are skipped.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from scipy.special import ndtr

from hdmap_core.checks import Rule, check_choice, check_range
from hdmap_core.errors import ConfigError
from hdmap_core.model import FeatureType

__all__ = [
    "SINGLE_DRIVE_STD_M",
    "AggregationConfig",
    "ManyAggregates",
    "aggregate_many",
    "kde_maxima",
    "overlap_coefficients",
    "gaussian_overlap",
    "aggregate_step",
    "ProcessedStore",
]

_SQRT2PI = np.sqrt(2.0 * np.pi)
#: Reported 1-sigma of a maximum supported by one drive (the spread part; ``common_sigma_m`` adds
#: to it): a drive's samples of one line scatter by about this after the EM [m].
SINGLE_DRIVE_STD_M = 0.5


@dataclass(frozen=True)
class AggregationConfig:
    """Aggregation options (Sec. IV-C); the defaults are the recommended method. Values the
    paper leaves open are marked (open).

    Attributes:
        method: "kde" (paper: KDE maximum) or "mean" (plain cluster mean; the naive baseline).
        kde_bandwidth_factor: kernel bandwidth = factor x cluster std (paper: 6).
        kde_min_bandwidth_m: lower bound of the bandwidth [m] (a cluster of identical values;
            paper reading 0.02).
        overlap_filter: drop the smaller of two clusters whose densities overlap.
        overlap_threshold: overlap coefficient in [0, 1] above which clusters are merged (open).
        common_sigma_m: 1-sigma of one drive's localization error that no offset correction can
            remove [m]. Offsets estimated from the drives alone (no absolute reference) align
            them with each other, so the corrected samples scatter little, but the map point
            still carries the mean of its n drives' errors, sigma / sqrt(n). The reported
            lateral_std is then sqrt(spread^2 + common_sigma_m^2 / n). Default: the adjustment's
            prior of one drive's error, hypot(``AdjustConfig.bias_sigma_m``,
            ``AdjustConfig.drift_sigma_m``). 0: not added (samples not corrected: their spread
            already holds the drives' errors; or the paper, which reports no uncertainty).
        refined: the overlap filter's rules measured and adopted since the paper (its fixed
            ``refined`` rules: a solid-dashed tie decided by the line's place, a border of two
            drives kept beside a marking). False: the paper.
    """

    method: str = "kde"
    kde_bandwidth_factor: float = 1.0
    kde_min_bandwidth_m: float = 0.15
    overlap_filter: bool = True
    overlap_threshold: float = 0.5
    common_sigma_m: float = math.hypot(1.0, 0.3)
    refined: bool = True

    #: also filter a road-border cluster against a neighbouring marking cluster (the paper)
    overlap_border_marking: ClassVar[bool] = True
    #: (refined) a solid-dashed tie keeps solid for a side's outermost marking, dashed for an
    #: inner one (97-100 % / 98 % in the ground-truth maps); off: the one further left
    tie_by_position = Rule("refined", True, False)
    #: (refined) a border cluster of at least this many drives is not filtered against an
    #: overlapping marking (a real border on the line); off (0): every pair is compared
    border_beside_marking_drives = Rule("refined", 2, 0)

    def __post_init__(self) -> None:
        check_choice(self, "method", ("kde", "mean"))
        check_range(self, ("kde_bandwidth_factor", "kde_min_bandwidth_m"), low=0.0, low_open=True)
        check_range(self, ("overlap_threshold",), low=0.0, high=1.0)
        check_range(self, ("common_sigma_m",), low=0.0, finite=True)


def kde_maxima(
    x: np.ndarray, labels: np.ndarray, bandwidth_m: np.ndarray, *, grid_points: int = 16, n_shift: int = 50
) -> np.ndarray:
    """Maximum of the Gaussian KDE of every cluster.

    Args:
        x: (M,) values [m]; labels: (M,) cluster 0..K-1 (every cluster non-empty).
        bandwidth_m: (K,) kernel std per cluster [m].

    Returns:
        (K,) arg max of each cluster's KDE [m].
    """
    k = int(labels.max()) + 1
    # per-cluster extent and grid densities without ufunc.at (slow): min/max over the clusters'
    # sorted runs, the sums by bincount per grid column (same summation order as add.at)
    order = np.argsort(labels, kind="stable")
    xs, ls = x[order], labels[order]
    starts = np.searchsorted(ls, np.arange(k))
    lo = np.minimum.reduceat(xs, starts)
    hi = np.maximum.reduceat(xs, starts)
    g = np.linspace(0.0, 1.0, grid_points)
    grid = lo[:, None] + (hi - lo)[:, None] * g[None, :]  # (K, G)
    hs = bandwidth_m[ls]
    # RULE bounded temporaries: the clusters go through in runs of about KDE_CHUNK_SAMPLES samples
    # (one array of (M, G) grew past the caches with hundreds of drives per place); a cluster's
    # samples keep their order, so every sum is the one over all samples at once
    runs = _cluster_runs(starts, len(xs), KDE_CHUNK_SAMPLES)
    dens = np.empty((k, grid_points))
    for c0, c1, a, b in runs:
        lc = ls[a:b] - c0
        z = (grid[ls[a:b]] - xs[a:b, None]) / hs[a:b, None]  # (run, G)
        e = np.exp(-0.5 * z * z)
        dens[c0:c1] = np.stack([np.bincount(lc, weights=e[:, j], minlength=c1 - c0) for j in range(grid_points)], 1)
    m = grid[np.arange(k), np.argmax(dens, axis=1)]
    new = np.empty(k)
    for _ in range(n_shift):
        # all runs step together: the iterations stop when every cluster has converged
        for c0, c1, a, b in runs:
            lc, xr = ls[a:b] - c0, xs[a:b]
            w = np.exp(-0.5 * ((m[ls[a:b]] - xr) / hs[a:b]) ** 2)
            num = np.bincount(lc, weights=w * xr, minlength=c1 - c0)
            den = np.bincount(lc, weights=w, minlength=c1 - c0)
            new[c0:c1] = np.where(den > 0, num / np.where(den > 0, den, 1.0), m[c0:c1])
        if np.max(np.abs(new - m)) < 1e-9:
            m = new
            break
        m, new = new, m
    return m


#: Samples per run of clusters in ``kde_maxima`` (a run is whole clusters).
KDE_CHUNK_SAMPLES = 1 << 15


def _cluster_runs(starts: np.ndarray, n: int, chunk: int) -> list[tuple[int, int, int, int]]:
    """Runs of consecutive clusters (``starts``: the first sample of each, in sorted order; ``n``
    samples) of about ``chunk`` samples each: (first cluster, end cluster, first sample, end sample)."""
    k = len(starts)
    runs = []
    c0 = 0
    while c0 < k:
        c1 = max(int(np.searchsorted(starts, starts[c0] + chunk, side="left")), c0 + 1)
        runs.append((c0, c1, int(starts[c0]), int(starts[c1]) if c1 < k else n))
        c0 = c1
    return runs


def _kde_on(points: np.ndarray, x: np.ndarray, h: float) -> np.ndarray:
    z = (points[:, None] - x[None, :]) / h
    return np.exp(-0.5 * z * z).sum(axis=1) / (len(x) * h * _SQRT2PI)


def overlap_coefficients(
    x: np.ndarray, labels: np.ndarray, bandwidth_m: np.ndarray, pairs: np.ndarray, *, grid_points: int = 48
) -> np.ndarray:
    """Overlap coefficient integral(min(p_i, p_j)) of the KDEs of cluster pairs.

    Args:
        x: (M,); labels: (M,) 0..K-1; bandwidth_m: (K,); pairs: (P, 2) cluster index pairs.

    Returns:
        (P,) overlaps in [0, 1].
    """
    out = np.zeros(len(pairs))
    for p, (i, j) in enumerate(pairs):
        xi, xj = x[labels == i], x[labels == j]
        hi_, hj = bandwidth_m[i], bandwidth_m[j]
        lo = min(xi.min() - 4 * hi_, xj.min() - 4 * hj)
        hi = max(xi.max() + 4 * hi_, xj.max() + 4 * hj)
        grid = np.linspace(lo, hi, 4 * grid_points)
        pi, pj = _kde_on(grid, xi, hi_), _kde_on(grid, xj, hj)
        out[p] = float(np.minimum(pi, pj).sum() * (grid[1] - grid[0]))
    return out


@dataclass(frozen=True)
class ManyAggregates:
    """Aggregated maxima of many steps at once, sorted by (step, lateral position).

    Attributes:
        step: (K,) step of each maximum; lateral_m: (K,) maxima [m]; types: (K,); counts: (K,)
        distinct drives; std_m: (K,) 1-sigma of each maximum [m]; n_samples: (K,); kept_labels:
        (K,) the input cluster label of each.
    """

    step: np.ndarray
    lateral_m: np.ndarray
    types: np.ndarray
    counts: np.ndarray
    std_m: np.ndarray
    n_samples: np.ndarray
    kept_labels: np.ndarray


def gaussian_overlap(mu1: np.ndarray, sd1: np.ndarray, mu2: np.ndarray, sd2: np.ndarray) -> np.ndarray:
    """Overlap coefficient integral(min(p, q)) of two normal densities, vectorised, exact.

    The densities cross where a quadratic in x vanishes; between and beyond the crossings the
    smaller density is integrated with the normal CDF.
    """
    mu1, sd1, mu2, sd2 = (np.asarray(v, dtype=float) for v in (mu1, sd1, mu2, sd2))
    # Order so that sd1 <= sd2.
    swap = sd1 > sd2
    mu1, mu2 = np.where(swap, mu2, mu1), np.where(swap, mu1, mu2)
    sd1, sd2 = np.where(swap, sd2, sd1), np.where(swap, sd1, sd2)
    equal = np.isclose(sd1, sd2, rtol=1e-9, atol=0.0)
    # Equal widths: one crossing at the middle.
    d = np.abs(mu1 - mu2)
    ovl_eq = 2.0 * ndtr(-d / (2.0 * sd1))
    a = 1.0 / (2 * sd1**2) - 1.0 / (2 * sd2**2)
    b = mu2 / sd2**2 - mu1 / sd1**2
    c = mu1**2 / (2 * sd1**2) - mu2**2 / (2 * sd2**2) - np.log(sd2 / sd1)
    a_s = np.where(equal, 1.0, a)
    disc = np.sqrt(np.maximum(b * b - 4 * a_s * c, 0.0))
    x1 = (-b - disc) / (2 * a_s)
    x2 = (-b + disc) / (2 * a_s)
    lo, hi = np.minimum(x1, x2), np.maximum(x1, x2)
    # The narrow density (sd1) is the smaller one outside [lo, hi], the wide one inside.
    narrow_out = ndtr((lo - mu1) / sd1) + 1.0 - ndtr((hi - mu1) / sd1)
    wide_in = ndtr((hi - mu2) / sd2) - ndtr((lo - mu2) / sd2)
    return np.where(equal, ovl_eq, np.clip(narrow_out + wide_in, 0.0, 1.0))


def aggregate_many(
    x: np.ndarray,
    step: np.ndarray,
    labels: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    *,
    config: AggregationConfig,
) -> ManyAggregates:
    """Sec. IV-C for many steps at once: KDE maxima and the overlap filter per step.

    Args:
        x: (M,) corrected lateral positions [m]; step: (M,) step of each sample; labels: (M,)
        cluster labels, unique across steps (-1 ignored); types: (M,); drive: (M,) drive codes.

    Returns:
        The surviving maxima, sorted by (step, position).
    """
    use = labels >= 0
    if not use.any():
        e = np.zeros(0)
        ei = np.zeros(0, np.int64)
        return ManyAggregates(ei, e, ei, ei, e, ei, ei)
    x, step, types, drive = x[use], step[use], types[use], drive[use]
    orig, lab = np.unique(labels[use], return_inverse=True)
    k = len(orig)
    n = np.bincount(lab, minlength=k).astype(float)
    mean = np.bincount(lab, weights=x, minlength=k) / n
    var = np.maximum(np.bincount(lab, weights=x * x, minlength=k) / n - mean * mean, 0.0)
    std = np.sqrt(var)
    ctype = np.zeros(k, dtype=np.int64)
    ctype[lab] = types
    cstep = np.zeros(k, dtype=np.int64)
    cstep[lab] = step
    n_drives = _distinct_drives(lab, drive, k)
    bw = np.maximum(config.kde_bandwidth_factor * std, config.kde_min_bandwidth_m)
    pos = kde_maxima(x, lab, bw) if config.method == "kde" else mean
    keep = np.ones(k, dtype=bool)
    order = np.lexsort((pos, cstep))
    if config.overlap_filter and k >= 2:
        # Neighbours in position within a step (within each class when borders and markings
        # are not compared, so a border between a line and its misclassified copy does not hide
        # the pair).
        cls = (
            np.zeros(k, dtype=np.int64)
            if config.overlap_border_marking
            else (ctype == int(FeatureType.ROAD_BORDER)).astype(np.int64)
        )
        by_class = np.lexsort((pos, cstep, cls))
        a, b = by_class[:-1], by_class[1:]
        near = (cstep[a] == cstep[b]) & (cls[a] == cls[b]) & (np.abs(pos[a] - pos[b]) < 4.0 * (bw[a] + bw[b]))
        pairs = np.stack([a[near], b[near]], axis=1)
        if len(pairs):
            # Each KDE is approximated by a normal of the same mean and variance (var + h^2),
            # whose overlap has a closed form; exact for the paper's wide kernels.
            sd = np.sqrt(var + bw * bw)
            ov = gaussian_overlap(mean[pairs[:, 0]], sd[pairs[:, 0]], mean[pairs[:, 1]], sd[pairs[:, 1]])
            step_sorted = cstep[order]  # the clusters of a step are a run of ``order``
            for p in np.argsort(-ov):
                if ov[p] <= config.overlap_threshold:
                    break
                i, j = pairs[p]
                if keep[i] and keep[j]:
                    if config.border_beside_marking_drives and (ctype[i] == _BORDER) != (ctype[j] == _BORDER):
                        border = i if ctype[i] == _BORDER else j
                        if n_drives[border] >= config.border_beside_marking_drives:
                            continue  # two drives' border on a line: both there (a curb on an edge line)
                    if config.tie_by_position and n[i] == n[j] and {int(ctype[i]), int(ctype[j])} == _SOLID_DASHED:
                        members = order[
                            np.searchsorted(step_sorted, cstep[i], "left") : np.searchsorted(
                                step_sorted, cstep[i], "right"
                            )
                        ]
                        keep[i if int(ctype[i]) != _tie_type(i, j, members, pos, ctype) else j] = False
                    else:
                        keep[i if n[i] < n[j] else j] = False
    idx = order[keep[order]]
    n_kept = np.maximum(n_drives[idx], 1)
    spread = np.where(n_drives[idx] > 1, std[idx] / np.sqrt(n_kept), SINGLE_DRIVE_STD_M)
    sigma = np.sqrt(spread**2 + config.common_sigma_m**2 / n_kept)
    return ManyAggregates(
        step=cstep[idx],
        lateral_m=pos[idx],
        types=ctype[idx],
        counts=n_drives[idx],
        std_m=sigma,
        n_samples=n[idx].astype(np.int64),
        kept_labels=orig[idx],
    )


def _distinct_drives(lab: np.ndarray, drive: np.ndarray, k: int) -> np.ndarray:
    """(K,) how many distinct drives have samples in each cluster (``lab`` (M,) 0..K-1)."""
    nd = int(drive.max()) + 1
    key = lab * nd + drive
    if k * nd <= 4 * len(key):
        # RULE linear in the samples: a mark per (cluster, drive) pair; the unique of the keys
        # (a hash table of every pair) grew faster than the samples at hundreds of drives per place
        seen = np.zeros(k * nd, dtype=bool)
        seen[key] = True
        return np.count_nonzero(seen.reshape(k, nd), axis=1).astype(np.int64)
    return np.bincount(np.unique(key) // nd, minlength=k)


_BORDER = int(FeatureType.ROAD_BORDER)
_SOLID_DASHED = {int(FeatureType.SOLID), int(FeatureType.DASHED)}


def _tie_type(i: int, j: int, step_members: np.ndarray, pos: np.ndarray, ctype: np.ndarray) -> int:
    """The type a solid/dashed tie between clusters i and j takes from the line's place in its step
    (``step_members``: the clusters of that step): dashed when other markings of the step lie on
    both sides of the pair, else solid."""
    other = step_members[(ctype[step_members] != _BORDER) & (step_members != i) & (step_members != j)]
    lo, hi = min(pos[i], pos[j]), max(pos[i], pos[j])
    inner = bool(np.any(pos[other] < lo)) and bool(np.any(pos[other] > hi))
    return int(FeatureType.DASHED if inner else FeatureType.SOLID)


def aggregate_step(
    x: np.ndarray, labels: np.ndarray, types: np.ndarray, drive: np.ndarray, *, config: AggregationConfig
) -> ManyAggregates:
    """Replace each cluster of one step by its KDE maximum and filter overlapping clusters.

    Args:
        x: (M,) corrected lateral positions [m]; labels: (M,) cluster labels (-1 ignored);
        types: (M,) FeatureType codes; drive: (M,) drive codes.

    Returns:
        The maxima of the surviving clusters, sorted by position (all of step 0).
    """
    return aggregate_many(x, np.zeros(len(x), np.int64), labels, types, drive, config=config)


@dataclass
class ProcessedStore:
    """Travelled-distance intervals already processed, per drive (Sec. IV-C).

    ``intervals[drive_id]`` is a sorted list of disjoint [start_m, end_m] pairs. JSON-serialisable
    via ``to_json`` / ``from_json``. Methods return new stores; an instance is never changed in
    place by the pipeline.
    """

    intervals: dict[str, list[tuple[float, float]]] = field(default_factory=dict)

    def contains(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        """(N,) bool: which travelled distances of a drive lie in a processed interval."""
        s_m = np.asarray(s_m, dtype=float)
        iv = self.intervals.get(drive_id)
        if not iv:
            return np.zeros(s_m.shape, dtype=bool)
        a = np.array(iv, dtype=float)
        i = np.searchsorted(a[:, 0], s_m, side="right") - 1
        ok = i >= 0
        return ok & (s_m <= a[np.maximum(i, 0), 1])

    def with_marks(self, marks: dict[str, np.ndarray], *, pad_m: float, merge_gap_m: float) -> ProcessedStore:
        """A new store with the given travelled distances added as processed.

        Args:
            marks: drive_id -> (N,) travelled distances [m] of processed steps.
            pad_m: each mark covers [s - pad, s + pad] (half a step).
            merge_gap_m: marks closer than this join one interval.
        """
        # the lists are never changed in place (``_merge`` makes new ones): shared, not copied
        # (a copy of every drive's list per pivot grew with pivots x drives)
        new = dict(self.intervals)
        for did, s in marks.items():
            s = np.sort(np.asarray(s, dtype=float))
            if len(s) == 0:
                continue
            brk = np.flatnonzero(np.diff(s) > merge_gap_m)
            starts = np.concatenate([[s[0]], s[brk + 1]]) - pad_m
            ends = np.concatenate([s[brk], [s[-1]]]) + pad_m
            new[did] = _merge(new.get(did, []) + list(zip(starts.tolist(), ends.tolist())))
        return ProcessedStore(new)

    def total_m(self) -> float:
        return float(sum(b - a for iv in self.intervals.values() for a, b in iv))

    def to_json(self) -> str:
        return json.dumps({k: [[a, b] for a, b in v] for k, v in self.intervals.items()})

    @classmethod
    def from_json(cls, text: str) -> ProcessedStore:
        try:
            raw = json.loads(text)
            return cls({str(k): _merge([(float(a), float(b)) for a, b in v]) for k, v in raw.items()})
        except (ValueError, TypeError, AttributeError) as err:
            raise ConfigError(f"processed-stretch store is not valid JSON of the documented form: {err}") from err


def _merge(iv: list[tuple[float, float]]) -> list[tuple[float, float]]:
    iv = sorted(iv)
    out: list[tuple[float, float]] = []
    for a, b in iv:
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out
