"""Sec. IV-B: EM estimation of one lateral offset per drive at one sampling step.

E-step: the samples of each type are clustered in 1-D; k is chosen by silhouette score (paper), or
the samples are split at gaps (when offsets are already close, e.g. warm started). 1-D k-means is
solved exactly: optimal clusters are contiguous in sorted order, so a dynamic programme over the
sorted samples (Ckmeans-style) gives the optimum for every k at once.

M-step: o_opt = argmin_o sum_i Var(c_i(o)) + sum_i exp(-s * d_min_i(o)^2). The variance term is
quadratic in o (each cluster's residuals are linear in o), so it is solved in closed form as
linear least squares; the penalty only matters when two same-type clusters come close, and then
(or always, with ``solver="lm"``, the paper's way) Levenberg-Marquardt solves the full cost.
The step is scored by silhouette; below the gate (paper: 0.67) it is rejected. Drift is removed by
keeping the mean cluster position unchanged by the correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from hdmap_core.errors import ConfigError

__all__ = [
    "AlignmentConfig",
    "StepAlignment",
    "kmeans_1d_all_k",
    "silhouette_samples_1d",
    "cluster_type",
    "cluster_step",
    "solve_offsets",
    "align_step",
]

_CLUSTERINGS = ("silhouette", "gap", "auto")
_SOLVERS = ("lm", "closed_form")


@dataclass(frozen=True)
class AlignmentConfig:
    """Per-step EM options (Sec. IV-B). Values the paper leaves open are marked (open).

    Attributes:
        estimate_offsets: False skips the M-step (no correction; the naive baseline).
        clustering: "silhouette" (paper: exact 1-D k-means for k = 2..k_max, best silhouette),
            "gap" (split the sorted samples where the gap exceeds ``gap_split_m``; exact, O(n log n),
            right once offsets are roughly known) or "auto" (gap when every drive of the step has a
            prior offset, else silhouette).
        k_max: largest k tried per type.
        single_cluster_silhouette: with "silhouette", k = 1 when no k >= 2 reaches this score (open:
            the silhouette is undefined for k = 1).
        min_cluster_separation_m: with "silhouette", a k whose neighbouring cluster means of one
            type are closer than this is not taken (two features of one type are at least about
            a lane apart); 0 = off (paper). Stops the E-step from splitting one line in two,
            which lets the M-step shift drives by a whole lane.
        gap_split_m: gap that separates clusters with "gap" [m].
        n_iterations: EM iterations (open); the loop stops early when labels repeat.
        solver: "lm" (paper: Levenberg-Marquardt on the full cost) or "closed_form" (variance term
            solved as linear least squares; LM only when the penalty is not negligible).
        penalty_s_per_m2: s of the penalty exp(-s d^2) (open; "set from the lane width": 0.25
            makes the penalty 0.05 at a 3.5 m lane width).
        robust_loss: Huber-reweighted variance residuals (a drive's odd sample cannot pull).
        huber_delta_m: Huber threshold [m].
        ridge: weight of sum(o^2), fixes the gauge (common shift) and keeps lone drives at 0.
        prior_weight: weight of (o_d - prior_d)^2 for drives with a prior offset (the previous
            step's offset: offsets smoothed along a drive). 0 = independent steps (paper).
        remove_drift: keep the mean cluster position unchanged by the correction (paper).
        silhouette_gate: steps scoring below are rejected (paper: 0.67).
        min_cluster_drives: clusters supported by fewer distinct drives are dropped (label -1).
        max_offset_m: offsets are clipped to +-this [m].
    """

    estimate_offsets: bool = True
    clustering: str = "silhouette"
    k_max: int = 8
    single_cluster_silhouette: float = 0.5
    min_cluster_separation_m: float = 0.0
    gap_split_m: float = 1.0
    n_iterations: int = 5
    solver: str = "lm"
    penalty_s_per_m2: float = 0.25
    robust_loss: bool = False
    huber_delta_m: float = 0.3
    ridge: float = 1e-4
    prior_weight: float = 0.0
    remove_drift: bool = True
    silhouette_gate: float = 0.67
    min_cluster_drives: int = 1
    max_offset_m: float = 5.0

    def __post_init__(self) -> None:
        if self.clustering not in _CLUSTERINGS:
            raise ConfigError(f"AlignmentConfig.clustering must be one of {_CLUSTERINGS}, got {self.clustering!r}")
        if self.solver not in _SOLVERS:
            raise ConfigError(f"AlignmentConfig.solver must be one of {_SOLVERS}, got {self.solver!r}")
        if self.k_max < 1 or self.n_iterations < 1 or self.min_cluster_drives < 1:
            raise ConfigError("AlignmentConfig.k_max, n_iterations, min_cluster_drives must be >= 1")
        if self.gap_split_m <= 0 or self.huber_delta_m <= 0 or self.ridge < 0 or self.prior_weight < 0:
            raise ConfigError("AlignmentConfig: gap_split_m, huber_delta_m > 0 and ridge, prior_weight >= 0 required")


@dataclass(frozen=True)
class StepAlignment:
    """Result of the EM at one step.

    Attributes:
        offsets_m: (D,) offset per local drive code, to ADD to that drive's samples [m].
        labels: (M,) cluster label per sample, unique across types; -1 = dropped.
        silhouette: score of the final clustering (-1 when undefined).
        valid: silhouette >= gate and at least two clusters.
        n_iterations: EM iterations run.
    """

    offsets_m: np.ndarray
    labels: np.ndarray
    silhouette: float
    valid: bool
    n_iterations: int


# ----------------------------------------------------------------------------- 1-D clustering


def kmeans_1d_all_k(x_sorted: np.ndarray, k_max: int) -> list[np.ndarray]:
    """Exact 1-D k-means for k = 1..k_max by dynamic programming over sorted samples.

    Args:
        x_sorted: (n,) ascending values.
        k_max: largest k (clipped to n).

    Returns:
        list, element k-1 is the (k+1,) array of cluster boundaries b (cluster c is
        ``x_sorted[b[c]:b[c+1]]``) of the optimal k-partition (minimum within-cluster SSE).
    """
    x = np.asarray(x_sorted, dtype=float)
    n = len(x)
    k_max = max(1, min(k_max, n))
    s1 = np.concatenate([[0.0], np.cumsum(x)])
    s2 = np.concatenate([[0.0], np.cumsum(x * x)])
    i = np.arange(n + 1)[:, None]
    j = np.arange(n + 1)[None, :]
    cnt = j - i
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = s2[j] - s2[i] - (s1[j] - s1[i]) ** 2 / cnt
    cost = np.where(cnt > 0, np.maximum(cost, 0.0), np.inf)
    best = cost[0].copy()  # best[j]: optimal SSE of x[:j] with the current k
    backs: dict[int, np.ndarray] = {}
    out = [np.array([0, n])]
    for k in range(2, k_max + 1):
        total = best[:, None] + cost  # (i, j): x[:i] in k-1 clusters, last cluster x[i:j]
        arg = np.argmin(total, axis=0)
        best = total[arg, np.arange(n + 1)]
        backs[k] = arg
        bounds = [n]
        j = n
        for kk in range(k, 1, -1):
            j = int(backs[kk][j])
            bounds.append(j)
        bounds.append(0)
        out.append(np.array(bounds[::-1]))
    return out


def silhouette_samples_1d(x: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Silhouette value of every sample (1-D, absolute distance), like sklearn.

    Args:
        x: (n,) values; labels: (n,) int >= 0.

    Returns:
        (n,) s = (b - a) / max(a, b); 0 for members of singleton clusters; all 0 with < 2 clusters.
    """
    x = np.asarray(x, dtype=float)
    uniq, lab = np.unique(labels, return_inverse=True)
    k = len(uniq)
    n = len(x)
    if k < 2 or n < 2:
        return np.zeros(n)
    onehot = np.zeros((n, k))
    onehot[np.arange(n), lab] = 1.0
    sums = np.abs(x[:, None] - x[None, :]) @ onehot  # (n, k) summed distances to each cluster
    cnt = onehot.sum(axis=0)
    own_cnt = cnt[lab]
    a = sums[np.arange(n), lab] / np.maximum(own_cnt - 1, 1)
    other = sums / cnt[None, :]
    other[np.arange(n), lab] = np.inf
    b = other.min(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (b - a) / np.maximum(a, b)
    s = np.where(own_cnt > 1, np.nan_to_num(s, nan=0.0), 0.0)
    return s


def cluster_type(
    x: np.ndarray,
    *,
    method: str,
    k_max: int,
    single_cluster_silhouette: float,
    gap_split_m: float,
    min_separation_m: float = 0.0,
) -> np.ndarray:
    """Cluster the samples of one type in 1-D.

    Args:
        x: (n,) corrected lateral positions [m].
        method: "silhouette" or "gap" (see ``AlignmentConfig.clustering``).

    Returns:
        (n,) labels 0..k-1 in ascending order of x.
    """
    n = len(x)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.argsort(x, kind="stable")
    xs = x[order]
    labels_sorted = np.zeros(n, dtype=np.int64)
    if method == "gap":
        labels_sorted[1:] = np.cumsum(np.diff(xs) > gap_split_m)
    elif n >= 3:
        parts = kmeans_1d_all_k(xs, min(k_max, n - 1))
        best_s, best_b = -np.inf, None
        s1 = np.concatenate([[0.0], np.cumsum(xs)])
        for b in parts[1:]:
            if min_separation_m > 0:
                means = (s1[b[1:]] - s1[b[:-1]]) / np.diff(b)
                if np.min(np.diff(means)) < min_separation_m:
                    continue
            lab = np.repeat(np.arange(len(b) - 1), np.diff(b))
            s = float(silhouette_samples_1d(xs, lab).mean())
            if s > best_s:
                best_s, best_b = s, b
        if best_b is not None and best_s >= single_cluster_silhouette:
            labels_sorted = np.repeat(np.arange(len(best_b) - 1), np.diff(best_b))
    labels = np.empty(n, dtype=np.int64)
    labels[order] = labels_sorted
    return labels


def cluster_step(x: np.ndarray, types: np.ndarray, *, method: str, config: AlignmentConfig) -> np.ndarray:
    """E-step: cluster every type separately; labels unique across types (M,)."""
    labels = np.empty(len(x), dtype=np.int64)
    base = 0
    for t in np.unique(types):
        sel = np.flatnonzero(types == t)
        lab = cluster_type(
            x[sel],
            method=method,
            k_max=config.k_max,
            single_cluster_silhouette=config.single_cluster_silhouette,
            gap_split_m=config.gap_split_m,
            min_separation_m=config.min_cluster_separation_m,
        )
        labels[sel] = lab + base
        base += int(lab.max()) + 1 if len(lab) else 0
    return labels


# ----------------------------------------------------------------------------- M-step


def _variance_system(x: np.ndarray, labels: np.ndarray, drive: np.ndarray, n_drives: int):
    """Linear residuals r(o) = A o + b of the variance term over labelled samples.

    Var(c) = mean over members of (x_j + o_dj - mean_c)^2, so every member gets the weight
    1/sqrt(n_c). Returns (A (M', D), b (M',), means (K,), F (K, D) member share per drive).
    """
    k = int(labels.max()) + 1
    cnt = np.bincount(labels, minlength=k).astype(float)
    mean = np.bincount(labels, weights=x, minlength=k) / np.maximum(cnt, 1)
    share = np.zeros((k, n_drives))
    np.add.at(share, (labels, drive), 1.0)
    share /= np.maximum(cnt, 1)[:, None]
    w = 1.0 / np.sqrt(cnt[labels])
    a = -share[labels]
    a[np.arange(len(x)), drive] += 1.0
    return w[:, None] * a, w * (x - mean[labels]), mean, share


def _penalty(mu: np.ndarray, ctype: np.ndarray, s: float) -> np.ndarray:
    """sqrt of exp(-s d_min^2) per cluster (residual form); 0 where no same-type neighbour."""
    same = ctype[:, None] == ctype[None, :]
    np.fill_diagonal(same, False)
    d = np.abs(mu[:, None] - mu[None, :])
    d = np.where(same, d, np.inf)
    dmin = d.min(axis=1)
    return np.exp(-0.5 * s * dmin * dmin)


def solve_offsets(
    x: np.ndarray,
    labels: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    n_drives: int,
    *,
    config: AlignmentConfig,
    prior: np.ndarray | None = None,
    init: np.ndarray | None = None,
) -> np.ndarray:
    """M-step: offsets (D,) minimising the cluster variances + same-type proximity penalty.

    Args:
        x: (M,) raw lateral positions [m]; labels: (M,) clusters (-1 ignored); types: (M,);
        drive: (M,) local drive codes 0..D-1.
        prior: optional (D,) prior offsets (NaN = none), pulled with ``config.prior_weight``.
        init: optional (D,) start values for LM.

    Returns:
        (D,) offsets to add to each drive's samples [m].
    """
    use = labels >= 0
    if not use.any():
        return np.zeros(n_drives)
    x, labels, types, drive = x[use], labels[use], types[use], drive[use]
    _, labels = np.unique(labels, return_inverse=True)
    a, b, mean0, share = _variance_system(x, labels, drive, n_drives)
    k = len(mean0)
    ctype = np.zeros(k, dtype=types.dtype)
    ctype[labels] = types
    reg_w = np.full(n_drives, config.ridge)
    reg_t = np.zeros(n_drives)
    if prior is not None and config.prior_weight > 0:
        has = np.isfinite(prior)
        reg_w = reg_w + np.where(has, config.prior_weight, 0.0)
        reg_t = np.where(has, config.prior_weight * np.nan_to_num(prior) / np.maximum(reg_w, 1e-300), 0.0)
    row_w = np.ones(len(b))
    o = np.zeros(n_drives)
    n_irls = 6 if config.robust_loss else 1
    for _ in range(n_irls):
        aw = a * row_w[:, None]
        bw = b * row_w
        lhs = aw.T @ aw + np.diag(reg_w)
        rhs = -aw.T @ bw + reg_w * reg_t
        o = np.linalg.solve(lhs, rhs)
        if config.robust_loss:
            r = np.abs(a @ o + b) * np.sqrt(np.bincount(labels)[labels])  # back to metres
            row_w = np.sqrt(np.minimum(1.0, config.huber_delta_m / np.maximum(r, 1e-12)))
    s = config.penalty_s_per_m2
    need_lm = config.solver == "lm" or _penalty(mean0 + share @ o, ctype, s).max() > 1e-3
    if need_lm and k >= 2 and s > 0:
        sq_reg = np.sqrt(reg_w)

        def fun(v: np.ndarray) -> np.ndarray:
            return np.concatenate([(a @ v + b) * row_w, _penalty(mean0 + share @ v, ctype, s), sq_reg * (v - reg_t)])

        start = o if config.solver == "closed_form" else (np.zeros(n_drives) if init is None else init)
        o = least_squares(fun, start, method="lm", xtol=1e-6, ftol=1e-8).x
    if config.remove_drift:
        # Road midpoint (mean cluster position) after correction = before it.
        o = o - float((share @ o).mean())
    return np.clip(o, -config.max_offset_m, config.max_offset_m)


# ----------------------------------------------------------------------------- EM


def _drop_thin_clusters(labels: np.ndarray, drive: np.ndarray, min_drives: int) -> np.ndarray:
    if min_drives <= 1:
        return labels
    use = labels >= 0
    pairs = np.unique(np.stack([labels[use], drive[use]], axis=1), axis=0)
    n_dr = np.bincount(pairs[:, 0], minlength=int(labels.max()) + 1)
    out = labels.copy()
    out[use & (n_dr[np.maximum(labels, 0)] < min_drives)] = -1
    return out


def step_silhouette(x: np.ndarray, labels: np.ndarray) -> float:
    """Mean silhouette of the labelled samples (all types together, labels as given); -1 when
    fewer than two clusters."""
    use = labels >= 0
    if len(np.unique(labels[use])) < 2:
        return -1.0
    return float(silhouette_samples_1d(x[use], labels[use]).mean())


def align_step(
    lateral_m: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    *,
    config: AlignmentConfig,
    prior: np.ndarray | None = None,
) -> StepAlignment:
    """EM lateral offset estimation at one step (Sec. IV-B).

    Args:
        lateral_m: (M,) sample positions along the cut [m].
        types: (M,) FeatureType codes.
        drive: (M,) local drive codes 0..D-1 (D = max + 1).
        config: EM options.
        prior: optional (D,) prior offsets (NaN where unknown), e.g. the previous step's.

    Returns:
        The offsets, final labels and silhouette gate decision.
    """
    x = np.asarray(lateral_m, dtype=float)
    n_drives = int(drive.max()) + 1 if len(drive) else 0
    if len(x) == 0:
        return StepAlignment(np.zeros(0), np.zeros(0, np.int64), -1.0, False, 0)
    o = np.zeros(n_drives)
    has_prior = prior is not None and np.all(np.isfinite(prior))
    if prior is not None:
        o = np.where(np.isfinite(prior), prior, 0.0)
    method = config.clustering
    if method == "auto":
        method = "gap" if has_prior else "silhouette"
    labels = None
    it = 0
    for it in range(1, (config.n_iterations if config.estimate_offsets else 1) + 1):
        new = cluster_step(x + o[drive], types, method=method, config=config)
        new = _drop_thin_clusters(new, drive, config.min_cluster_drives)
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        if not config.estimate_offsets:
            break
        o = solve_offsets(x, labels, types, drive, n_drives, config=config, prior=prior, init=o)
    score = step_silhouette(x + o[drive], labels)
    valid = score >= config.silhouette_gate
    return StepAlignment(offsets_m=o, labels=labels, silhouette=score, valid=bool(valid), n_iterations=it)
