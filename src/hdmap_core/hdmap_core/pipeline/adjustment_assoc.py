"""Sample pool and association for the network-wide offset adjustment (``hdmap_core.pipeline.adjustment``).

Internal to the adjustment: gathering all steps' samples into flat arrays (bad steps skipped and
named), selecting the informative ones, and the global association (cluster centres, nearest
centre of the same step and type, per-drive lane-shift search). Everything is vectorised over all
steps; see docs/adjustment.md for the method.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__: list[str] = []  # internal module

MAX_REPORTED_PROBLEMS = 20
#: samples scored per chunk of the lane-shift search (each against every shift of the grid)
SHIFT_CHUNK_SAMPLES = 20_000
#: samples looked up per chunk by ``nearest`` (its temporaries, a dozen arrays per sample, then
#: grow with the chunk, not with a block's millions of samples; per sample, so the same result)
NEAREST_CHUNK_SAMPLES = 262_144


@dataclass(frozen=True)
class Pool:
    """Every finite sample of every readable step (before any cluster filtering)."""

    drive: np.ndarray  # (n,) int drive index into drive_ids
    drive_ids: tuple[str, ...]
    s_m: np.ndarray  # (n,) travelled distance
    lateral_m: np.ndarray  # (n,)
    step: np.ndarray  # (n,) int step number (position in the observation sequence)
    ftype: np.ndarray  # (n,) int FeatureType code
    label: np.ndarray  # (n,) int cluster label from the observations (-1 = none)
    step_drives: np.ndarray  # (number of observations,) distinct drives of each step (0 if skipped)
    #: number of the first step in the whole observation sequence (a part of it: ``adjustment_dist``),
    #: or, for a part whose steps are not consecutive there, the number of each of its steps;
    #: ``select`` thins by the global step number
    step0: int | np.ndarray = 0
    #: (D,) the step of each drive's first sample (finite or not): drives are numbered in that
    #: order (``adjustment_dist`` merges the parts' drives by it)
    first_step: np.ndarray | None = None
    #: (number of observations, 2) each step's cut midpoint [m] (NaN if unreadable): where it is
    step_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True)
class Samples:
    """The samples one fit uses: in clusters seen by >= 2 drives, indices compacted."""

    drive: np.ndarray  # (n,) int drive index into drive_ids
    s_m: np.ndarray  # (n,) travelled distance
    lateral_m: np.ndarray  # (n,)
    cluster: np.ndarray  # (n,) int global cluster index 0..C-1
    n_clusters: int
    drive_ids: tuple[str, ...]
    pool_index: np.ndarray  # (n,) position of each sample in the Pool
    pool_drive: np.ndarray  # (D,) pool drive index of each drive
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (n, 2) its step's midpoint [m]


def gather(observations: Sequence[Any], stats: dict[str, Any]) -> Pool:
    """Concatenate all steps' samples; skip malformed steps, drop non-finite samples."""
    drive_lists: list[tuple[str, ...]] = []
    s_list, lat_list, cl_list, type_list, step_list = [], [], [], [], []
    problems: list[str] = []
    n_bad_steps = 0
    step_drives = np.zeros(len(observations), dtype=np.int64)
    step_xy = np.full((len(observations), 2), np.nan)
    for j, obs in enumerate(observations):
        try:
            ids = tuple(obs.drive_ids)
            s = np.asarray(obs.drive_s_m, dtype=float).ravel()
            lat = np.asarray(obs.lateral_m, dtype=float).ravel()
            cl = np.asarray(obs.cluster).ravel()
            ty = np.asarray(obs.types).ravel()
            if ty.dtype == object:  # e.g. FeatureType members: IntEnum converts exactly
                ty = ty.astype(np.int64)
        except (AttributeError, TypeError, ValueError) as err:
            reason = f"unreadable ({err})"
        else:
            m = len(ids)
            reason = (
                ""
                if s.size == lat.size == cl.size == ty.size == m
                else (
                    f"array lengths differ: drive_ids {m}, drive_s_m {s.size}, lateral_m {lat.size}, "
                    f"types {ty.size}, cluster {cl.size}"
                )
            )
            if not reason and m and (cl.dtype.kind not in "iu" or ty.dtype.kind not in "iu"):
                reason = f"cluster labels ({cl.dtype}) and types ({ty.dtype}) must be integers"
        if reason:
            n_bad_steps += 1
            if len(problems) < MAX_REPORTED_PROBLEMS:
                problems.append(f"step {getattr(obs, 'pivot_id', '?')}#{getattr(obs, 'index', j)}: {reason}")
            continue
        drive_lists.append(ids)
        step_drives[j] = len(set(ids))
        step_xy[j] = _midpoint(obs)
        s_list.append(s)
        lat_list.append(lat)
        cl_list.append(cl)
        type_list.append(ty)
        step_list.append(j)
    stats["n_steps"] = len(observations)
    stats["n_steps_skipped"] = n_bad_steps
    stats["problems"] = problems
    if not s_list:
        stats["n_samples"] = stats["n_nonfinite_dropped"] = 0
        e_i, e_f = np.zeros(0, np.int64), np.zeros(0)
        return Pool(
            e_i, (), e_f, e_f, e_i, e_i, e_i, np.zeros(len(observations), np.int64), first_step=e_i, step_xy=step_xy
        )
    s = np.concatenate(s_list)
    lat = np.concatenate(lat_list)
    label = np.concatenate(cl_list).astype(np.int64)
    ftype = np.concatenate(type_list).astype(np.int64)
    step = np.repeat(np.asarray(step_list, dtype=np.int64), [len(ids) for ids in drive_lists])
    all_ids = [d for ids in drive_lists for d in ids]
    lookup: dict[str, int] = {}
    # index of each drive's first sample: unique per drive, built at C speed
    first = np.fromiter(map(lookup.setdefault, all_ids, range(len(all_ids))), dtype=np.int64, count=len(all_ids))
    stats["n_samples"] = int(s.size)
    finite = np.isfinite(s) & np.isfinite(lat)
    stats["n_nonfinite_dropped"] = int((~finite).sum())
    drive, firsts = compact(first[finite], return_values=True)
    return Pool(
        drive,
        tuple(all_ids[i] for i in firsts),
        s[finite],
        lat[finite],
        step[finite],
        ftype[finite],
        label[finite],
        step_drives,
        first_step=step[firsts],
        step_xy=step_xy,
    )


