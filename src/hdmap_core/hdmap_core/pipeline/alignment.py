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
from typing import ClassVar

import numpy as np
from scipy.optimize import least_squares

from hdmap_core.checks import check_choice, check_range
from hdmap_core.errors import ConfigError
from hdmap_core.model import FeatureType

__all__ = [
    "AlignmentConfig",
    "StepAlignment",
    "kmeans_1d_all_k",
    "silhouette_samples_1d",
    "silhouette_sorted",
    "step_silhouette",
    "cluster_type",
    "cluster_step",
    "solve_offsets",
    "align_step",
    "align_steps_gap",
    "gap_batchable",
]

_CLUSTERINGS = ("silhouette", "gap", "auto")
_SOLVERS = ("lm", "closed_form")

# Values the paper leaves open, fixed since the first measurements (docs/pipeline.md, "Stages as
# implemented"):
#: largest k tried per type: a carriageway shows at most a few lines of one type, and many small
#: clusters score well on the silhouette even for noise
K_MAX = 6
#: with silhouette clustering, k = 1 when no k >= 2 reaches this score (the silhouette is
#: undefined for k = 1)
SINGLE_CLUSTER_SILHOUETTE = 0.5
#: a gap wider than this separates clusters with gap clustering, and bounds the lane-shift
#: search of drive registration [m]
GAP_SPLIT_M = 1.0
#: s of the M-step's penalty exp(-s d^2), "set from the lane width": 0.05 at a 3.5 m lane [1/m^2]
PENALTY_S_PER_M2 = 0.25
#: offsets are clipped to +-this [m]
MAX_OFFSET_M = 5.0


@dataclass(frozen=True)
class AlignmentConfig:
    """Per-step EM options (Sec. IV-B); the defaults are the recommended method (the paper's
    values in brackets). Values the paper leaves open are marked (open).

    Attributes:
        estimate_offsets: False skips the M-step (no correction; the naive baseline).
        clustering: "silhouette" (paper: exact 1-D k-means for k = 2..``K_MAX``, best silhouette),
            "gap" (split the sorted samples where the gap exceeds ``GAP_SPLIT_M``; exact, O(n log n),
            right once offsets are roughly known) or "auto" (gap when every drive of the step has a
            prior offset, else silhouette).
        n_iterations: EM iterations (open; paper reading 5); the loop stops early when labels repeat.
        solver: "lm" (paper: Levenberg-Marquardt on the full cost) or "closed_form" (variance term
            solved as linear least squares; LM only when some cluster's penalty exceeds
            ``penalty_lm_threshold``).
        robust_loss: Huber-reweighted variance residuals (a drive's odd sample cannot pull).
            False: the paper.
        huber_delta_m: Huber threshold [m].
        prior_weight: weight of (o_d - prior_d)^2 for drives with a prior offset (the previous
            step's offset: offsets smoothed along a drive). 0 = independent steps (paper).
        silhouette_gate: steps scoring below are rejected (paper: 0.67).
        sparse_step_max_drives: sparse-step rules, 0 = off (paper). In a step seen by at most this
            many drives each drive sees lines the others miss; those are one-sample clusters
            that score silhouette 0 and pull the mean below the gate although every cluster is
            tight. Such a step is accepted when every cluster's std is at most
            ``sparse_step_max_std_m`` and the mean silhouette of the samples in clusters of two or
            more passes the gate; one-sample clusters that clash with another drive's sample of
            another type (``sparse_type_clash_m``) are dropped, and a step whose clusters are all
            one drive's (silhouette undefined or 0) is accepted when every cluster's std is at
            most ``sparse_step_max_std_m`` (``lone_cluster_max_std_m``; sparse places: one drive
            on a ramp).
        sparse_step_max_std_m: cluster std limit of the sparse-step rules [m].
    """

    estimate_offsets: bool = True
    clustering: str = "auto"
    n_iterations: int = 4
    solver: str = "closed_form"
    robust_loss: bool = True
    huber_delta_m: float = 0.3
    prior_weight: float = 1.0
    silhouette_gate: float = 0.67
    sparse_step_max_drives: int = 3
    sparse_step_max_std_m: float = 0.3

    #: with "silhouette", a k whose neighbouring cluster means of one type are closer than this
    #: is not taken; 0 = off (the paper) [m]
    min_cluster_separation_m: ClassVar[float] = 0.0
    #: with "closed_form", LM polishes only above this penalty (labels are fixed in the M-step;
    #: the penalty would only push apart clusters of one feature split by a gap)
    penalty_lm_threshold: ClassVar[float] = 2.0
    #: weight of sum(o^2): fixes the gauge (common shift) and keeps lone drives at 0
    ridge: ClassVar[float] = 1e-4
    #: keep the mean cluster position unchanged by the correction (paper)
    remove_drift: ClassVar[bool] = True
    #: clusters supported by fewer distinct drives are dropped (label -1)
    min_cluster_drives: ClassVar[int] = 1
    #: sparse-step rule: a one-sample cluster within this of another drive's sample of another
    #: type is dropped (two drives disagreeing on one line's type) [m]
    sparse_type_clash_m: ClassVar[float] = 1.0
    # The final pass's sparse rules (``FinalAlignment``: samples already corrected); off here.
    #: a sparse step of singletons and one shared cluster is accepted when tight
    sparse_singletons_accept: ClassVar[bool] = False
    #: the type-clash drop applies to steps of at most this many drives; 0: every sparse step
    sparse_type_clash_max_drives: ClassVar[int] = 0
    #: clash-dropped singletons of two or more drives at one spot are kept as a line of unknown type
    sparse_type_clash_keep: ClassVar[bool] = False
    #: drives sharing no cluster are accepted when their samples lie this far apart; 0: off [m]
    sparse_disjoint_apart_m: ClassVar[float] = 0.0

    @property
    def lone_cluster_max_std_m(self) -> float:
        """A step without two clusters of a type (or of one drive) is accepted when every
        cluster's std is at most this (the sparse-step rules' limit; 0 without them: the paper
        rejects such a step) [m]."""
        return self.sparse_step_max_std_m if self.sparse_step_max_drives > 0 else 0.0

    def __post_init__(self) -> None:
        check_choice(self, "clustering", _CLUSTERINGS)
        check_choice(self, "solver", _SOLVERS)
        check_range(self, ("n_iterations",), low=1, integer=True)
        check_range(self, ("sparse_step_max_drives",), low=0, integer=True)
        check_range(self, ("huber_delta_m", "sparse_step_max_std_m"), low=0.0, low_open=True)
        check_range(self, ("prior_weight",), low=0.0)


