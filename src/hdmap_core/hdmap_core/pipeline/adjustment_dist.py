"""The offset adjustment's one solve over observations split into parts that stay where they are.

``adjustment.adjust_offsets`` holds every step's samples in one process. Here the observation
sequence is cut into parts (in a tiled build: runs of tiles in key order, each an ``AdjustPart``
in a Dask actor on a worker; in the whole-fleet build: the pivot shares of its forked workers,
``pipeline.driver``, whose steps interleave and which share no drive), and the client runs the same
algorithm as ``adjust_offsets`` (raw association, coarse fit, lane-shift search, re-association,
coarse rejection and the robust IRLS curve fit; docs/adjustment.md) by asking every part for its
share:

- the normal equations are a sum over clusters, and a cluster lies in one step, a step in one
  part: ``H = P + sum_b H_b``, ``rhs = sum_b rhs_b``. Each part forms its ``H_b`` (the pairs of
  unknowns its clusters couple: it grows with the knots and the drives per place, not with the
  samples) and, after each re-weighting, only the change of the clusters whose weights changed;
  the client adds them and solves, as ``adjust_offsets`` does. Above
  ``AdjustConfig.max_pair_fill`` (the parts' pair entries summed) nothing is assembled: conjugate
  gradients on ``H v = P v + sum_b H_b v`` (``adjustment_schur``), one round of part products per
  iteration, preconditioned by the sum of the parts' per-drive blocks and deflated by the coarse
  space of place-wise shifts (``adjustment_coarse``: its ``H Z`` one more round per solve);
- what is per sample (association, residuals, weights, coarse rejection) stays in its part; what
  is per drive is reduced in the client: each drive's used range (its knots), the lane-shift
  search's cost per drive and shift (summed), the curves (sent back to every part);
- the global numbering the one solve uses is kept: step numbers (the thinning of dense steps
  picks the same steps), drive order (first appearance), and the lane-shift search's picks (every
  ``stride``-th sample of a drive counted over the whole fleet).

So the result is the one solve's up to the order of floating-point sums (tested against it:
test_adjustment_dist.py); only knot vectors, per-drive arrays and the parts' sparse
normal-matrix shares cross the network, never the samples. The posterior std is not computed
(``stats["std_computed"]`` False; the mapping does not use it).

``call(method, args)``: runs ``AdjustPart.method(*args[b])`` on every part ``b`` and returns the
results in part order (``local_call`` for parts in this process; ``tiled.cluster`` for actors).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from hdmap_core.errors import ConfigError
from hdmap_core.pipeline import adjustment_assoc as assoc
from hdmap_core.pipeline.adjustment import (
    HUBER_WARMUP_ITERATIONS,
    REASSOCIATE_GATE_M,
    ROBUST_K,
    SHIFT_SEARCH_M,
    THIN_DRIVES,
    TOL_M,
    AdjustConfig,
    NormalSolver,
    OffsetModel,
    coarse_config,
    covariance_parts,
    design_matrix,
    drive_curves,
    kept_weights,
    layout_of,
    pool_offsets,
    prior_matrix,
    rebuilds,
    reduced_normal,
    robust_weights,
    sample_residuals,
)
from hdmap_core.pipeline.adjustment_coarse import coarse_basis, drive_links, place_sums
from hdmap_core.pipeline.adjustment_schur import SchurNormal, SchurSolver, pair_fill

__all__ = ["AdjustPart", "Call", "adjust_parts", "local_call"]

Call = Callable[[str, Sequence[tuple]], list]


class AdjustPart:
    """Consecutive observations of the fleet (a run of tiles) and what the solve keeps per sample.

    Built from one or more lists of step observations (concatenated in order). The client
    (``adjust_parts``) calls its methods in a fixed protocol; every array here is per sample of
    this part, every argument and result per drive, per unknown or per shift."""

    def __init__(self, *observation_lists: Sequence[Any]) -> None:
        observations = [o for part in observation_lists for o in part]
        self.n_observations = len(observations)
        self.gather_stats: dict[str, Any] = {}
        self.pool = assoc.gather(observations, self.gather_stats)
        del observations
        self.label = self.pool.label
        self.picks = np.zeros(0, dtype=np.int64)
        self.samples: assoc.Samples | None = None
        self.keep = np.zeros(0, dtype=bool)
        self.offset = np.zeros(0)
        self.cen: assoc.Centres | None = None

    # -- numbering --------------------------------------------------------------------------------

    def summary(self) -> tuple[int, tuple[str, ...], dict[str, Any], np.ndarray]:
        """Observations, drives (in order of first appearance), the gathering's stats and the
        step (here) of each drive's first sample."""
        first = self.pool.first_step if self.pool.first_step is not None else np.zeros(0, dtype=np.int64)
        return self.n_observations, self.pool.drive_ids, self.gather_stats, first

    def set_fleet(self, step0: int | np.ndarray, drive_index: np.ndarray, drive_ids: tuple[str, ...]) -> np.ndarray:
        """Number steps (``step0``: of the first step, or of each step) and drives as in the whole
        fleet; returns the samples per fleet drive."""
        p = self.pool
        self.pool = replace(p, drive=np.asarray(drive_index, dtype=np.int64)[p.drive], drive_ids=drive_ids, step0=step0)
        return np.bincount(self.pool.drive, minlength=len(drive_ids))

    def set_picks(self, first_rank: np.ndarray, stride: np.ndarray) -> None:
        """The lane-shift search's samples here (``assoc.shift_picks`` over the whole fleet)."""
        self.picks = assoc.shift_picks(self.pool, first_rank, stride)

    # -- association --------------------------------------------------------------------------------

    def raw_extent(self) -> assoc.Extent:
        """The scale of the raw positions' centres here (``assoc.extent``)."""
        p = self.pool
        return assoc.extent(p, p.label, p.lateral_m)

    def associate_raw(self, scale: assoc.Extent) -> None:
        """Every sample to the nearest centre of its step and type by raw position (``scale``: the
        fleet's ``raw_extent``)."""
        p = self.pool
        self.label = assoc.reassociate(
            p, p.label, np.zeros(p.s_m.size), assoc.centres(p, p.label, p.lateral_m, scale), gate_m=np.inf
        )

    def shift_extent(self, model: OffsetModel) -> assoc.Extent:
        """The samples' offsets under ``model`` (kept for ``shift_costs``) and the scale of their
        centres here."""
        self.offset = pool_offsets(self.pool, model)
        return assoc.extent(self.pool, self.label, self.pool.lateral_m + self.offset)

    def shift_costs(self, grid: np.ndarray, noise_sigma_m: float, scale: assoc.Extent) -> np.ndarray | None:
        """The lane-shift search's data term per fleet drive and shift (None: no cluster here),
        at the offsets of the last ``shift_extent`` (``scale``: the fleet's)."""
        self.cen = assoc.centres(self.pool, self.label, self.pool.lateral_m + self.offset, scale)
        if self.cen is None:
            return None
        return assoc.shift_costs(
            self.pool, self.cen, self.offset, self.picks, grid, gate_m=REASSOCIATE_GATE_M, noise_sigma_m=noise_sigma_m
        )

    def reassociate(self, shift: np.ndarray) -> None:
        """Re-associate at the gate with the offsets of the last ``shift_costs`` plus ``shift``."""
        self.label = assoc.reassociate(
            self.pool, self.label, self.offset + shift[self.pool.drive], self.cen, gate_m=REASSOCIATE_GATE_M
        )

    def select(self) -> tuple[np.ndarray, int]:
        """The samples of informative clusters; returns their fleet drives (sorted) and count."""
        self.samples = assoc.select(self.pool, self.label, THIN_DRIVES)
        self.keep = np.ones(self.samples.s_m.size, dtype=bool)
        return self.samples.pool_drive, int(self.samples.s_m.size)

    def use_drives(self, used: np.ndarray) -> None:
        """Number the selected samples' drives as the fleet's used drives ``used`` (sorted)."""
        s = self._samples()
        self.samples = replace(s, drive=np.searchsorted(used, s.pool_drive[s.drive]).astype(np.int64))
        self.n_used = int(used.size)

    def span(self) -> tuple[np.ndarray, np.ndarray]:
        """Per used drive, the least and greatest travelled distance of its samples here."""
        s = self._samples()
        smin = np.full(self.n_used, np.inf)
        smax = np.full(self.n_used, -np.inf)
        np.minimum.at(smin, s.drive, s.s_m)
        np.maximum.at(smax, s.drive, s.s_m)
        return smin, smax

    # -- the fit ------------------------------------------------------------------------------------

    def begin_fit(self, lay: Any, cfg: AdjustConfig, use_keep: bool) -> int:
        """Design matrix and weights of a fit (``use_keep``: without the coarse-rejected samples);
        returns this part's pair-term entries (counted up to ``cfg.max_pair_fill``)."""
        s = self._samples()
        self.cfg = cfg
        self.a = design_matrix(s, lay, cfg)
        self.info0 = np.where(self.keep if use_keep else np.ones(s.s_m.size, dtype=bool), cfg.noise_sigma_m**-2, 0.0)
        self.info = self.info0.copy()
        self.schur: SchurNormal | None = None
        self.r = np.zeros(s.s_m.size)
        return pair_fill(self.a, s.cluster, s.n_clusters, stop_above=cfg.max_pair_fill)

    def normal(self) -> tuple[sp.csr_matrix, np.ndarray]:
        """This part's share of the reduced normal matrix and right-hand side (no prior)."""
        s = self._samples()
        return reduced_normal(self.a, s.cluster, s.n_clusters, self.info, s.lateral_m)

    def residuals(self, theta: np.ndarray) -> None:
        """Residuals of the samples about their weighted cluster means under ``theta``."""
        self.r = sample_residuals(self.a, theta, self._samples(), self.info)

    def reweigh(self, loss: str) -> int:
        """IRLS: the new weights (``kept_weights``); returns the samples of the clusters whose
        weights changed (the client decides from all parts' whether ``reweight`` rebuilds)."""
        s = self._samples()
        want = self.info0 * robust_weights(self.r, ROBUST_K * self.cfg.noise_sigma_m, loss)
        self.new_info = kept_weights(self.info, want)
        changed = self.new_info != self.info
        hit = np.zeros(s.n_clusters, dtype=bool)
        hit[s.cluster[changed]] = True
        self.rows = np.flatnonzero(hit[s.cluster])
        return int(self.rows.size)

    def reweight(self, rebuild: bool) -> tuple[sp.csr_matrix, np.ndarray] | None:
        """The weights of the last ``reweigh`` in this part's share: with ``rebuild`` its whole H
        and rhs anew, else their change (None: none), from only the clusters whose weights
        changed (``adjustment.update_normal``'s rules)."""
        s = self._samples()
        new, rows = self.new_info, self.rows
        if rebuild:
            self.info = new
            return self.normal()
        if rows.size == 0:
            return None
        a_sub, c_sub, l_sub = self.a[rows], s.cluster[rows], s.lateral_m[rows]
        h_old, rhs_old = reduced_normal(a_sub, c_sub, s.n_clusters, self.info[rows], l_sub)
        h_new, rhs_new = reduced_normal(a_sub, c_sub, s.n_clusters, new[rows], l_sub)
        self.info = new
        diff = h_new - h_old
        del h_new, h_old
        return diff.tocsr(), rhs_new - rhs_old

    def schur_begin(self) -> np.ndarray:
        """Matrix-free: this part's operator (no prior); returns its rhs."""
        s = self._samples()
        p = self.a.shape[1]
        self.schur = SchurNormal(
            self.a, s.cluster, s.n_clusters, self.info, s.lateral_m, sp.csr_matrix((p, p)), s.drive
        )
        return self.schur.rhs

    def schur_reweight(self, loss: str) -> np.ndarray:
        """Matrix-free IRLS re-weighting; returns the new rhs."""
        want = self.info0 * robust_weights(self.r, ROBUST_K * self.cfg.noise_sigma_m, loss)
        self.info = kept_weights(self.info, want)
        return self.schur_begin()

    def schur_matvec(self, v: np.ndarray) -> np.ndarray:
        """This part's ``H_b @ v``."""
        assert self.schur is not None
        return self.schur.matvec(v)

    def schur_matmat(self, z: sp.csr_matrix) -> sp.csr_matrix:
        """This part's ``H_b @ z`` (the coarse space's share)."""
        assert self.schur is not None
        return self.schur.matmat(z)

    def coarse_shares(self) -> tuple[np.ndarray, np.ndarray]:
        """This part's shares of the coarse space: ``place_sums`` and ``drive_links``."""
        s = self._samples()
        return place_sums(self.a, s.xy), drive_links(s.drive, s.cluster)

    def schur_blocks(self) -> sp.csc_matrix:
        """This part's per-drive diagonal blocks of ``H_b`` (the preconditioner's share)."""
        assert self.schur is not None
        return self.schur.drive_blocks()

    def coarse_keep(self, reject_m: float) -> None:
        """Coarse rejection: keep the samples within ``reject_m`` of their cluster."""
        self.keep = np.abs(self.r) <= reject_m

    def fit_stats(self, noise_sigma_m: float) -> dict[str, float]:
        """Counts for the model's stats."""
        s = self._samples()
        inlier = self.keep & (np.abs(self.r) <= ROBUST_K * noise_sigma_m)
        return {
            "samples": float(s.s_m.size),
            "clusters": float(s.n_clusters),
            "rejected": float(np.count_nonzero(~self.keep)),
            "downweighted": float(np.count_nonzero(self.info < 0.5 * noise_sigma_m**-2)),
            "inliers": float(np.count_nonzero(inlier)),
            "inlier_ss": float(np.sum(self.r[inlier] ** 2)),
        }

    def relabelled(self) -> tuple[int, int]:
        """Samples whose label differs from the observations', and all samples."""
        return int(np.count_nonzero(self.label != self.pool.label)), int(self.label.size)

    def _samples(self) -> assoc.Samples:
        assert self.samples is not None, "select() first"
        return self.samples