def _midpoint(obs: Any) -> np.ndarray:
    """A step's cut midpoint (NaN when it has none: only the matrix-free solve's coarse space uses it)."""
    try:
        xy = np.asarray(obs.midpoint, dtype=float).ravel()
    except (AttributeError, TypeError, ValueError):
        return np.full(2, np.nan)
    return xy[:2] if xy.size >= 2 else np.full(2, np.nan)


def select(pool: Pool, label: np.ndarray, thin_drives: int = 0) -> Samples:
    """The samples with a label, in clusters seen by >= 2 different drives (others carry no information).

    ``thin_drives`` > 0: a step seen by d drives is used only when its number is a multiple of
    ceil(d / thin_drives). Eliminating a cluster's position couples every pair of its drives, so
    the work per step grows with d^2; thinned, it grows with d, and a drive's offset curve (knots
    every 200 m) is still fitted from dozens of steps per knot.
    """
    keep = np.flatnonzero(label >= 0)
    if thin_drives > 0 and keep.size:
        stride = np.maximum(1, -(-pool.step_drives // thin_drives))
        st = pool.step[keep]
        keep = keep[step_numbers(pool, st) % stride[st] == 0]
    cl, n_cl = compact(pool.step[keep] * (int(label[keep].max(initial=0)) + 1) + label[keep])
    _, first_of_pair = np.unique(cl * max(len(pool.drive_ids), 1) + pool.drive[keep], return_index=True)
    n_drives_in = np.bincount(cl[first_of_pair], minlength=n_cl)
    informative = n_drives_in[cl] >= 2
    used = keep[informative]
    cl, n_clusters = compact(cl[informative])
    drive, pool_drive = compact(pool.drive[used], return_values=True)
    return Samples(
        drive=drive,
        s_m=pool.s_m[used],
        lateral_m=pool.lateral_m[used],
        cluster=cl,
        n_clusters=n_clusters,
        drive_ids=tuple(pool.drive_ids[i] for i in pool_drive),
        pool_index=used,
        pool_drive=np.asarray(pool_drive, dtype=np.int64),
        xy=pool.step_xy[pool.step[used]] if pool.step_xy.shape[0] else np.full((used.size, 2), np.nan),
    )


def step_numbers(pool: Pool, step: np.ndarray) -> np.ndarray:
    """The numbers in the whole observation sequence of this pool's steps ``step``."""
    if isinstance(pool.step0, np.ndarray):
        return pool.step0[step]
    return step + pool.step0


#: what sets the scale of ``centres``' sort keys: max |v| of the labelled samples, max |v| of
#: all samples, the largest type code; a part of the fleet is given the whole fleet's
#: (``adjustment_dist``), so that its keys round as the one solve's
Extent = tuple[float, float, int]


def extent(pool: Pool, label: np.ndarray, v: np.ndarray) -> Extent:
    """``centres``' scale from this pool's samples (``max_extent`` of the parts' for the fleet's)."""
    return (
        float(np.abs(v[label >= 0]).max(initial=0.0)),
        float(np.abs(v).max(initial=0.0)),
        int(pool.ftype.max(initial=0)),
    )


def max_extent(extents: Sequence[Extent]) -> Extent:
    """The fleet's ``Extent`` from its parts'."""
    return (max(e[0] for e in extents), max(e[1] for e in extents), max(e[2] for e in extents))


@dataclass(frozen=True)
class Centres:
    """Cluster centres of all steps, sorted by (step, type) group then position."""

    key: np.ndarray  # (K,) sort key: group * span + position + span / 2
    group: np.ndarray  # (K,) step * n_types + type
    pos: np.ndarray  # (K,) centre position along the cut [m]
    label: np.ndarray  # (K,) cluster label within its step
    n_types: int
    span: float


def centres(pool: Pool, label: np.ndarray, v: np.ndarray, scale: Extent | None = None) -> Centres | None:
    """Centres (median of the members' positions ``v``) of the clusters of ``label``; ``scale``:
    the whole fleet's ``extent`` when this pool is a part of it (default: this pool's)."""
    have = np.flatnonzero(label >= 0)
    if have.size == 0:
        return None
    v_have, v_all, top_type = scale if scale is not None else extent(pool, label, v)
    g, n_g = compact(pool.step[have] * (int(label[have].max()) + 1) + label[have])
    width = 2.0 * v_have + 1.0
    o = np.argsort(g * width + (v[have] + width / 2))  # by cluster, then position
    starts = np.concatenate([[0], np.cumsum(np.bincount(g, minlength=n_g))[:-1]])
    mid = have[o][starts + np.bincount(g, minlength=n_g) // 2]
    n_types = top_type + 1
    span = 2.0 * v_all + 20.0
    group = pool.step[mid] * n_types + pool.ftype[mid]
    key = group * span + (v[mid] + span / 2)
    o = np.argsort(key)
    return Centres(key[o], group[o], v[mid][o], label[mid][o], n_types, span)


def nearest(cen: Centres, step: np.ndarray, ftype: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label of and distance to the nearest centre of the same step and type (-1, inf if none)."""
    if v.ndim == 1 and v.size > NEAREST_CHUNK_SAMPLES:
        best = np.empty(v.shape, dtype=np.int64)
        best_d = np.empty(v.shape)
        for c0 in range(0, v.size, NEAREST_CHUNK_SAMPLES):
            part = slice(c0, c0 + NEAREST_CHUNK_SAMPLES)
            best[part], best_d[part] = nearest(cen, step[part], ftype[part], v[part])
        return best, best_d
    grp = step * cen.n_types + ftype
    idx = np.searchsorted(cen.key, grp * cen.span + (v + cen.span / 2))
    best = np.full(v.shape, -1, dtype=np.int64)
    best_d = np.full(v.shape, np.inf)
    for cand in (idx - 1, idx):
        cc = np.clip(cand, 0, cen.key.size - 1)
        ok = (cand >= 0) & (cand < cen.key.size) & (cen.group[cc] == grp)
        d = np.where(ok, np.abs(v - cen.pos[cc]), np.inf)
        better = d < best_d
        best[better], best_d[better] = cen.label[cc[better]], d[better]
    return best, best_d


def reassociate(pool: Pool, label: np.ndarray, offset: np.ndarray, cen: Centres | None, *, gate_m: float) -> np.ndarray:
    """New cluster labels: each sample joins the nearest cluster centre of its step and type.

    ``cen``: the current clusters' centres (``centres``); a sample whose corrected position
    ``lateral + offset`` is farther than ``gate_m`` from every centre gets -1. Labels stay unique
    within a step (a centre keeps its cluster's label). Vectorised over all steps.
    """
    v = pool.lateral_m + offset
    if cen is None:
        return label.copy()
    best, dist = nearest(cen, pool.step, pool.ftype, v)
    return np.where(dist <= gate_m, best, -1).astype(np.int64)


def lane_shift_search(
    pool: Pool,
    cen: Centres | None,
    offset: np.ndarray,
    bias_m: np.ndarray,
    *,
    search_m: float,
    gate_m: float,
    noise_sigma_m: float,
    bias_sigma_m: float,
) -> np.ndarray:
    """(D,) constant correction per pool drive that best fits the cluster centres [m].

    ``offset``: (n,) current offset of every pool sample; ``bias_m``: (D,) current bias per drive.
    Per drive, a grid of shifts c in [-search_m, search_m] is scored with a truncated
    quadratic: sum_i min(d_i(c), gate)^2 / noise^2 + (bias + c)^2 / bias_sigma^2, d_i the distance
    of the shifted sample to the nearest centre of its step and type. Unlike IRLS this sees the
    samples that a lane-off association rejects (borders, solid lines of the other type), so a
    drive associated one lane off over its whole length snaps back. At most ~200 samples per drive.
    """
    n_d = len(pool.drive_ids)
    if cen is None or search_m <= 0:
        return np.zeros(n_d)
    grid = shift_grid(search_m)
    cost = shift_costs(pool, cen, offset, shift_picks(pool), grid, gate_m=gate_m, noise_sigma_m=noise_sigma_m)
    return choose_shifts(cost, bias_m, grid, bias_sigma_m=bias_sigma_m)


def shift_grid(search_m: float) -> np.ndarray:
    """The constant shifts the lane-shift search tries: 0.25 m apart (fine enough to tell lanes
    apart; the fit that follows refines the offset)."""
    return np.arange(-search_m, search_m + 1e-9, 0.25)


def shift_picks(pool: Pool, first_rank: np.ndarray | None = None, stride: np.ndarray | None = None) -> np.ndarray:
    """The pool samples the lane-shift search scores: every ``stride``-th of each drive's samples
    in pool order (at most ~200 per drive), by drive then position.

    ``first_rank`` / ``stride`` (per pool drive; a part of the observations, ``adjustment_dist``):
    the rank, in the whole fleet's pool, of the drive's first sample here, and the whole fleet's
    stride; by default this pool is the whole fleet."""
    order = np.argsort(pool.drive, kind="stable")
    counts = np.bincount(pool.drive, minlength=len(pool.drive_ids))
    bounds = np.concatenate([[0], np.cumsum(counts)])
    if stride is None:
        stride = np.maximum(1, counts // 200)
    if first_rank is None:
        first_rank = np.zeros(len(pool.drive_ids), dtype=np.int64)
    d = pool.drive[order]
    rank = first_rank[d] + np.arange(order.size) - bounds[d]
    return order[rank % stride[d] == 0]


def shift_costs(
    pool: Pool,
    cen: Centres,
    offset: np.ndarray,
    sel: np.ndarray,
    grid: np.ndarray,
    *,
    gate_m: float,
    noise_sigma_m: float,
) -> np.ndarray:
    """(D, shifts) data term of the lane-shift search: sum over the picked samples ``sel`` of each
    drive of min(d_i(c), gate)^2 / noise^2."""
    v = pool.lateral_m + offset
    cost = np.zeros((len(pool.drive_ids), grid.size))
    # RULE bounded memory: (samples x shifts) at once is ~0.5 GB for a tile of 745 drives, more
    # for a block of tiles. Consecutive chunks add the same terms in the same order (add.at is
    # sequential), so the cost is bit-identical.
    for c0 in range(0, sel.size, SHIFT_CHUNK_SAMPLES):
        part = sel[c0 : c0 + SHIFT_CHUNK_SAMPLES]
        vv = v[part][:, None] + grid[None, :]
        _, dist = nearest(cen, pool.step[part][:, None], pool.ftype[part][:, None], vv)
        np.add.at(cost, pool.drive[part], np.minimum(dist, gate_m) ** 2 / noise_sigma_m**2)
    return cost


def choose_shifts(cost: np.ndarray, bias_m: np.ndarray, grid: np.ndarray, *, bias_sigma_m: float) -> np.ndarray:
    """(D,) the shift per drive from the data term ``cost`` (``shift_costs``) and the bias prior."""
    cost = cost + (bias_m[:, None] + grid[None, :]) ** 2 / bias_sigma_m**2
    best = grid[np.argmin(cost, axis=1)]
    # keep the current solution unless a shift is clearly better (a lane, not a nudge)
    at_zero = cost[:, np.argmin(np.abs(grid))]
    return np.where((np.abs(best) >= 1.0) & (cost.min(axis=1) < at_zero - 10.0), best, 0.0)


def compact(key: np.ndarray, *, return_values: bool = False) -> tuple[np.ndarray, Any]:
    """Relabel non-negative int keys to 0..K-1 in increasing key order.

    Returns (labels, K), or (labels, the distinct keys) with ``return_values``. O(n) with a
    lookup table when the key range is small, else a sort.
    """
    if key.size == 0:
        return key.astype(np.int64), (key if return_values else 0)
    top = int(key.max()) + 1
    if top <= 8 * key.size + 1024:
        used = np.zeros(top, dtype=bool)
        used[key] = True
        new_id = np.cumsum(used) - 1
        return new_id[key].astype(np.int64), (np.flatnonzero(used) if return_values else int(used.sum()))
    values, labels = np.unique(key, return_inverse=True)
    return labels.astype(np.int64), (values if return_values else values.size)