@dataclass(frozen=True)
class StepAlignment:
    """Result of the EM at one step.

    Attributes:
        offsets_m: (D,) offset per local drive code, to ADD to that drive's samples [m].
        labels: (M,) cluster label per sample, unique across types; -1 = dropped.
        silhouette: score of the final clustering (-1 when undefined).
        valid: silhouette >= gate and at least two clusters.
        n_iterations: EM iterations run.
        types: (M,) the samples' types as aggregated, where a rule changed one (a type clash kept
            as a line of unknown type, ``AlignmentConfig.sparse_type_clash_keep``); None: the
            input types.
    """

    offsets_m: np.ndarray
    labels: np.ndarray
    silhouette: float
    valid: bool
    n_iterations: int
    types: np.ndarray | None = None


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
        end = n
        for kk in range(k, 1, -1):
            end = int(backs[kk][end])
            bounds.append(end)
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
            s = float(silhouette_sorted(xs, lab, np.zeros(n, np.int64)).mean())
            if s > best_s:
                best_s, best_b = s, b
        if best_b is not None and best_s >= single_cluster_silhouette:
            labels_sorted = np.repeat(np.arange(len(best_b) - 1), np.diff(best_b))
    labels = np.empty(n, dtype=np.int64)
    labels[order] = labels_sorted
    return labels


def gap_labels(x: np.ndarray, types: np.ndarray, gap_m: float) -> np.ndarray:
    """Split the samples of every type at sorted gaps wider than ``gap_m``; exact, O(n log n).

    Returns:
        (n,) labels unique across types, increasing with (type, x).
    """
    n = len(x)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((x, types))
    xs, ts = x[order], types[order]
    brk = np.ones(n, dtype=bool)
    brk[1:] = (np.diff(xs) > gap_m) | (ts[1:] != ts[:-1])
    labels = np.empty(n, dtype=np.int64)
    labels[order] = np.cumsum(brk) - 1
    return labels


def cluster_step(x: np.ndarray, types: np.ndarray, *, method: str, config: AlignmentConfig) -> np.ndarray:
    """E-step: cluster every type separately; labels unique across types (M,)."""
    if method == "gap":
        return gap_labels(x, types, GAP_SPLIT_M)
    labels = np.empty(len(x), dtype=np.int64)
    base = 0
    for t in np.unique(types):
        sel = np.flatnonzero(types == t)
        lab = cluster_type(
            x[sel],
            method=method,
            k_max=K_MAX,
            single_cluster_silhouette=SINGLE_CLUSTER_SILHOUETTE,
            gap_split_m=GAP_SPLIT_M,
            min_separation_m=config.min_cluster_separation_m,
        )
        labels[sel] = lab + base
        base += int(lab.max()) + 1 if len(lab) else 0
    return labels


# ----------------------------------------------------------------------------- M-step


def _dense(labels: np.ndarray) -> tuple[np.ndarray, int]:
    """Non-negative labels (M,) renumbered 0..K-1 in their order (``np.unique``'s inverse,
    without the sort: a step has few, small labels) and K."""
    present = np.bincount(labels) > 0
    return (np.cumsum(present) - 1)[labels], int(present.sum())


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