def local_call(parts: Sequence[AdjustPart]) -> Call:
    """``call`` for parts held in this process."""

    def call(method: str, args: Sequence[tuple]) -> list:
        return [getattr(p, method)(*a) for p, a in zip(parts, args, strict=True)]

    return call


@dataclass(frozen=True)
class _Fit:
    layout: Any
    theta: np.ndarray
    iterations: int
    last_change_m: float
    schur: SchurSolver | None
    normal: sp.csr_matrix | None  # the explicit normal matrix of the last solve (None: matrix-free)


class _PartsNormal:
    """``H = P + sum_b H_b`` as an operator over the parts (for ``SchurSolver``)."""

    def __init__(self, each: Callable[..., list], prior: sp.csr_matrix) -> None:
        self._each, self._prior = each, prior
        self.shape = prior.shape

    def matvec(self, v: np.ndarray) -> np.ndarray:
        out = np.asarray(self._prior @ v).ravel()
        for part in self._each("schur_matvec", v):
            out += part
        return out

    def matmat(self, z: sp.csr_matrix) -> sp.csr_matrix:
        out = (self._prior @ z).tocsr()
        for part in self._each("schur_matmat", z):
            out = out + part
        return out.tocsr()

    def drive_blocks(self) -> sp.csc_matrix:
        total = self._prior.tocsc()
        for part in self._each("schur_blocks"):
            total = total + part
        return total.tocsc()


