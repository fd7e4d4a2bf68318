"""Network-wide lateral offset adjustment: one smooth offset curve per drive, all steps jointly.

Beyond the paper (Immel et al. 2023, Sec. IV-B estimates one offset per drive per step). The
per-step estimate only sees the N drives crossing a cut, so their common offset stays in the map
(about sigma/sqrt(N)). Here every drive's lateral offset is a curve along its travelled distance
``s``, estimated jointly from all steps of all drives in one sparse least-squares adjustment (like
a pose graph):

    lateral_i + o_{d(i)}(s_i) = x_{j, c(i)} + noise_i           (one row per clustered sample)
    o_d(s) = b_d + g_d(s),  g_d piecewise linear on knots s = k * knot_spacing_m
    b_d ~ N(0, bias_sigma^2)                                     (fleet offsets have zero mean)
    g_{d,0} ~ N(0, drift_sigma^2),  g_{d,k+1} - phi g_{d,k} ~ N(0, drift_sigma^2 (1 - phi^2)),
    phi = exp(-knot_spacing / correlation_length)                (exact first-order Gauss-Markov)

The cluster positions x (one per cluster and step; they also absorb the pivot's own error) are
nuisance parameters, eliminated in closed form (Schur complement: subtract the weighted cluster
mean). The association is re-derived globally (raw-position association, per-drive lane-shift
search, re-association with the fitted offsets: a global EM), a coarse one-constant-per-drive fit
drops lane-off stretches, and IRLS with a Huber or Cauchy loss handles the remaining wrong
associations. Only the gauge that
the data cannot see (a shift common to all drives at a place) is set by the priors, which is what
ties every place to the whole chain of overlapping drives. See docs/adjustment.md.

Observations are ``hdmap_core.steps.StepObservations`` (duck-typed here: only ``drive_ids``,
``drive_s_m``, ``lateral_m``, ``types`` and ``cluster`` are read; ``pivot_id``/``index`` name bad
steps). The association (re-clustering all samples, lane-shift search) is in
``hdmap_core.pipeline.adjustment_assoc``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Protocol

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hdmap_core.checks import check_choice, check_range
from hdmap_core.errors import ConfigError
from hdmap_core.parallel import one_blas_thread
from hdmap_core.pipeline import adjustment_assoc as assoc
from hdmap_core.pipeline.adjustment_coarse import coarse_basis, drive_links, place_sums
from hdmap_core.pipeline.adjustment_schur import SchurNormal, SchurSolver, pair_fill
from hdmap_core.pipeline.offset_table import OffsetTable, knot_position, offset_table

__all__ = ["AdjustConfig", "OffsetModel", "OffsetSource", "DriveOffset", "adjust_offsets"]
# The solver's building blocks (shift_and_reassociate, knot_layout, layout_of, design_matrix,
# prior_matrix, reduced_normal, NormalSolver, update_normal, rebuilds, kept_weights,
# sample_residuals, robust_weights, pool_offsets, coarse_config, covariance_parts, drive_curves)
# are public but not in __all__:
# adjustment_local.update_offsets solves new drives with them against a fixed fleet, and
# adjustment_dist runs the same solve over observations split into parts.

_LOSSES = ("linear", "huber", "cauchy")
_REWEIGHT_REL = 0.05  # IRLS: a sample is re-weighted only when its weight changes by more than 5 %
# Rules of the robust fit, fixed since docs/adjustment.md measured them:
#: the robust loss's threshold in units of ``AdjustConfig.noise_sigma_m``
ROBUST_K = 2.5
#: with ``loss="cauchy"``, the first IRLS iterations use Huber (a convex start keeps Cauchy from
#: locking onto a wrong solution)
HUBER_WARMUP_ITERATIONS = 2
#: stop re-weighting when no offset changes by more than this [m]
TOL_M = 2e-3
#: after a fit, samples farther than this from every centre are dropped [m]
REASSOCIATE_GATE_M = 1.0
#: before each re-association, every drive's offset is searched for a constant shift within
#: +-this (0.25 m grid, truncated-quadratic cost on the nearest centres of the same type): repairs
#: drives associated a whole lane off [m]
SHIFT_SEARCH_M = 4.5
#: the fit uses every step seen by at most this many drives, and every ceil(d / THIN_DRIVES)-th
#: step of those seen by d more. The cost of a step grows with d^2 (its cluster positions couple
#: all its drives); thinned, the fit grows linearly with the fleet while a drive still has dozens
#: of steps per knot (re-association and the lane-shift search still use every step;
#: docs/adjustment.md, "Model")
THIN_DRIVES = 16


@dataclass(frozen=True)
class AdjustConfig:
    """Settings of the offset adjustment (lengths in metres).

    Attributes:
        knot_spacing_m: distance between the knots of a drive's offset curve (global grid
            ``k * knot_spacing_m`` in the drive's travelled distance, so knots are stable when
            a drive is re-adjusted with more data).
        bias_sigma_m: prior sigma of a drive's constant lateral bias (the gauge prior).
        drift_sigma_m: stationary sigma of the Gauss-Markov drift; 0 = constant offset per drive.
        correlation_length_m: correlation length of the drift.
        noise_sigma_m: sigma of one sample's lateral position about its cluster, after correction.
        loss: ``"linear"`` (plain least squares), ``"huber"`` or ``"cauchy"``.
        iterations: maximum number of solves (1 = no re-weighting).
        reassociate_rounds: 0 = use the observations' cluster labels as given. > 0: first
            re-associate every sample to the nearest cluster centre of its step and type by raw
            position (centres: medians of the members' raw positions), fit, then this many times
            re-associate with the fitted offsets applied and fit again (a global EM; it repairs
            per-step associations that were a lane off).
        compute_std: compute the posterior std of the offsets (exact, from a dense inverse of the
            normal matrix; O(p^3) in the number of unknowns p; at most ``std_max_unknowns``).
    """

    knot_spacing_m: float = 200.0
    bias_sigma_m: float = 1.0
    drift_sigma_m: float = 0.3
    correlation_length_m: float = 1000.0
    noise_sigma_m: float = 0.12
    loss: str = "huber"
    iterations: int = 5
    reassociate_rounds: int = 2
    compute_std: bool = True

    #: before the curves are fitted, one constant per drive is fitted (Huber); samples farther
    #: than this from their cluster then are dropped as wrong associations (a drive associated
    #: one lane off over a stretch, which a curve would follow) [m]
    coarse_reject_m: ClassVar[float] = 1.5
    #: above this many unknowns the std is not computed (left NaN)
    std_max_unknowns: ClassVar[int] = 4000
    #: RULE a fit whose normal matrix would hold more drive-pair entries than this
    #: (``adjustment_schur.pair_fill``: pairs of unknowns that share a cluster) is solved
    #: matrix-free (conjugate gradients on the Schur complement, the same solution within 1e-10
    #: relative residual), in memory and time linear in the samples; below it the normal matrix
    #: is formed and factorised (faster there: 4x paper_like's one fit, 2.65 M entries, 5.9 CPU-s
    #: explicit against 14.2 matrix-free). Where many drives cross a place (hundreds: 16x
    #: paper_like) the explicit matrix grows with their square. A solver's budget, not a knob of
    #: the method: the offsets are the same either way.
    max_pair_fill: ClassVar[int] = 4_000_000

    def __post_init__(self) -> None:
        check_range(
            self,
            ("knot_spacing_m", "bias_sigma_m", "correlation_length_m", "noise_sigma_m"),
            low=0.0,
            low_open=True,
            finite=True,
        )
        check_range(self, ("drift_sigma_m",), low=0.0, finite=True)
        check_choice(self, "loss", _LOSSES)
        check_range(self, ("iterations",), low=1, integer=True)
        check_range(self, ("reassociate_rounds",), low=0, integer=True)


@dataclass(frozen=True)
class DriveOffset:
    """The estimated offset curve of one drive: ``o(s) = bias_m + drift(s)``.

    Attributes:
        k0: index of the first knot; knot k sits at ``(k0 + k) * knot_spacing_m`` of travelled distance.
        bias_m: posterior mean of the constant part.
        drift_m: (K,) posterior mean of the drift at the knots (K = 0 without drift).
        var_bias: posterior variance of the bias [m^2] (NaN when not computed).
        cov_bias_drift: (K,) covariance bias/knot.
        var_drift: (K,) variance per knot.
        cov_drift_next: (K-1,) covariance of consecutive knots.
    """

    k0: int
    bias_m: float
    drift_m: np.ndarray
    var_bias: float = float("nan")
    cov_bias_drift: np.ndarray = field(default_factory=lambda: np.zeros(0))
    var_drift: np.ndarray = field(default_factory=lambda: np.zeros(0))
    cov_drift_next: np.ndarray = field(default_factory=lambda: np.zeros(0))


class OffsetSource(Protocol):
    """What the final pass reads of an offset model (an ``OffsetModel``, or one seen through a
    change of travelled distance such as a live tile's clip): the offsets of one drive, and of
    many drives at once where the source can give them so."""

    def offset(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        """Lateral offset [m] to add to ``drive_id``'s samples at travelled distances ``s_m``."""
        ...

    def table(self, drive_ids: Sequence[str]) -> OffsetTable | None:
        """The offsets of ``drive_ids`` (drive i: ``drive_ids[i]``) as one ``OffsetTable``, the
        same values as ``offset`` to the last bit; None where the source has no such table (it
        is then read drive by drive with ``offset``)."""
        ...


@dataclass(frozen=True)
class OffsetModel:
    """Per-drive lateral offset curves; ``offset(drive, s)`` is to be ADDED to that drive's samples.

    Outside a drive's knot range the drift decays towards 0 as the Gauss-Markov prior predicts
    (``exp(-distance / correlation_length)``); unknown drives get offset 0 and the prior std.
    """

    knot_spacing_m: float
    correlation_length_m: float
    drift_sigma_m: float
    bias_sigma_m: float
    drives: dict[str, DriveOffset] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict, compare=False)

    def _locate(self, cur: DriveOffset, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Knot index k (0..K-2), fraction t in [0, 1], decay factor rho and inside-mask per s."""
        u = s_m / self.knot_spacing_m - cur.k0
        k, t, rho, outside_m = knot_position(u, cur.drift_m.size, self.knot_spacing_m, self.correlation_length_m)
        return k, t, rho, outside_m > 0

    def offset(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        """Lateral offset [m] to add to ``drive_id``'s samples at travelled distances ``s_m`` (any shape)."""
        s = np.asarray(s_m, dtype=float)
        cur = self.drives.get(drive_id)
        if cur is None:
            return np.zeros(s.shape)
        if cur.drift_m.size == 0:
            return np.full(s.shape, cur.bias_m)
        k, t, rho, _ = self._locate(cur, s)
        g = (1.0 - t) * cur.drift_m[k] + t * cur.drift_m[k + 1]
        return cur.bias_m + rho * g

    def table(self, drive_ids: Sequence[str]) -> OffsetTable:
        """The curves of ``drive_ids`` as one ``OffsetTable`` (drive i: ``drive_ids[i]``): the
        offsets of many drives at once, the same values as ``offset``."""
        return offset_table(self, drive_ids)

    def std(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        """Posterior 1-sigma of ``offset(drive_id, s_m)`` [m]; NaN when it was not computed."""
        s = np.asarray(s_m, dtype=float)
        cur = self.drives.get(drive_id)
        prior_var = self.bias_sigma_m**2 + self.drift_sigma_m**2
        if cur is None:
            return np.full(s.shape, np.sqrt(prior_var))
        if cur.drift_m.size == 0:
            return np.full(s.shape, np.sqrt(cur.var_bias))
        k, t, rho, _ = self._locate(cur, s)
        k1 = np.minimum(k + 1, cur.drift_m.size - 1)
        t = np.where(k1 == k, 0.0, t)
        cov_next = np.append(cur.cov_drift_next, 0.0)[k]
        var_g = (1 - t) ** 2 * cur.var_drift[k] + t**2 * cur.var_drift[k1] + 2 * t * (1 - t) * cov_next
        cov_bg = (1 - t) * cur.cov_bias_drift[k] + t * cur.cov_bias_drift[k1]
        var = cur.var_bias + rho**2 * var_g + 2 * rho * cov_bg + self.drift_sigma_m**2 * (1 - rho**2)
        return np.sqrt(np.maximum(var, 0.0))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (plain floats, ints and lists); NaN variances are written as None."""

        def _list(a: np.ndarray | list[float]) -> list:
            return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, dtype=float)]

        return {
            "format": "hdmap.offset_model",
            "version": 1,
            "knot_spacing_m": self.knot_spacing_m,
            "correlation_length_m": self.correlation_length_m,
            "drift_sigma_m": self.drift_sigma_m,
            "bias_sigma_m": self.bias_sigma_m,
            "drives": {
                did: {
                    "k0": int(c.k0),
                    "bias_m": float(c.bias_m),
                    "drift_m": _list(c.drift_m),
                    "var_bias": _list([c.var_bias])[0],
                    "cov_bias_drift": _list(c.cov_bias_drift),
                    "var_drift": _list(c.var_drift),
                    "cov_drift_next": _list(c.cov_drift_next),
                }
                for did, c in self.drives.items()
            },
            "stats": _jsonable(self.stats),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OffsetModel:
        """Inverse of :meth:`to_dict`; raises ConfigError on a malformed dict."""

        def _arr(v: list) -> np.ndarray:
            return np.array([np.nan if x is None else x for x in v], dtype=float)

        try:
            if data.get("format") != "hdmap.offset_model":
                raise ConfigError(f"not an offset model dict (format={data.get('format')!r})")
            drives = {
                str(did): DriveOffset(
                    k0=int(c["k0"]),
                    bias_m=float(c["bias_m"]),
                    drift_m=_arr(c["drift_m"]),
                    var_bias=float("nan") if c["var_bias"] is None else float(c["var_bias"]),
                    cov_bias_drift=_arr(c["cov_bias_drift"]),
                    var_drift=_arr(c["var_drift"]),
                    cov_drift_next=_arr(c["cov_drift_next"]),
                )
                for did, c in data["drives"].items()
            }
            return cls(
                knot_spacing_m=float(data["knot_spacing_m"]),
                correlation_length_m=float(data["correlation_length_m"]),
                drift_sigma_m=float(data["drift_sigma_m"]),
                bias_sigma_m=float(data["bias_sigma_m"]),
                drives=drives,
                stats=dict(data.get("stats", {})),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as err:
            raise ConfigError(f"malformed offset model dict: {err!r}") from err


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


# ---------------------------------------------------------------------------------------------
# The linear system
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    k0: np.ndarray  # (D,) first knot index per drive
    n_knots: np.ndarray  # (D,) knots per drive (0 without drift)
    col0: np.ndarray  # (D,) column of the bias; knots follow
    n_unknowns: int


def knot_layout(samples: assoc.Samples, cfg: AdjustConfig) -> _Layout:
    n_drives = len(samples.drive_ids)
    smin = np.full(n_drives, np.inf)
    smax = np.full(n_drives, -np.inf)
    if cfg.drift_sigma_m != 0:
        np.minimum.at(smin, samples.drive, samples.s_m)
        np.maximum.at(smax, samples.drive, samples.s_m)
    return layout_of(smin, smax, cfg)


def layout_of(smin: np.ndarray, smax: np.ndarray, cfg: AdjustConfig) -> _Layout:
    """The unknowns of drives whose used samples span ``smin`` .. ``smax`` (per drive) [m]."""
    n_drives = smin.size
    if cfg.drift_sigma_m == 0:
        n_knots = np.zeros(n_drives, dtype=np.int64)
        k0 = np.zeros(n_drives, dtype=np.int64)
    else:
        k0 = np.floor(smin / cfg.knot_spacing_m).astype(np.int64)
        k1 = np.maximum(np.ceil(smax / cfg.knot_spacing_m).astype(np.int64), k0 + 1)
        n_knots = k1 - k0 + 1
    col0 = np.concatenate([[0], np.cumsum(1 + n_knots)[:-1]]).astype(np.int64)
    return _Layout(k0, n_knots, col0, int((1 + n_knots).sum()))


def design_matrix(samples: assoc.Samples, lay: _Layout, cfg: AdjustConfig) -> sp.csr_matrix:
    """(n, p) matrix A with o(s_i) = A[i] @ theta (bias + linear interpolation of the drift)."""
    n = samples.s_m.size
    d = samples.drive
    if cfg.drift_sigma_m == 0:
        cols, vals = lay.col0[d][:, None], np.ones((n, 1))
    else:
        u = samples.s_m / cfg.knot_spacing_m - lay.k0[d]
        k = np.clip(np.floor(u), 0, lay.n_knots[d] - 2).astype(np.int64)
        t = u - k
        cols = np.stack([lay.col0[d], lay.col0[d] + 1 + k, lay.col0[d] + 2 + k], axis=1)
        vals = np.stack([np.ones(n), 1.0 - t, t], axis=1)
    # every row has the same number of entries, in increasing column order: build CSR directly
    indptr = np.arange(0, cols.size + 1, cols.shape[1], dtype=np.int64)
    return sp.csr_matrix((vals.ravel(), cols.ravel(), indptr), shape=(n, lay.n_unknowns))


def prior_matrix(lay: _Layout, cfg: AdjustConfig) -> sp.csr_matrix:
    """(p, p) prior information: bias ~ N(0, sb^2), drift an exact AR(1) chain on the knots."""
    diag_b = sp.csr_matrix(
        (np.full(lay.col0.size, cfg.bias_sigma_m**-2), (lay.col0, lay.col0)), shape=(lay.n_unknowns,) * 2
    )
    if cfg.drift_sigma_m == 0:
        return diag_b
    phi = np.exp(-cfg.knot_spacing_m / cfg.correlation_length_m)
    first = lay.col0 + 1
    # rows of the whitened prior Jacobian J: g_0 / sd, (g_{k+1} - phi g_k) / (sd sqrt(1 - phi^2))
    n_inc = lay.n_knots - 1
    inc_start = np.repeat(first, n_inc) + (np.arange(n_inc.sum()) - np.repeat(np.cumsum(n_inc) - n_inc, n_inc))
    n_first, n_rows = first.size, first.size + inc_start.size
    inc_scale = 1.0 / (cfg.drift_sigma_m * np.sqrt(1.0 - phi**2))
    rows = np.concatenate(
        [np.arange(n_first), n_first + np.arange(inc_start.size), n_first + np.arange(inc_start.size)]
    )
    cols = np.concatenate([first, inc_start + 1, inc_start])
    vals = np.concatenate(
        [
            np.full(n_first, 1.0 / cfg.drift_sigma_m),
            np.full(inc_start.size, inc_scale),
            np.full(inc_start.size, -phi * inc_scale),
        ]
    )
    jac = sp.csr_matrix((vals, (rows, cols)), shape=(n_rows, lay.n_unknowns))
    return (diag_b + jac.T @ jac).tocsr()


def reduced_normal(
    a: sp.csr_matrix, cluster: np.ndarray, n_clusters: int, info: np.ndarray, lateral: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Normal matrix and right-hand side with the cluster positions eliminated (Schur complement).

    Cost sum_i info_i (l_i + a_i theta - x_c)^2, minimised over x_c in closed form:
    H = A^T W A - B diag(1/W_c) B^T with B = A^T W E, rhs = -A^T W (l - weighted cluster mean of l).
    """
    n = lateral.size
    w_c = np.maximum(np.bincount(cluster, weights=info, minlength=n_clusters), 1e-300)
    # scale rows / columns through .data: much cheaper than scipy's broadcasting multiply
    awt = sp.csr_matrix((a.data * np.repeat(info, np.diff(a.indptr)), a.indices, a.indptr), shape=a.shape).T.tocsr()
    inc = sp.csr_matrix((np.ones(n), cluster, np.arange(n + 1)), shape=(n, n_clusters))
    b = awt @ inc
    b_scaled = sp.csr_matrix((b.data / w_c[b.indices], b.indices, b.indptr), shape=b.shape)
    pairs = b_scaled @ b.T.tocsr()  # the clusters' coupling of their drives: d^2 entries per step
    del b, b_scaled
    h = (awt @ a) - pairs
    del pairs
    mean_l = np.bincount(cluster, weights=info * lateral, minlength=n_clusters) / w_c
    rhs = -(awt @ (lateral - mean_l[cluster]))
    return h.tocsr(), np.asarray(rhs).ravel()


def update_normal(
    h: sp.csr_matrix,
    rhs: np.ndarray,
    a: sp.csr_matrix,
    samples: assoc.Samples,
    prior: sp.csr_matrix,
    old_info: np.ndarray,
    want_info: np.ndarray,
) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """Re-weight the normal equations, recomputing only the clusters whose weights changed.

    The normal matrix is a sum over clusters, and IRLS changes few weights after the first
    iterations (inliers keep weight 1 under Huber), so this is much cheaper than a rebuild.
    Weights that would change by less than ``_REWEIGHT_REL`` keep their old value (a negligible
    change of the IRLS fixed point). Returns the new H, rhs and the weights actually used.
    """
    changed = np.abs(want_info - old_info) > _REWEIGHT_REL * old_info
    new_info = kept_weights(old_info, want_info)
    hit = np.zeros(samples.n_clusters, dtype=bool)
    hit[samples.cluster[changed]] = True
    rows = np.flatnonzero(hit[samples.cluster])
    if rows.size == 0:
        return h, rhs, old_info
    if rebuilds(rows.size, samples.s_m.size):
        h_all, rhs_all = reduced_normal(a, samples.cluster, samples.n_clusters, new_info, samples.lateral_m)
        return (h_all + prior).tocsr(), rhs_all, new_info
    a_sub, c_sub, l_sub = a[rows], samples.cluster[rows], samples.lateral_m[rows]
    h_old, rhs_old = reduced_normal(a_sub, c_sub, samples.n_clusters, old_info[rows], l_sub)
    h_new, rhs_new = reduced_normal(a_sub, c_sub, samples.n_clusters, new_info[rows], l_sub)
    # the same sum as h + (h_new - h_old), without keeping both parts while it is formed (each
    # is of the order of H when many clusters change: their pairs of drives, d^2 per step)
    diff = h_new - h_old
    del h_new, h_old
    return (h + diff).tocsr(), rhs + (rhs_new - rhs_old), new_info


def rebuilds(changed_rows: int, n_samples: int) -> bool:
    """IRLS: whether re-weighting ``changed_rows`` of ``n_samples`` rebuilds the normal
    equations (cheaper than subtracting and adding the changed clusters)."""
    return changed_rows > n_samples // 3


def kept_weights(old_info: np.ndarray, want_info: np.ndarray) -> np.ndarray:
    """IRLS: the new weights, except where they change by at most ``_REWEIGHT_REL`` (kept)."""
    return np.where(np.abs(want_info - old_info) > _REWEIGHT_REL * old_info, want_info, old_info)


class NormalSolver:
    """Solves the SPD systems of the IRLS loop.

    The first system is factorised (SuperLU in symmetric mode); the re-weighted ones differ little,
    so they are solved by conjugate gradients preconditioned with that first factorisation and
    warm-started at the previous solution (a handful of iterations), with a fresh factorisation
    as the fallback.
    """

    def __init__(self) -> None:
        self._lu: Any = None

    def solve(self, h: sp.csr_matrix, rhs: np.ndarray, x0: np.ndarray) -> np.ndarray:
        if self._lu is not None:
            pre = spla.LinearOperator(h.shape, matvec=self._lu.solve, dtype=float)
            x, info = spla.cg(h, rhs, x0=x0, M=pre, rtol=1e-10, atol=0.0, maxiter=200)
            if info == 0:
                return x
        # H is symmetric positive definite: no pivoting needed, and a symmetric ordering keeps the
        # factors sparse (measured on paper_like 4x, 8217 unknowns: L+U 3.1 M entries in 0.8 s,
        # against 15 M in 1.9 s with COLAMD and partial pivoting)
        self._lu = spla.splu(
            h.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True)
        )
        return self._lu.solve(rhs)


def robust_weights(r: np.ndarray, scale_m: float, loss: str) -> np.ndarray:
    """IRLS weights of residuals ``r`` [m] for the given loss with threshold ``scale_m``."""
    z = np.abs(r) / scale_m
    if loss == "huber":
        return np.where(z <= 1.0, 1.0, 1.0 / np.maximum(z, 1e-12))
    if loss == "cauchy":
        return 1.0 / (1.0 + z**2)
    return np.ones_like(r)


def sample_residuals(a: sp.csr_matrix, theta: np.ndarray, samples: assoc.Samples, info: np.ndarray) -> np.ndarray:
    v = samples.lateral_m + a @ theta
    w_c = np.maximum(np.bincount(samples.cluster, weights=info, minlength=samples.n_clusters), 1e-300)
    mean_v = np.bincount(samples.cluster, weights=info * v, minlength=samples.n_clusters) / w_c
    return v - mean_v[samples.cluster]


def adjust_offsets(observations: Sequence[Any], *, config: AdjustConfig = AdjustConfig()) -> OffsetModel:
    """Estimate every drive's lateral offset curve from all steps jointly (sparse least squares).

    Args:
        observations: StepObservations of all steps (any order, any pivots). Their cluster labels
            seed the association; with ``config.reassociate_rounds > 0`` every sample (also those
            labelled -1) is re-associated to the nearest cluster of its step and type. Samples
            with non-finite values, or in a cluster seen by fewer than 2 drives, are not used;
            malformed steps are skipped and named in ``stats["problems"]``.
        config: model and solver settings.

    Returns:
        OffsetModel with one curve per drive that has at least one usable sample. ``stats`` holds
        counts, iterations, lane shifts, the relabelled / coarse-rejected / robustly down-weighted
        fractions and the inlier residual RMS.
    """
    cfg = config
    stats: dict[str, Any] = {}
    pool = assoc.gather(observations, stats)
    base: dict[str, Any] = dict(
        knot_spacing_m=cfg.knot_spacing_m,
        correlation_length_m=cfg.correlation_length_m,
        drift_sigma_m=cfg.drift_sigma_m,
        bias_sigma_m=cfg.bias_sigma_m,
    )
    label = pool.label
    n_shifted = 0
    if cfg.reassociate_rounds > 0:
        # RULE association from the prior: a drive's raw samples lie within its localization
        # error (~1 m) of the truth, so the nearest cluster centre (median of the members' raw
        # positions) is an association that no per-step EM lane shift can bias. One constant
        # per drive fitted on it is then enough to re-associate at the gate.
        label = assoc.reassociate(
            pool, label, np.zeros(pool.s_m.size), assoc.centres(pool, label, pool.lateral_m), gate_m=np.inf
        )
        samples = assoc.select(pool, label, THIN_DRIVES)
        if samples.s_m.size:
            coarse = coarse_config(cfg)
            coarse_fit = _irls(samples, coarse, np.ones(samples.s_m.size, dtype=bool))
            model = OffsetModel(
                **base, drives=drive_curves(samples.drive_ids, coarse_fit.layout, coarse_fit.theta, None)
            )
            label, n = shift_and_reassociate(pool, label, model, cfg)
            n_shifted += n
    samples, fit, keep = _fit_all(pool, label, cfg)
    for _ in range(cfg.reassociate_rounds - 1):
        if fit is None:
            break
        model = OffsetModel(**base, drives=drive_curves(samples.drive_ids, fit.layout, fit.theta, None))
        label, n = shift_and_reassociate(pool, label, model, cfg)
        n_shifted += n
        samples, fit, keep = _fit_all(pool, label, cfg)
    stats["n_samples_used"] = int(samples.s_m.size)
    stats["lane_shifts"] = n_shifted
    stats["relabelled_fraction"] = float(np.mean(label != pool.label)) if label.size else 0.0
    if fit is None:
        stats.update(n_drives=0, n_unknowns=0, iterations=0)
        return OffsetModel(**base, stats=stats)
    r, info, lay = fit.residual, fit.info, fit.layout
    inlier = keep & (np.abs(r) <= ROBUST_K * cfg.noise_sigma_m)
    stats.update(
        n_drives=len(samples.drive_ids),
        n_clusters=samples.n_clusters,
        n_unknowns=lay.n_unknowns,
        iterations=fit.iterations,
        last_change_m=fit.last_change_m,
        coarse_rejected_fraction=float(np.mean(~keep)),
        downweighted_fraction=float(np.mean(info < 0.5 * cfg.noise_sigma_m**-2)),
        inlier_rms_m=float(np.sqrt(np.mean(r[inlier] ** 2))) if inlier.any() else float("nan"),
    )
    if fit.schur is not None:  # the curve fit was solved matrix-free (past cfg.max_pair_fill)
        stats.update(
            matrix_free=True,
            cg_iterations=fit.schur.iterations,
            cg_unconverged=fit.schur.unconverged,
            cg_coarse_unknowns=fit.schur.coarse_unknowns,
        )
    theta, h = fit.theta, fit.normal
    cov = None
    if cfg.compute_std and lay.n_unknowns <= cfg.std_max_unknowns:
        cov = covariance_parts(h, lay)
    stats["std_computed"] = cov is not None
    return OffsetModel(**base, drives=drive_curves(samples.drive_ids, lay, theta, cov), stats=stats)


def coarse_config(cfg: AdjustConfig) -> AdjustConfig:
    """One constant per drive (prior: the total offset variance), Huber, few iterations."""
    return replace(
        cfg,
        drift_sigma_m=0.0,
        bias_sigma_m=float(np.hypot(cfg.bias_sigma_m, cfg.drift_sigma_m)),
        loss="huber",
        iterations=min(cfg.iterations, 3),
    )


def shift_and_reassociate(
    pool: assoc.Pool, label: np.ndarray, model: OffsetModel, cfg: AdjustConfig, free: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """Lane-shift search per drive, then re-association at the gate; returns labels and #shifted drives.

    ``free``: per pool drive, whether it may shift (None: all); the others keep their association
    (``adjustment_local``: the solved fleet's)."""
    offset = pool_offsets(pool, model)
    cen = assoc.centres(pool, label, pool.lateral_m + offset)
    bias = np.array([model.drives[d].bias_m if d in model.drives else 0.0 for d in pool.drive_ids])
    shift = assoc.lane_shift_search(
        pool,
        cen,
        offset,
        bias,
        search_m=SHIFT_SEARCH_M,
        gate_m=REASSOCIATE_GATE_M,
        noise_sigma_m=cfg.noise_sigma_m,
        bias_sigma_m=cfg.bias_sigma_m,
    )
    if free is not None:
        shift = np.where(free, shift, 0.0)
    new = assoc.reassociate(pool, label, offset + shift[pool.drive], cen, gate_m=REASSOCIATE_GATE_M)
    return new, int(np.count_nonzero(shift))


def _fit_all(pool: assoc.Pool, label: np.ndarray, cfg: AdjustConfig) -> tuple[assoc.Samples, _Fit | None, np.ndarray]:
    """Select the informative samples of ``label`` and fit them (coarse stage, then curves)."""
    samples = assoc.select(pool, label, THIN_DRIVES)
    keep = np.ones(samples.s_m.size, dtype=bool)
    if samples.s_m.size == 0:
        return samples, None, keep
    if cfg.coarse_reject_m > 0 and cfg.drift_sigma_m > 0:
        # RULE coarse-to-fine: a drive associated a lane off over a stretch gives samples that
        # agree with each other but not with the rest of the drive. A curve would follow them;
        # one constant per drive does not, so they stand out here and are dropped.
        keep = np.abs(_irls(samples, coarse_config(cfg), keep).residual) <= cfg.coarse_reject_m
    return samples, _irls(samples, cfg, keep), keep


def pool_offsets(pool: assoc.Pool, model: OffsetModel) -> np.ndarray:
    """(n,) offset of every pool sample under ``model`` (0 for drives it does not know)."""
    out = np.zeros(pool.s_m.size)
    order = np.argsort(pool.drive, kind="stable")
    bounds = np.searchsorted(pool.drive[order], np.arange(len(pool.drive_ids) + 1))
    for d, did in enumerate(pool.drive_ids):  # one vectorised call per drive (~100s)
        part = order[bounds[d] : bounds[d + 1]]
        if part.size and did in model.drives:
            out[part] = model.offset(did, pool.s_m[part])
    return out


@dataclass(frozen=True)
class _Fit:
    layout: _Layout
    theta: np.ndarray  # (p,) unknowns
    normal: sp.csr_matrix | SchurNormal  # (p, p) final normal matrix incl. prior (explicit or an operator)
    info: np.ndarray  # (n,) final sample weights / noise variance
    residual: np.ndarray  # (n,) residual of every sample about its weighted cluster mean [m]
    iterations: int
    last_change_m: float
    schur: SchurSolver | None = None  # the matrix-free solver, when it was used


def _irls(samples: assoc.Samples, cfg: AdjustConfig, keep: np.ndarray) -> _Fit:
    """Solve the adjustment with IRLS re-weighting; samples outside ``keep`` have weight 0."""
    lay = knot_layout(samples, cfg)
    a = design_matrix(samples, lay, cfg)
    prior = prior_matrix(lay, cfg)
    info0 = np.where(keep, cfg.noise_sigma_m**-2, 0.0)
    theta = np.zeros(lay.n_unknowns)
    warmup = HUBER_WARMUP_ITERATIONS if cfg.loss == "cauchy" else 0
    info = info0.copy()
    # RULE the explicit normal matrix holds every pair of drives seen in a cluster; past the
    # budget the same system is solved matrix-free (adjustment_schur)
    h: sp.csr_matrix | SchurNormal
    solver: NormalSolver | SchurSolver
    if pair_fill(a, samples.cluster, samples.n_clusters, stop_above=cfg.max_pair_fill) <= cfg.max_pair_fill:
        h, rhs = reduced_normal(a, samples.cluster, samples.n_clusters, info, samples.lateral_m)
        h = (h + prior).tocsr()
        solver = NormalSolver()
    else:
        h = SchurNormal(a, samples.cluster, samples.n_clusters, info, samples.lateral_m, prior, samples.drive)
        links = drive_links(samples.drive, samples.cluster)
        z = coarse_basis(lay.col0, lay.n_knots, place_sums(a, samples.xy), links)
        rhs, solver = h.rhs, SchurSolver(z)
    it, change = 0, 0.0
    for it in range(1, cfg.iterations + 1):
        new_theta = solver.solve(h, rhs, theta)  # each solver gets its own kind of h
        change = float(np.max(np.abs(new_theta - theta), initial=0.0))
        theta = new_theta
        r = sample_residuals(a, theta, samples, info)
        # solve k uses the weights from solve k-1's residuals; Huber for solves 2..1+warmup
        if cfg.loss == "linear" or it == cfg.iterations or (it >= 2 + warmup and change < TOL_M):
            break
        weights = robust_weights(r, ROBUST_K * cfg.noise_sigma_m, "huber" if it <= warmup else cfg.loss)
        if isinstance(h, SchurNormal):
            info = kept_weights(info, info0 * weights)
            h = h.reweighted(info)
            rhs = h.rhs
        else:
            h, rhs, info = update_normal(h, rhs, a, samples, prior, info, info0 * weights)
    schur = solver if isinstance(solver, SchurSolver) else None
    return _Fit(lay, theta, h, info, r, it, change, schur)


def covariance_parts(h: sp.csr_matrix, lay: _Layout) -> dict[str, np.ndarray]:
    """Entries of H^-1 needed for the std of o(s): var/cov of bias and knots, per column."""
    # One BLAS thread: on a small shared machine OpenBLAS threads thrash (measured 20x slower).
    with one_blas_thread():
        c, lower = scipy.linalg.cho_factor(h.toarray(), lower=False, check_finite=False)
        inv, info = scipy.linalg.lapack.dpotri(c, lower=lower)
    if info != 0:
        raise np.linalg.LinAlgError(f"dpotri failed with info={info}")
    # dpotri fills the upper triangle only; every entry read below has row <= column.
    col_owner = np.repeat(np.arange(lay.col0.size), 1 + lay.n_knots)
    idx = np.arange(lay.n_unknowns)
    nxt = np.minimum(idx + 1, lay.n_unknowns - 1)
    return {
        "diag": np.diag(inv).copy(),
        "with_bias": inv[lay.col0[col_owner], idx],
        "next": inv[idx, nxt],
    }


def drive_curves(
    drive_ids: Sequence[str], lay: _Layout, theta: np.ndarray, cov: dict[str, np.ndarray] | None
) -> dict[str, DriveOffset]:
    out: dict[str, DriveOffset] = {}
    for d, did in enumerate(drive_ids):  # one entry per drive (~100s): cheap
        c0, nk = int(lay.col0[d]), int(lay.n_knots[d])
        g = slice(c0 + 1, c0 + 1 + nk)
        extra: dict[str, Any]
        if cov is None:
            nan = np.full(nk, np.nan)
            extra = dict(
                var_bias=float("nan"),
                cov_bias_drift=nan,
                var_drift=nan.copy(),
                cov_drift_next=np.full(max(nk - 1, 0), np.nan),
            )
        else:
            extra = dict(
                var_bias=float(cov["diag"][c0]),
                cov_bias_drift=cov["with_bias"][g].copy(),
                var_drift=cov["diag"][g].copy(),
                cov_drift_next=cov["next"][c0 + 1 : c0 + nk].copy(),
            )
        out[did] = DriveOffset(k0=int(lay.k0[d]), bias_m=float(theta[c0]), drift_m=theta[g].copy(), **extra)
    return out