def _closed_form(
    x: np.ndarray,
    labels: np.ndarray,
    drive: np.ndarray,
    n_drives: int,
    w: np.ndarray,
    reg_w: np.ndarray,
    reg_t: np.ndarray,
) -> np.ndarray:
    """Exact minimiser of sum_c (1/n_c) sum_j w_j (x_j + o_dj - mu_c(o))^2 + sum_d reg_w (o_d - reg_t)^2.

    mu_c is the w-weighted mean of the corrected members. The cost is quadratic in o: with
    m[c, d] = sum of w over drive d's members of c, X[c, d] = sum of w x over them and
    W_c, S_c the cluster totals, its Hessian/2 is sum_c (diag(m_c) - m_c m_c^T / W_c) / n_c and
    its gradient/2 at 0 is sum_c (X_c - S_c m_c / W_c) / n_c. The Hessian is a diagonal less
    a rank-K term (K clusters): with K < D it is solved by the Woodbury identity, one K x K
    solve, instead of one D x D solve.
    """
    k = int(labels.max()) + 1
    n_c = np.bincount(labels, minlength=k).astype(float)
    key = labels * n_drives + drive
    m = np.bincount(key, weights=w, minlength=k * n_drives).reshape(k, n_drives)
    xm = np.bincount(key, weights=w * x, minlength=k * n_drives).reshape(k, n_drives)
    wc = np.maximum(m.sum(axis=1), 1e-300)
    sc = xm.sum(axis=1)
    inv_n = 1.0 / n_c
    mn = m * np.sqrt(inv_n / wc)[:, None]
    diag = m.T @ inv_n + reg_w
    g = xm.T @ inv_n - m.T @ (sc * inv_n / wc)
    rhs = reg_w * reg_t - g
    if k >= n_drives:
        return np.linalg.solve(np.diag(diag) - mn.T @ mn, rhs)
    # RULE linear in the drives of a step: (A - N^T N)^-1 b = A^-1 b + A^-1 N^T C^-1 N A^-1 b with
    # A = diag, N = mn (K x D) and C = I - N A^-1 N^T (positive definite as the Hessian is, the
    # ridge > 0); the D x D solve was cubic in the drives (hundreds at 16x paper_like). The
    # offsets agree with it within 1e-13 m there.
    na = mn / diag[None, :]
    cap = np.eye(k) - na @ mn.T
    return rhs / diag + np.linalg.solve(cap, na @ rhs) @ na


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
    labels, k = _dense(labels)
    ctype = np.zeros(k, dtype=types.dtype)
    ctype[labels] = types
    reg_w = np.full(n_drives, config.ridge)
    reg_t = np.zeros(n_drives)
    if prior is not None and config.prior_weight > 0:
        has = np.isfinite(prior)
        reg_w = reg_w + np.where(has, config.prior_weight, 0.0)
        reg_t = np.where(has, config.prior_weight * np.where(has, prior, 0.0) / np.maximum(reg_w, 1e-300), 0.0)
    w = np.ones(len(x))
    n_c = np.bincount(labels, minlength=k).astype(float)
    for it in range(4 if config.robust_loss else 1):
        o = _closed_form(x, labels, drive, n_drives, w, reg_w, reg_t)
        if config.robust_loss and it < 3:
            y = x + o[drive]
            mu = np.bincount(labels, weights=w * y, minlength=k) / np.maximum(
                np.bincount(labels, weights=w, minlength=k), 1e-300
            )
            w_new = np.minimum(1.0, config.huber_delta_m / np.maximum(np.abs(y - mu[labels]), 1e-12))
            if np.array_equal(w_new, w):  # the weights are a fixed point: the next solve is this one
                break
            w = w_new
    s = PENALTY_S_PER_M2
    centres = np.bincount(labels, weights=x + o[drive], minlength=k) / n_c
    # The penalty only acts when two same-type clusters come close; the closed form already
    # minimises the variance term, so LM runs only then (always with solver="lm", the paper's way).
    need_lm = (
        k >= 2 and s > 0 and (config.solver == "lm" or _penalty(centres, ctype, s).max() > config.penalty_lm_threshold)
    )
    if need_lm:
        a, b, mean0, share = _variance_system(x, labels, drive, n_drives)
        row_w = np.sqrt(w)
        sq_reg = np.sqrt(reg_w)

        aw = a * row_w[:, None]
        same = ctype[:, None] == ctype[None, :]
        np.fill_diagonal(same, False)
        has_nb = same.any(axis=1)

        def fun(v: np.ndarray) -> np.ndarray:
            return np.concatenate([aw @ v + b * row_w, _penalty(mean0 + share @ v, ctype, s), sq_reg * (v - reg_t)])

        def jac(v: np.ndarray) -> np.ndarray:
            # Analytic Jacobian: the variance rows are linear; penalty_i = exp(-s d_i^2 / 2) with
            # d_i = |mu_i - mu_j*| to the nearest same-type cluster j*, mu = mean0 + share @ v.
            mu = mean0 + share @ v
            d = np.where(same, np.abs(mu[:, None] - mu[None, :]), np.inf)
            j = np.argmin(d, axis=1)
            diff = mu - mu[j]
            pen = np.where(has_nb, np.exp(-0.5 * s * diff * diff), 0.0)
            jp = (-s * diff * pen)[:, None] * (share - share[j])
            return np.vstack([aw, np.where(has_nb[:, None], jp, 0.0), np.diag(sq_reg)])

        start = o if config.solver == "closed_form" else (np.zeros(n_drives) if init is None else init)
        o = least_squares(fun, start, jac=jac, method="lm", xtol=1e-6, ftol=1e-8).x
    if config.remove_drift:
        # Road midpoint (mean cluster position) after correction = before it.
        key = labels * n_drives + drive
        share = np.bincount(key, minlength=k * n_drives).reshape(k, n_drives) / n_c[:, None]
        o = o - float((share @ o).mean())
    return np.clip(o, -MAX_OFFSET_M, MAX_OFFSET_M)