def adjust_parts(
    call: Call, n_parts: int, config: AdjustConfig, steps: Sequence[np.ndarray] | None = None
) -> OffsetModel:
    """``adjustment.adjust_offsets`` over the observations held by ``n_parts`` parts, in order
    (their concatenation is the observation sequence); see the module docstring.

    ``steps``: per part, the number of each of its observations in the whole sequence, for parts
    that are not consecutive runs of it (e.g. the pivot shares of ``pipeline.driver``, whose steps
    interleave). Such parts must not share a drive (ConfigError). Parts that share no drive give
    the one solve's offsets to the last bit (explicit solver): each drive's samples, clusters and
    normal-matrix rows lie in one part, in the one solve's order, and the client joins the parts'
    rows instead of adding them."""
    cfg = config

    def each(method: str, *args: Any) -> list:
        return call(method, [args] * n_parts)

    stats: dict[str, Any] = {}
    summaries = each("summary")
    step0 = np.concatenate([[0], np.cumsum([n for n, _, _, _ in summaries])[:-1]]).astype(int)
    numbers = list(steps) if steps is not None else [int(step0[b]) + np.arange(s[0]) for b, s in enumerate(summaries)]
    # drives in order of first appearance in the whole sequence (a part's in its own order)
    first = [
        (int(numbers[b][f]), b, r, d)
        for b, (_, ids, _, fs) in enumerate(summaries)
        for r, (d, f) in enumerate(zip(ids, fs))
    ]
    lookup: dict[str, int] = {}
    for *_, d in sorted(first):
        lookup.setdefault(d, len(lookup))
    drive_ids = tuple(lookup)
    if steps is not None and len(lookup) < len(first):
        raise ConfigError("adjust_parts: parts given with their step numbers must not share a drive")
    gstats = [g for _, _, g, _ in summaries]
    for key in ("n_steps", "n_steps_skipped", "n_samples", "n_nonfinite_dropped"):
        stats[key] = int(sum(g.get(key, 0) for g in gstats))
    stats["problems"] = [p for g in gstats for p in g.get("problems", [])][: assoc.MAX_REPORTED_PROBLEMS]
    counts = np.array(
        call(
            "set_fleet",
            [
                (
                    int(step0[b]) if steps is None else np.asarray(numbers[b], dtype=np.int64),
                    np.array([lookup[d] for d in ids], dtype=np.int64),
                    drive_ids,
                )
                for b, (_, ids, _, _) in enumerate(summaries)
            ],
        )
    ).reshape(n_parts, len(drive_ids))
    first_rank = np.cumsum(counts, axis=0) - counts
    stride = np.maximum(1, counts.sum(axis=0) // 200)
    call("set_picks", [(first_rank[b], stride) for b in range(n_parts)])
    base: dict[str, Any] = dict(
        knot_spacing_m=cfg.knot_spacing_m,
        correlation_length_m=cfg.correlation_length_m,
        drift_sigma_m=cfg.drift_sigma_m,
        bias_sigma_m=cfg.bias_sigma_m,
    )
    n_shifted = 0
    if cfg.reassociate_rounds > 0:
        each("associate_raw", assoc.max_extent(each("raw_extent")))
        used, n = _select(each)
        if n:
            fit = _irls(each, coarse_config(cfg), False, used.size, n)
            model = OffsetModel(**base, drives=drive_curves(_ids(drive_ids, used), fit.layout, fit.theta, None))
            n_shifted += _shift(each, model, cfg, drive_ids)
    used, n, curve_fit = _fit_all(each, cfg)
    for _ in range(cfg.reassociate_rounds - 1):
        if curve_fit is None:
            break
        model = OffsetModel(**base, drives=drive_curves(_ids(drive_ids, used), curve_fit.layout, curve_fit.theta, None))
        n_shifted += _shift(each, model, cfg, drive_ids)
        used, n, curve_fit = _fit_all(each, cfg)
    stats["n_samples_used"] = n
    stats["lane_shifts"] = n_shifted
    rel = np.array(each("relabelled")).reshape(n_parts, 2).sum(axis=0)
    stats["relabelled_fraction"] = float(rel[0] / rel[1]) if rel[1] else 0.0
    stats["parts"] = n_parts
    if curve_fit is None:
        stats.update(n_drives=0, n_unknowns=0, iterations=0)
        return OffsetModel(**base, stats=stats)
    fs = each("fit_stats", cfg.noise_sigma_m)
    tot = {k: sum(f[k] for f in fs) for k in fs[0]}
    lay = curve_fit.layout
    stats.update(
        n_drives=int(used.size),
        n_clusters=int(tot["clusters"]),
        n_unknowns=lay.n_unknowns,
        iterations=curve_fit.iterations,
        last_change_m=curve_fit.last_change_m,
        coarse_rejected_fraction=tot["rejected"] / tot["samples"],
        downweighted_fraction=tot["downweighted"] / tot["samples"],
        inlier_rms_m=float(np.sqrt(tot["inlier_ss"] / tot["inliers"])) if tot["inliers"] else float("nan"),
    )
    if curve_fit.schur is not None:
        stats.update(
            matrix_free=True,
            cg_iterations=curve_fit.schur.iterations,
            cg_unconverged=curve_fit.schur.unconverged,
            cg_coarse_unknowns=curve_fit.schur.coarse_unknowns,
        )
    cov = None
    if curve_fit.normal is not None and cfg.compute_std and lay.n_unknowns <= cfg.std_max_unknowns:
        cov = covariance_parts(curve_fit.normal, lay)
    stats["std_computed"] = cov is not None
    return OffsetModel(**base, drives=drive_curves(_ids(drive_ids, used), lay, curve_fit.theta, cov), stats=stats)


def _ids(drive_ids: tuple[str, ...], used: np.ndarray) -> tuple[str, ...]:
    return tuple(drive_ids[i] for i in used)


def _select(each: Callable[..., list]) -> tuple[np.ndarray, int]:
    """Every part selects its informative samples; the fleet's used drives are numbered."""
    picked = each("select")
    used = np.unique(np.concatenate([np.asarray(u, dtype=np.int64) for u, _ in picked]))
    each("use_drives", used)
    return used, int(sum(n for _, n in picked))


def _fit_all(each: Callable[..., list], cfg: AdjustConfig) -> tuple[np.ndarray, int, _Fit | None]:
    """``adjustment._fit_all`` over the parts: select, coarse rejection, curve fit."""
    used, n = _select(each)
    if n == 0:
        return used, n, None
    if cfg.coarse_reject_m > 0 and cfg.drift_sigma_m > 0:
        _irls(each, coarse_config(cfg), False, used.size, n)
        each("coarse_keep", cfg.coarse_reject_m)
    return used, n, _irls(each, cfg, True, used.size, n)


def _shift(each: Callable[..., list], model: OffsetModel, cfg: AdjustConfig, drive_ids: tuple[str, ...]) -> int:
    """``adjustment.shift_and_reassociate`` over the parts: the costs summed, the shifts chosen
    here, the re-association in the parts."""
    grid = assoc.shift_grid(SHIFT_SEARCH_M)
    scale = assoc.max_extent(each("shift_extent", model))
    costs = [c for c in each("shift_costs", grid, cfg.noise_sigma_m, scale) if c is not None]
    shift = np.zeros(len(drive_ids))
    if costs:
        cost = costs[0].copy()
        for c in costs[1:]:
            cost += c
        bias = np.array([model.drives[d].bias_m if d in model.drives else 0.0 for d in drive_ids])
        shift = assoc.choose_shifts(cost, bias, grid, bias_sigma_m=cfg.bias_sigma_m)
    each("reassociate", shift)
    return int(np.count_nonzero(shift))


def _joined(shares: Sequence[sp.csr_matrix]) -> sp.csr_matrix:
    """The sum of the parts' (p, p) shares of the normal matrix. Where no two parts have entries
    in the same row (they share no drive) the rows are put together as they are, every entry and
    its place in its row kept: the one solve's matrix to the last bit (its products then add in
    the same order); else added."""
    shares = [sp.csr_matrix(m) for m in shares]
    lengths = np.array([np.diff(m.indptr) for m in shares])
    if len(shares) == 1 or np.count_nonzero(lengths, axis=0).max(initial=0) > 1:
        total = shares[0]
        for m in shares[1:]:
            total = total + m
        return total.tocsr()
    indptr = np.concatenate([[0], np.cumsum(lengths.sum(axis=0))])
    indices = np.empty(indptr[-1], dtype=np.int64)
    data = np.empty(indptr[-1])
    for m, n in zip(shares, lengths):
        rows = np.repeat(np.arange(n.size), n)
        at = indptr[rows] + np.arange(rows.size) - m.indptr[rows]
        indices[at], data[at] = m.indices, m.data
    return sp.csr_matrix((data, indices, indptr), shape=shares[0].shape)


def _irls(each: Callable[..., list], cfg: AdjustConfig, use_keep: bool, n_used: int, n_samples: int) -> _Fit:
    """``adjustment._irls`` over the parts (see the module docstring)."""
    if cfg.drift_sigma_m > 0:
        spans = each("span")
        smin = np.minimum.reduce([lo for lo, _ in spans])
        smax = np.maximum.reduce([hi for _, hi in spans])
    else:
        smin, smax = np.full(n_used, np.inf), np.full(n_used, -np.inf)
    lay = layout_of(smin, smax, cfg)
    prior = prior_matrix(lay, cfg)
    fill = sum(each("begin_fit", lay, cfg, use_keep))
    h: sp.csr_matrix | _PartsNormal
    solver: NormalSolver | SchurSolver
    if fill <= cfg.max_pair_fill:
        h, rhs = _normal(each("normal"), prior)
        solver = NormalSolver()
    else:
        rhs = np.sum(each("schur_begin"), axis=0)
        shares = each("coarse_shares")
        sums = np.sum([s for s, _ in shares], axis=0)
        z = coarse_basis(lay.col0, lay.n_knots, sums, np.concatenate([k for _, k in shares]))
        h, solver = _PartsNormal(each, prior), SchurSolver(z)
    theta = np.zeros(lay.n_unknowns)
    warmup = HUBER_WARMUP_ITERATIONS if cfg.loss == "cauchy" else 0
    it, change = 0, 0.0
    for it in range(1, cfg.iterations + 1):
        new_theta = solver.solve(h, rhs, theta)  # each solver its own kind of h
        change = float(np.max(np.abs(new_theta - theta), initial=0.0))
        theta = new_theta
        each("residuals", theta)
        if cfg.loss == "linear" or it == cfg.iterations or (it >= 2 + warmup and change < TOL_M):
            break
        loss = "huber" if it <= warmup else cfg.loss
        if isinstance(h, _PartsNormal):
            rhs = np.sum(each("schur_reweight", loss), axis=0)
            continue
        rows = sum(each("reweigh", loss))
        if rows == 0:
            continue
        if rebuilds(rows, n_samples):
            h, rhs = _normal(each("reweight", True), prior)
            continue
        deltas = [d for d in each("reweight", False) if d is not None]
        h = (h + _joined([d[0] for d in deltas])).tocsr()
        rhs = rhs + _summed([d[1] for d in deltas])
    if isinstance(solver, SchurSolver):
        return _Fit(lay, theta, it, change, solver, None)
    return _Fit(lay, theta, it, change, None, h)


def _summed(vectors: Sequence[np.ndarray]) -> np.ndarray:
    out = vectors[0].copy()
    for v in vectors[1:]:
        out += v
    return out


def _normal(
    shares: Sequence[tuple[sp.csr_matrix, np.ndarray]], prior: sp.csr_matrix
) -> tuple[sp.csr_matrix, np.ndarray]:
    """The normal equations from the parts' shares: H = (joined shares) + prior, as the one solve
    adds them, and rhs."""
    return (_joined([hb for hb, _ in shares]) + prior).tocsr(), _summed([rb for _, rb in shares])
