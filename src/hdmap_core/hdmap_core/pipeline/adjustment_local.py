"""Local update of the network-wide offset adjustment: new drives join a solved fleet.

:func:`~hdmap_core.pipeline.adjustment.adjust_offsets` solves every drive's offset curve from all
steps jointly. When a few drives join a fleet already solved, most of that work only reproduces
the old solution: a new drive's curve is pinned by the drives it shares steps with, and their
curves move by about 1/N of the new drive's own error. :func:`update_offsets` therefore solves
only the ``free`` drives (the new ones, optionally their neighbours), holding every other drive's
curve at its value in the old model:

    lateral_i + o_{d(i)}(s_i) = x_{j, c(i)} + noise_i      (the rows of steps a free drive sees)
    o_d = old model's curve, known, for every fixed drive

The fixed drives' samples stay in the steps (they carry the cluster positions, which are still
eliminated in closed form), with their known offsets added to their lateral positions; only the
free drives' columns are unknown. Association (nearest centre at the corrected positions, lane-shift
search, re-association at the gate), the coarse-to-fine rejection and the IRLS loop are the global
adjustment's, on that restricted system. The cost is that of the free drives' steps, not of the
fleet's.

What it leaves out: the fixed drives do not learn from the new drives, and the gauge (the shift
common to the drives at a place, set by the priors of all of them) stays the old fleet's. Each new
drive moves the global solution by about its offset / N; 5 drives added to 25 left the map
0.13-0.16 m from the global solve's (mean over steps), while as close to the simulator's truth.
So a map within a few cm of the offline one needs a global (re-)solve; this update is for the
time between. Measured in ``scripts/bench_adjustment_local.py`` (docs/adjustment.md, "Local
update").
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
import scipy.sparse as sp

from hdmap_core.pipeline import adjustment_assoc as assoc
from hdmap_core.pipeline.adjustment import (
    HUBER_WARMUP_ITERATIONS,
    ROBUST_K,
    THIN_DRIVES,
    TOL_M,
    AdjustConfig,
    DriveOffset,
    NormalSolver,
    OffsetModel,
    coarse_config,
    design_matrix,
    knot_layout,
    pool_offsets,
    prior_matrix,
    reduced_normal,
    robust_weights,
    sample_residuals,
    shift_and_reassociate,
    update_normal,
)

__all__ = ["update_offsets", "steps_of"]


def steps_of(observations: Sequence[Any], drive_ids: Iterable[str]) -> list[Any]:
    """The observations (steps) that at least one of ``drive_ids`` crosses: all a local update reads."""
    want = set(drive_ids)
    out = []
    for obs in observations:
        ids = getattr(obs, "drive_ids", ())
        try:
            if not want.isdisjoint(ids):
                out.append(obs)
        except TypeError:
            continue
    return out


def update_offsets(
    observations: Sequence[Any],
    *,
    model: OffsetModel,
    free: Iterable[str],
    config: AdjustConfig | None = None,
) -> OffsetModel:
    """``model`` with the curves of the ``free`` drives re-estimated, every other drive held fixed.

    Args:
        observations: StepObservations (as for ``adjust_offsets``); only the steps a free drive
            crosses are read, so passing the whole fleet's is fine.
        model: the current fleet-wide model (its settings must match ``config``'s).
        free: drives to estimate: new drives (absent from ``model``) and any drive to re-fit.
            Drives in the steps that are neither free nor in ``model`` are made free too (their
            offset is unknown).
        config: the adjustment's settings (default ``AdjustConfig()``; ``compute_std`` is ignored:
            no posterior std).

    Returns:
        A new OffsetModel: the old curves of the fixed drives, the new curves of the free drives
        that have usable samples (a free drive without any keeps its old curve, if it had one).
        ``stats`` holds ``n_free``, ``n_fixed``, ``n_steps`` (read), ``n_samples_used``,
        ``iterations`` and ``lane_shifts``.
    """
    cfg = config if config is not None else AdjustConfig()
    free_set = set(free)
    local = steps_of(observations, free_set)
    stats: dict[str, Any] = {}
    pool = assoc.gather(local, stats)
    free_set.update(d for d in pool.drive_ids if d not in model.drives)
    is_free = np.array([d in free_set for d in pool.drive_ids], dtype=bool)
    old = pool_offsets(pool, model)  # the old model's offsets (0 for new drives): a warm start
    fixed_off = np.where(is_free[pool.drive], 0.0, old) if pool.s_m.size else old
    base: dict[str, Any] = dict(
        knot_spacing_m=cfg.knot_spacing_m,
        correlation_length_m=cfg.correlation_length_m,
        drift_sigma_m=cfg.drift_sigma_m,
        bias_sigma_m=cfg.bias_sigma_m,
    )
    stats.update(n_free=int(is_free.sum()), n_fixed=int((~is_free).sum()), lane_shifts=0, iterations=0)
    if pool.s_m.size == 0 or not is_free.any():
        stats["n_samples_used"] = 0
        return OffsetModel(**base, drives=dict(model.drives), stats=stats)
    label = pool.label
    if cfg.reassociate_rounds > 0:
        # association at the old model's corrected positions: the fixed drives' centres are where
        # the solved fleet put them; a new drive's raw samples lie within its localization error
        label = assoc.reassociate(pool, label, old, assoc.centres(pool, label, pool.lateral_m + old), gate_m=np.inf)
    curves: dict[str, DriveOffset] = {}
    n_shifted = 0
    for round_ in range(max(cfg.reassociate_rounds, 1)):
        samples = assoc.select(pool, label, THIN_DRIVES)
        if samples.s_m.size == 0:
            break
        fit = _fit_local(samples, fixed_off, is_free, cfg)
        if fit is None:
            break
        curves, iterations = fit
        stats["iterations"] = iterations
        if round_ + 1 >= cfg.reassociate_rounds:
            break
        merged = OffsetModel(**base, drives={**model.drives, **curves})
        label, n = shift_and_reassociate(pool, label, merged, cfg, free=is_free)
        n_shifted += n
    stats["lane_shifts"] = n_shifted
    stats["n_samples_used"] = int(assoc.select(pool, label, THIN_DRIVES).s_m.size)
    return OffsetModel(**base, drives={**model.drives, **curves}, stats=stats)


def _fit_local(
    samples: assoc.Samples, fixed_off: np.ndarray, is_free_pool: np.ndarray, cfg: AdjustConfig
) -> tuple[dict[str, DriveOffset], int] | None:
    """Coarse rejection then the curves of the free drives; None when no free drive has samples."""
    free_d = is_free_pool[samples.pool_drive]
    if not free_d[samples.drive].any():
        return None
    shifted = replace(samples, lateral_m=samples.lateral_m + fixed_off[samples.pool_index])
    keep = np.ones(samples.s_m.size, dtype=bool)
    if cfg.coarse_reject_m > 0 and cfg.drift_sigma_m > 0:
        # RULE coarse-to-fine, as in the global adjustment (one constant per free drive first)
        _, _, r = _irls_free(shifted, free_d, coarse_config(cfg), keep)
        keep = np.abs(r) <= cfg.coarse_reject_m
    lay, (theta, iterations), _ = _irls_free(shifted, free_d, cfg, keep)
    out: dict[str, DriveOffset] = {}
    cols = _free_columns(lay, free_d)
    full = np.zeros(lay.n_unknowns)
    full[cols] = theta
    for d in np.flatnonzero(free_d):
        c0, nk = int(lay.col0[d]), int(lay.n_knots[d])
        nan = np.full(nk, np.nan)
        out[samples.drive_ids[d]] = DriveOffset(
            k0=int(lay.k0[d]),
            bias_m=float(full[c0]),
            drift_m=full[c0 + 1 : c0 + 1 + nk].copy(),
            var_bias=float("nan"),
            cov_bias_drift=nan,
            var_drift=nan.copy(),
            cov_drift_next=np.full(max(nk - 1, 0), np.nan),
        )
    return out, iterations


def _free_columns(lay: Any, free_d: np.ndarray) -> np.ndarray:
    owner = np.repeat(np.arange(lay.col0.size), 1 + lay.n_knots)
    return np.flatnonzero(free_d[owner])


def _irls_free(
    samples: assoc.Samples, free_d: np.ndarray, cfg: AdjustConfig, keep: np.ndarray
) -> tuple[Any, tuple[np.ndarray, int], np.ndarray]:
    """The global adjustment's IRLS loop (``adjustment._irls``) with only the free drives' columns
    unknown; ``samples.lateral_m`` already holds the fixed drives' corrected positions. Returns the
    layout of all drives, (theta of the free columns, iterations) and the residuals."""
    lay = knot_layout(samples, cfg)
    cols = _free_columns(lay, free_d)
    a = design_matrix(samples, lay, cfg)[:, cols].tocsr()
    prior = prior_matrix(lay, cfg)[cols][:, cols].tocsr()  # a drive's prior couples its own columns only
    info0 = np.where(keep, cfg.noise_sigma_m**-2, 0.0)
    theta = np.zeros(cols.size)
    warmup = HUBER_WARMUP_ITERATIONS if cfg.loss == "cauchy" else 0
    info = info0.copy()
    h, rhs = reduced_normal(a, samples.cluster, samples.n_clusters, info, samples.lateral_m)
    h = sp.csr_matrix(h + prior)
    solver = NormalSolver()
    it = 0
    r = np.zeros(samples.s_m.size)
    for it in range(1, cfg.iterations + 1):
        new_theta = solver.solve(h, rhs, theta)
        change = float(np.max(np.abs(new_theta - theta), initial=0.0))
        theta = new_theta
        r = sample_residuals(a, theta, samples, info)
        if cfg.loss == "linear" or it == cfg.iterations or (it >= 2 + warmup and change < TOL_M):
            break
        weights = robust_weights(r, ROBUST_K * cfg.noise_sigma_m, "huber" if it <= warmup else cfg.loss)
        h, rhs, info = update_normal(h, rhs, a, samples, prior, info, info0 * weights)
    return lay, (theta, it), r