# ----------------------------------------------------------------------------- EM


def _gap_clusters(y: np.ndarray, types: np.ndarray, gap_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Corrected positions ``y`` (M,) split into per-type clusters at gaps > ``gap_m``:
    labels (M,), cluster centres (K,) [m] and cluster types (K,)."""
    lab = gap_labels(y, types, gap_m)
    k = int(lab.max()) + 1
    centre = np.bincount(lab, weights=y, minlength=k) / np.bincount(lab, minlength=k)
    ctype = np.zeros(k, dtype=types.dtype)
    ctype[lab] = types
    return lab, centre, ctype


def _grid_scores(
    x: np.ndarray, cand: np.ndarray, centre: np.ndarray, allowed: np.ndarray, capture_m: float
) -> np.ndarray:
    """(G, M) score of each sample ``x`` (M,) shifted by each candidate offset ``cand`` (G,):
    max(0, 1 - distance to the nearest allowed cluster centre / ``capture_m``); ``allowed``
    (M, K) marks the clusters a sample may land on."""
    d = np.abs((x[None, :] + cand[:, None])[:, :, None] - centre[None, None, :])  # (G, M, K)
    d = np.where(allowed[None, :, :], d, np.inf).min(axis=2)
    return np.maximum(0.0, 1.0 - d / capture_m)


def match_new_drives(
    x: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    offsets: np.ndarray,
    known: np.ndarray,
    *,
    max_offset_m: float,
    gap_m: float,
    grid_m: float = 0.05,
    capture_m: float = 0.5,
) -> np.ndarray:
    """Offsets of drives without a prior, by matching their samples onto the clusters of the
    drives with one (a 1-D grid search: score = sum over the drive's samples of
    max(0, 1 - distance to the nearest same-type cluster / capture_m)).

    Args:
        x: (M,) raw positions; types: (M,); drive: (M,) local codes; offsets: (D,) current offsets.
        known: (D,) bool, drives whose offsets are trusted.

    Returns:
        (D,) offsets with the unknown drives' filled in (0 when nothing matches).
    """
    out = offsets.copy()
    ks = known[drive]
    if not ks.any():
        return out
    lab, centre, ctype = _gap_clusters(x[ks] + offsets[drive[ks]], types[ks], gap_m)
    k = len(centre)
    n_known = int(known.sum())
    if n_known >= 5:  # clusters of one known drive only (e.g. its misclassified line) do not attract
        nd = int(drive.max()) + 1
        n_dr = np.bincount(np.unique(lab * nd + drive[ks]) // nd, minlength=k)
        ctype = np.where(n_dr >= 2, ctype, -1)
    us = np.flatnonzero(~ks)
    cand = np.arange(-max_offset_m, max_offset_m + 1e-9, grid_m)
    score = _grid_scores(x[us], cand, centre, types[us][:, None] == ctype[None, :], capture_m)  # (G, U)
    ud, inv = np.unique(drive[us], return_inverse=True)
    per = score @ (inv[:, None] == np.arange(len(ud))[None, :]).astype(float)  # (G, Du)
    # Prefer small offsets (localization errors are small more often): a 3 m shift costs less
    # than one matched sample.
    best = np.argmax(per - 0.02 * (cand * cand)[:, None], axis=0)
    ok = per[best, np.arange(len(ud))] > 0
    out[ud[ok]] = cand[best[ok]]
    return out


def recheck_offsets(
    x: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    offsets: np.ndarray,
    *,
    max_offset_m: float,
    gap_m: float,
    grid_m: float = 0.1,
    capture_m: float = 0.5,
    prior_per_m2: float = 0.02,
    min_gain: float = 0.5,
) -> np.ndarray:
    """Move drives that tracking locked onto a wrong place (e.g. one lane off).

    All drives at once: the samples are clustered with the current offsets; each drive's
    absolute offset is scored on a grid by how well its samples land on same-type clusters that
    other drives support, minus ``prior_per_m2 * offset^2`` (small errors are likelier, which
    settles the lane-periodic ties of dashed lines). A drive moves when the best score beats its
    current one by ``min_gain`` (about half a sample).

    Returns:
        (D,) offsets.
    """
    n_drives = len(offsets)
    lab, centre, ctype = _gap_clusters(x + offsets[drive], types, gap_m)
    member = np.zeros((n_drives, len(centre)), dtype=bool)
    member[drive, lab] = True
    support = member.sum(axis=0)
    # (M, K): clusters a sample may land on: same type and supported by other drives (two when
    # there are enough drives, so one drive's misclassified line cannot attract another drive).
    need = 2 if n_drives >= 6 else 1
    ok = (types[:, None] == ctype[None, :]) & ((support[None, :] - member[drive]) >= need)
    cand = np.arange(-max_offset_m, max_offset_m + 1e-9, grid_m)
    score = _grid_scores(x, cand, centre, ok, capture_m)  # (G, M)
    onehot = (drive[:, None] == np.arange(n_drives)[None, :]).astype(float)
    per = score @ onehot - prior_per_m2 * (cand * cand)[:, None]  # (G, D)
    best = np.argmax(per, axis=0)
    # Current place: the best candidate within capture_m of the current offset (the current
    # offset itself is a little off by noise; compare like with like).
    near = np.abs(cand[:, None] - offsets[None, :]) <= capture_m
    cur = np.where(near, per, -np.inf).max(axis=0)
    gain = per[best, np.arange(n_drives)] - cur
    out = offsets.copy()
    move = gain > min_gain
    out[move] = cand[best[move]]
    return out


def register_drives(
    x: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    n_drives: int,
    *,
    max_offset_m: float,
    gap_m: float,
    n_sweeps: int = 1,
) -> np.ndarray:
    """Start offsets for a step without prior: greedy registration, drive after drive.

    The drive with the most samples is the reference (offset 0); every other drive, in order of
    sample count, is matched onto the clusters of the drives placed so far (``match_new_drives``),
    which uses all types at once, so a solid line or a border breaks the lane-periodic ambiguity
    of dashed lines. Drift removal later fixes the gauge.

    Returns:
        (D,) start offsets [m].
    """
    o = np.zeros(n_drives)
    cnt = np.bincount(drive, minlength=n_drives)
    order = np.argsort(-cnt, kind="stable")
    known = np.zeros(n_drives, dtype=bool)
    known[order[0]] = True
    for d in order[1:]:
        if cnt[d] == 0:
            continue
        sel = known[drive] | (drive == d)
        kd = known.copy()
        o = match_new_drives(x[sel], types[sel], drive[sel], o, kd, max_offset_m=max_offset_m, gap_m=gap_m)
        known[d] = True
    # Second sweep: every drive again against all others, so early drives (matched against few
    # clusters) can move to a better-supported place.
    for _ in range(n_sweeps):
        for d in order:
            if cnt[d] == 0:
                continue
            kd = known.copy()
            kd[d] = False
            o = match_new_drives(x, types, drive, o, kd, max_offset_m=max_offset_m, gap_m=gap_m)
    return o


def _drop_thin_clusters(labels: np.ndarray, drive: np.ndarray, min_drives: int) -> np.ndarray:
    if min_drives <= 1:
        return labels
    use = labels >= 0
    nd = int(drive.max()) + 1
    n_dr = np.bincount(np.unique(labels[use] * nd + drive[use]) // nd, minlength=int(labels.max()) + 1)
    out = labels.copy()
    out[use & (n_dr[np.maximum(labels, 0)] < min_drives)] = -1
    return out


def silhouette_sorted(xs: np.ndarray, run: np.ndarray, group: np.ndarray) -> np.ndarray:
    """Silhouette of 1-D samples whose clusters are contiguous runs of the sorted order, O(n).

    In 1-D with contiguous clusters the nearest other cluster of a sample is a neighbouring run,
    and summed distances to a run follow from prefix sums, so no distance matrix is needed.

    Args:
        xs: (n,) values sorted ascending within each group.
        run: (n,) cluster id, non-decreasing, consecutive runs 0..R-1.
        group: (n,) group id (e.g. type); silhouettes only compare clusters of one group.

    Returns:
        (n,) silhouette per sample; NaN where the group has a single cluster; 0 for singletons.
    """
    n = len(xs)
    if n == 0:
        return np.zeros(0)
    r = int(run[-1]) + 1
    start = np.searchsorted(run, np.arange(r + 1))
    s = np.concatenate([[0.0], np.cumsum(xs)])
    rgroup = group[start[:-1]]
    i = np.arange(n)
    a0, b0 = start[run], start[run + 1]
    cnt = b0 - a0
    own = (i - a0) * xs - (s[i] - s[a0]) + (s[b0] - s[i + 1]) - (b0 - i - 1) * xs
    a = own / np.maximum(cnt - 1, 1)
    rsum = s[start[1:]] - s[start[:-1]]
    rmean = rsum / np.diff(start)
    has_l = (run > 0) & (rgroup[np.maximum(run - 1, 0)] == group)
    has_r = (run < r - 1) & (rgroup[np.minimum(run + 1, r - 1)] == group)
    dl = np.where(has_l, xs - rmean[np.maximum(run - 1, 0)], np.inf)
    dr = np.where(has_r, rmean[np.minimum(run + 1, r - 1)] - xs, np.inf)
    b = np.minimum(dl, dr)
    with np.errstate(invalid="ignore", divide="ignore"):
        sil = (b - a) / np.maximum(a, b)
    sil = np.where((cnt > 1) & np.isfinite(sil), sil, 0.0)
    return np.where(np.isfinite(b), sil, np.nan)


def step_silhouette(x: np.ndarray, labels: np.ndarray, types: np.ndarray, *, skip_singletons: bool = False) -> float:
    """Mean silhouette of a step's labelled samples, each type scored on its own clusters.

    Clustering is per type (Sec. IV-B), so the score is too: samples of types with at least two
    clusters count; -1 when no type has two clusters. ``skip_singletons``: the mean leaves out
    the samples of one-sample clusters (their silhouette is 0 by definition; they still count
    as the nearest cluster of others).
    """
    use = labels >= 0
    x, labels, types = x[use], labels[use], types[use]
    if len(x) < 2:
        return -1.0
    sil, ls = _silhouette_values(x, labels, types)
    ok = np.isfinite(sil)
    if skip_singletons:
        _, inv, cnt = np.unique(ls, return_inverse=True, return_counts=True)
        ok &= cnt[inv] > 1
    return float(sil[ok].mean()) if ok.any() else -1.0


def _silhouette_values(x: np.ndarray, labels: np.ndarray, types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample silhouettes (NaN where the type has one cluster) and labels, in (type, x) order."""
    order = np.lexsort((x, types))
    xs, ls, ts = x[order], labels[order], types[order]
    change = np.ones(len(xs), dtype=bool)
    change[1:] = (ls[1:] != ls[:-1]) | (ts[1:] != ts[:-1])
    run = np.cumsum(change) - 1
    if run[-1] + 1 == np.count_nonzero(np.bincount(ls)):
        sil = silhouette_sorted(xs, run, ts)
    else:  # clusters interleave (not contiguous): general per-type silhouette
        sil = np.full(len(xs), np.nan)
        for t in np.unique(ts):
            sel = ts == t
            if len(np.unique(ls[sel])) >= 2:
                sil[sel] = silhouette_samples_1d(xs[sel], ls[sel])
    return sil, ls


def align_step(
    lateral_m: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    *,
    config: AlignmentConfig,
    prior: np.ndarray | None = None,
    init: np.ndarray | None = None,
    recheck: bool = False,
) -> StepAlignment:
    """EM lateral offset estimation at one step (Sec. IV-B).

    Args:
        lateral_m: (M,) sample positions along the cut [m].
        types: (M,) FeatureType codes.
        drive: (M,) local drive codes 0..D-1 (D = max + 1).
        config: EM options.
        prior: optional (D,) prior offsets (NaN where unknown), e.g. the previous step's.
        init: optional (D,) start offsets (NaN where unknown) for drives without a prior, e.g.
            remembered from earlier pivots; used to start from, not as a prior.
        recheck: with "auto", first move drives locked onto a wrong place (``recheck_offsets``).

    Returns:
        The offsets, final labels and silhouette gate decision.
    """
    x = np.asarray(lateral_m, dtype=float)
    n_drives = int(drive.max()) + 1 if len(drive) else 0
    if len(x) == 0:
        return StepAlignment(np.zeros(0), np.zeros(0, np.int64), -1.0, False, 0)
    o = np.zeros(n_drives)
    known = np.zeros(n_drives, dtype=bool) if prior is None else np.isfinite(prior)
    if prior is not None:
        o = np.where(known, prior, 0.0)
    if init is not None:
        fill = ~known & np.isfinite(init)
        o = np.where(fill, init, o)
        known = known | fill
    if config.clustering != "auto" or not config.estimate_offsets:
        return _em(
            x, types, drive, o, prior, method=config.clustering if config.clustering != "auto" else "gap", config=config
        )
    # Tracking: drives carried over from the previous step keep their offsets, new ones are
    # matched onto the clusters those form, then gaps separate the clusters. Without a
    # carried-over drive, or when the tracked result fails the gate (a drive may have locked onto
    # the wrong lane), the step is registered from scratch: greedy matching of drive after drive.
    res = None
    if known.any():
        if not known.all():
            o = match_new_drives(x, types, drive, o, known, max_offset_m=MAX_OFFSET_M, gap_m=GAP_SPLIT_M)
        if recheck:
            o2 = recheck_offsets(x, types, drive, o, max_offset_m=MAX_OFFSET_M, gap_m=GAP_SPLIT_M)
            moved = o2 != o
            if moved.any():
                o = o2
                if prior is not None:  # a moved drive must not be pulled back by its prior
                    prior = np.where(moved, np.nan, prior)
        res = _em(x, types, drive, o, prior, method="gap", config=config)
        if res.valid:
            return res
    o0 = register_drives(x, types, drive, n_drives, max_offset_m=MAX_OFFSET_M, gap_m=GAP_SPLIT_M)
    fresh = _em(x, types, drive, o0, None, method="gap", config=config)
    if res is None or fresh.silhouette > res.silhouette:
        return fresh
    return res


def align_steps_gap(
    lateral_m: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    ptr: np.ndarray,
    steps: np.ndarray,
    *,
    config: AlignmentConfig,
) -> dict[int, StepAlignment]:
    """``align_step`` without offset estimation ("gap" clustering), for many steps at once.

    With ``estimate_offsets=False`` a step is its samples split at gaps and scored by silhouette,
    independent of every other step, so all steps of a pivot are clustered and scored in one
    sorted pass (groups = (step, type)). Steps that a special rule judges (few drives: the
    sparse-step rule; no type with two clusters: the lone-cluster rule) are left out of the
    result; the caller runs ``align_step`` on those.

    Args:
        lateral_m, types, drive: samples of all steps back to back; ``drive`` may be any codes
            (only whether two samples share a drive matters).
        ptr: (Q + 1,) step q's samples are ``ptr[q]:ptr[q + 1]``.
        steps: the step indices to align.

    Returns:
        {step: StepAlignment} for the steps decided here (offsets are zeros of the step's
        number of distinct drives).
    """
    if not gap_batchable(config):
        raise ConfigError("align_steps_gap needs estimate_offsets=False, clustering='gap', min_cluster_drives <= 1")
    steps = np.asarray(steps, dtype=np.int64)
    n_in = ptr[steps + 1] - ptr[steps]
    steps = steps[n_in >= 2]
    if len(steps) == 0:
        return {}
    n_in = ptr[steps + 1] - ptr[steps]
    idx = np.repeat(ptr[steps] - np.concatenate([[0], np.cumsum(n_in)[:-1]]), n_in) + np.arange(int(n_in.sum()))
    owner = np.repeat(np.arange(len(steps)), n_in)
    x, ty, dv = lateral_m[idx], types[idx].astype(np.int64), drive[idx]
    order = np.lexsort((x, ty, owner))
    xs, ts, os_ = x[order], ty[order], owner[order]
    n = len(xs)
    new_group = np.ones(n, dtype=bool)
    new_group[1:] = (ts[1:] != ts[:-1]) | (os_[1:] != os_[:-1])
    brk = new_group.copy()
    brk[1:] |= np.diff(xs) > GAP_SPLIT_M
    run = np.cumsum(brk) - 1
    group = np.cumsum(new_group) - 1
    sil = silhouette_sorted(xs, run, group)
    ok = np.isfinite(sil)
    cnt = np.bincount(os_[ok], minlength=len(steps))
    score = np.where(cnt > 0, np.bincount(os_[ok], weights=sil[ok], minlength=len(steps)) / np.maximum(cnt, 1), -1.0)
    nd = int(dv.max()) + 1
    n_drv = np.bincount(np.unique(owner * np.int64(nd) + dv) // nd, minlength=len(steps))  # distinct drives per step
    special = (score == -1.0) | (n_drv <= max(config.sparse_step_max_drives, 1))
    labels_sorted = run - np.repeat(
        run[np.searchsorted(os_, np.arange(len(steps)))], np.bincount(os_, minlength=len(steps))
    )
    labels = np.empty(n, dtype=np.int64)
    labels[order] = labels_sorted
    first = np.concatenate([[0], np.cumsum(n_in)])
    out: dict[int, StepAlignment] = {}
    for j in np.flatnonzero(~special):
        out[int(steps[j])] = StepAlignment(
            offsets_m=np.zeros(int(n_drv[j])),
            labels=labels[first[j] : first[j + 1]],
            silhouette=float(score[j]),
            valid=bool(score[j] >= config.silhouette_gate),
            n_iterations=1,
        )
    return out


def gap_batchable(config: AlignmentConfig) -> bool:
    """Whether ``align_steps_gap`` can align steps under ``config`` (no offsets, gap clustering)."""
    return not config.estimate_offsets and config.clustering == "gap" and config.min_cluster_drives <= 1


def _em(
    x: np.ndarray,
    types: np.ndarray,
    drive: np.ndarray,
    o: np.ndarray,
    prior: np.ndarray | None,
    *,
    method: str,
    config: AlignmentConfig,
) -> StepAlignment:
    """E-step / M-step iterations from the start offsets ``o``."""
    n_drives = len(o)
    labels: np.ndarray | None = None
    it, n_rounds = 0, (config.n_iterations if config.estimate_offsets else 1)
    while it < n_rounds:
        it += 1
        new = cluster_step(x + o[drive], types, method=method, config=config)
        new = _drop_thin_clusters(new, drive, config.min_cluster_drives)
        if labels is not None and np.array_equal(new, labels):
            break
        labels = new
        if not config.estimate_offsets:
            break
        o = solve_offsets(x, labels, types, drive, n_drives, config=config, prior=prior, init=o)
    assert labels is not None, "AlignmentConfig checks n_iterations >= 1: the loop ran"
    y = x + o[drive]
    n_present = np.count_nonzero(np.bincount(drive))
    sparse = 0 < n_present <= config.sparse_step_max_drives
    clash_max = config.sparse_type_clash_max_drives or config.sparse_step_max_drives
    before_clash = labels
    if sparse and config.sparse_type_clash_m > 0 and n_present <= clash_max:
        labels = _drop_type_clashing_singletons(y, labels, types, drive, config.sparse_type_clash_m)
    score = step_silhouette(y, labels, types)
    valid = score >= config.silhouette_gate
    if sparse and not valid and score != -1.0:
        # Few drives: lines one drive sees and the other misses are singletons (silhouette 0);
        # judge the step by the clusters both see, and by every cluster being tight.
        paired = step_silhouette(y, labels, types, skip_singletons=True)
        valid = _max_cluster_std(y, labels) <= config.sparse_step_max_std_m and (
            paired >= config.silhouette_gate
            # RULE sparse singletons: no cluster of two or more samples in a type with two
            # clusters, so nothing is left to score: judged like a lone-cluster step when the
            # drives agree somewhere, or (RULE disjoint drives) share no line and contradict
            # none (docs/pipeline.md)
            or (
                config.sparse_singletons_accept
                and paired == -1.0
                and (
                    _shared_cluster(labels, drive)
                    or (
                        config.sparse_disjoint_apart_m > 0
                        and _drives_apart(y, labels, drive, config.sparse_disjoint_apart_m)
                    )
                )
            )
        )
    use = labels >= 0
    one_drive = bool(use.any()) and bool(np.all(drive[use] == drive[use][0]))
    if (score == -1.0 or (one_drive and not valid)) and config.lone_cluster_max_std_m > 0:
        # No type has two clusters (e.g. one drive on a ramp seeing one line of each type), or
        # one drive alone (one sample per line: every cluster a singleton, silhouette 0): the
        # silhouette says nothing; accept when every cluster is tight.
        if use.any():
            valid = _max_cluster_std(y, labels) <= config.lone_cluster_max_std_m
    out_types = None
    if valid and config.sparse_type_clash_keep and labels is not before_clash:
        labels, out_types = _keep_clashes(y, before_clash, labels, types, drive, config.sparse_type_clash_m)
    return StepAlignment(
        offsets_m=o, labels=labels, silhouette=score, valid=bool(valid), n_iterations=it, types=out_types
    )


def _keep_clashes(
    y: np.ndarray, before: np.ndarray, labels: np.ndarray, types: np.ndarray, drive: np.ndarray, radius_m: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """RULE type clash kept: the samples the clash drop removed (labelled before, -1 after) that
    lie within ``radius_m`` of each other in a chain, and of no other sample, form one cluster of
    type UNKNOWN per chain of two or more drives and two or more types. (Such a line becomes the
    marking it continues; it never continues a road border, ``hdmap_core.graph.flat``.) Returns
    (labels, types or None)."""
    dropped = (before >= 0) & (labels < 0)
    gone = np.flatnonzero(dropped)
    if len(gone) < 2:
        return labels, None
    gone = gone[np.argsort(y[gone], kind="stable")]
    # a chain may not come near a sample that is kept (or was dropped by another rule): then the
    # line is that sample's, of its type
    y_other = y[~dropped]
    brk = np.r_[True, np.diff(y[gone]) > radius_m]
    chain = np.cumsum(brk) - 1
    out, out_t = labels.copy(), None
    nxt = int(labels.max()) + 1
    for c in range(int(chain[-1]) + 1):
        mem = gone[chain == c]
        if len(np.unique(drive[mem])) < 2 or len(np.unique(types[mem])) < 2:
            continue
        lo, hi = y[mem].min() - radius_m, y[mem].max() + radius_m
        if np.any((y_other >= lo) & (y_other <= hi)):
            continue
        if out_t is None:
            out_t = np.asarray(types).copy()
        out[mem] = nxt
        out_t[mem] = int(FeatureType.UNKNOWN)
        nxt += 1
    return out, out_t


def _shared_cluster(labels: np.ndarray, drive: np.ndarray) -> bool:
    """Whether some cluster holds samples of two or more drives (the drives agree somewhere)."""
    use = labels >= 0
    if not use.any():
        return False
    pairs = np.unique(np.stack([labels[use], drive[use]], axis=1), axis=0)
    return bool((np.bincount(pairs[:, 0]) >= 2).any())


def _drives_apart(y: np.ndarray, labels: np.ndarray, drive: np.ndarray, apart_m: float) -> bool:
    """Whether the kept samples (labels >= 0) of two or more drives are, between any two
    different drives, at least ``apart_m`` apart."""
    use = labels >= 0
    if len(np.unique(drive[use])) < 2:
        return False  # one drive's samples alone: the one-drive rule judges them
    yy, dd = y[use], drive[use]
    near = (np.abs(yy[:, None] - yy[None, :]) < apart_m) & (dd[:, None] != dd[None, :])
    return not bool(near.any())


def _max_cluster_std(y: np.ndarray, labels: np.ndarray) -> float:
    """Largest std of a cluster's corrected positions (labels >= 0); inf when nothing is labelled."""
    use = labels >= 0
    if not use.any():
        return float("inf")
    lab, yy = labels[use], y[use]
    k = int(lab.max()) + 1
    n = np.bincount(lab, minlength=k)
    mean = np.bincount(lab, weights=yy, minlength=k) / np.maximum(n, 1)
    var = np.bincount(lab, weights=yy**2, minlength=k) / np.maximum(n, 1) - mean**2
    return float(np.sqrt(np.maximum(var[n > 0], 0.0)).max())


def _drop_type_clashing_singletons(
    y: np.ndarray, labels: np.ndarray, types: np.ndarray, drive: np.ndarray, radius_m: float
) -> np.ndarray:
    """Label -1 for one-sample clusters with another drive's sample of another type within
    ``radius_m``.

    With two drives, a line one classifies as solid and the other as dashed becomes two
    singletons side by side; neither is evidence of a line of its type. (One drive's own
    samples of two types close together, e.g. a line beside the road border, are no clash.)
    """
    use = labels >= 0
    if not use.any():
        return labels
    cnt = np.bincount(labels[use], minlength=int(labels.max()) + 1)
    single = np.flatnonzero(use & (cnt[np.maximum(labels, 0)] == 1))
    if len(single) == 0:
        return labels
    # All samples count as witnesses (also dropped ones: the other drive still saw something there).
    near = np.abs(y[single][:, None] - y[None, :]) <= radius_m
    other = (types[single][:, None] != types[None, :]) & (drive[single][:, None] != drive[None, :])
    clash = (near & other).any(axis=1)
    out = labels.copy()
    out[single[clash]] = -1
    return out
