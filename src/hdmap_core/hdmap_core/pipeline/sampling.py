"""Sec. IV-A: step-wise lateral sampling along a pivot drive.

The pivot trajectory is walked in ``step_m`` steps (paper: 2 m). Each step gets a long lateral cut
line through the trajectory point, perpendicular to the heading, which is intersected with all
detection segments at once (all steps of the pivot in one vectorised query). Samples of drives
going the other way are dropped by heading. The cut line is then refined to the ego road: from
the pivot point the first road-border samples on each side, extended by a spread margin (dl_s) and
a constant margin (dl_c); the cut-line length is smoothed with decaying weights for older steps and
the midpoint with a plain moving average, so that the width survives stretches without borders.
The refined cut is collinear with the initial one, so "sampling again" is a filter of the initial
samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from hdmap_core.checks import Rule, check_range
from hdmap_core.errors import ConfigError
from hdmap_core.geometry import arc_length, interp_angle, resample_by_distance, wrap_angle
from hdmap_core.model import Drive, FeatureType
from hdmap_core.pipeline.preprocess import DetectionIndex
from hdmap_core.steps import left_normal

__all__ = ["SamplingConfig", "PivotSamples", "pivot_groups", "pivot_walk", "sample_pivot", "refine_cuts"]

ShiftFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

# Cut-line refinement rules (Sec. IV-A; values the paper leaves open, fixed since the first
# measurements, docs/pipeline.md "Stages as implemented"):
#: border samples within this distance beyond the first one form the "first road border" group
#: whose spread sets dl_s [m]
_BORDER_WINDOW_M = 2.0
#: window and per-step weight decay of the weighted moving average of the cut length (older steps
#: weigh decay^k) ...
_WIDTH_SMOOTHING_STEPS = 10
_WIDTH_DECAY = 0.8
#: ... and window of the plain moving average of the midpoint
_MIDPOINT_SMOOTHING_STEPS = 5
#: cut length used before any border was seen [m]
_DEFAULT_WIDTH_M = 16.0
#: the refined cut is at least this long [m]
_MIN_WIDTH_M = 3.0


@dataclass(frozen=True)
class SamplingConfig:
    """Lateral sampling and cut-line refinement (Sec. IV-A); the defaults are the recommended
    method. Values the paper leaves open are marked (open).

    Attributes:
        step_m: distance between steps along the pivot (paper: 2 m).
        initial_half_length_m: half length of the first cut line (open: "several times a highway
            width"; 30 m reaches the far edge of a 4-lane carriageway from any lane).
        max_heading_diff_deg: samples of drives whose heading differs more from the pivot's are
            dropped as opposite direction (open).
        spread_factor: dl_s = spread_factor * std(first border group) (open).
        margin_m: constant margin dl_c [m] (open).
        refined: the cut rules measured and adopted since the paper (its fixed ``refined``
            rules: a border needs the support of a share of the step's drives, an open side ends
            at a gap in its samples, a step whose pivot lies beyond its cut is not aligned).
            False: the paper's reading.
    """

    step_m: float = 2.0
    initial_half_length_m: float = 30.0
    max_heading_diff_deg: float = 60.0
    spread_factor: float = 2.0
    margin_m: float = 0.5
    refined: bool = True

    #: a border sample only counts as the first border when at least this many border samples
    #: lie in its window (one badly localised drive cannot cut the road short)
    min_border_support: ClassVar[int] = 2
    #: the refined cut is at most this long [m]
    max_width_m: ClassVar[float] = 40.0
    #: a side without a supported first border also keeps its samples up to a border sample
    #: that is its outermost sample (``_side_reach``; the final pass only: ``FinalSampling``)
    outer_border_reach: ClassVar[bool] = False
    #: (refined) the border support is also at least this share of the step's drives
    min_border_support_fraction = Rule("refined", 0.05, 0.0)
    #: (refined) a side without a road border ends after the chain of samples from the pivot
    #: with no gap wider than this, plus the margins; off: the smoothed width of earlier steps [m]
    open_side_gap_m = Rule("refined", 4.0, 0.0)
    #: (refined) a step whose pivot (``PivotSamples.pose``) lies more than this beyond its
    #: refined cut is off its ego road (``PivotSamples.off_cut``) and not aligned [m]
    max_pivot_outside_m = Rule("refined", 2.0, math.inf)

    def __post_init__(self) -> None:
        check_range(self, ("step_m", "initial_half_length_m", "max_heading_diff_deg"), low=0.0, low_open=True)
        check_range(self, ("margin_m", "spread_factor"), low=0.0)


@dataclass(frozen=True)
class PivotSamples:
    """The refined samples of all steps of one pivot drive.

    Attributes:
        s_m: (Q,) pivot travelled distance per step [m].
        point: (Q, 2) pivot trajectory point per step [m].
        heading: (Q,) pivot heading per step [rad].
        midpoint: (Q, 2) refined (smoothed) cut midpoint [m].
        width_m: (Q,) refined cut length [m].
        skipped: (Q,) True where the step was not sampled (already processed).
        ptr: (Q + 1,) CSR offsets: samples of step q are ``ptr[q]:ptr[q+1]``.
        lateral_m: (M,) sample position along the cut from the refined midpoint, + = left [m].
        types: (M,) FeatureType codes.
        drive: (M,) drive index (``DetectionIndex.drive_ids``).
        drive_s_m: (M,) travelled distance of the sampled drive at the sample [m].
        off_cut: (Q,) True where the pivot (``pose``) lies beyond the refined cut by more than
            ``SamplingConfig.max_pivot_outside_m`` (the step is not on the pivot's road).
        pose: (Q, 2) the pivot point corrected like its samples (``shift`` of ``sample_pivot``:
            the offset model at the pivot's own travelled distance, along the cut) [m]; None:
            ``point``.
    """

    s_m: np.ndarray
    point: np.ndarray
    heading: np.ndarray
    midpoint: np.ndarray
    width_m: np.ndarray
    skipped: np.ndarray
    ptr: np.ndarray
    lateral_m: np.ndarray
    types: np.ndarray
    drive: np.ndarray
    drive_s_m: np.ndarray
    off_cut: np.ndarray | None = None
    pose: np.ndarray | None = None

    @property
    def n_steps(self) -> int:
        return len(self.s_m)


def pivot_walk(drive: Drive, *, step_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points every ``step_m`` along a drive's trajectory.

    Returns:
        (s (Q,) [m], points (Q, 2) [m], heading (Q,) [rad]); heading from the drive's yaw.
    """
    xy = np.asarray(drive.xy, dtype=float)
    pts, s = resample_by_distance(xy, step_m)
    s_traj = arc_length(xy)
    keep = np.concatenate([[True], np.diff(s_traj) > 1e-9])
    if keep.sum() < 2:
        return s, pts, np.full(len(s), float(np.asarray(drive.yaw, dtype=float)[0]))
    heading = interp_angle(s, s_traj[keep], np.asarray(drive.yaw, dtype=float)[keep])
    return s, pts, heading


def _side_first_border(
    q: np.ndarray, d: np.ndarray, n_steps: int, *, window_m: float, support: np.ndarray
) -> np.ndarray:
    """Per step, the distance d >= 0 of the first border sample with enough support, else NaN.

    q: (B,) step of each border sample on this side; d: (B,) its distance from the pivot [m];
    support: (n_steps,) border samples needed in the window, per step.
    """
    first = np.full(n_steps, np.nan)
    if len(q) == 0:
        return first
    order = np.lexsort((d, q))
    q, d = q[order], d[order]
    key = q * 1e6 + d  # steps are far apart in key space; d < 1e5 m
    n_in_window = np.searchsorted(key, key + window_m, side="right") - np.arange(len(key))
    ok = n_in_window >= support[q]
    qk, dk = q[ok], d[ok]
    # First qualifying sample per step (already sorted by d within a step).
    is_first = np.ones(len(qk), dtype=bool)
    is_first[1:] = qk[1:] != qk[:-1]
    first[qk[is_first]] = dk[is_first]
    return first


def _side_chain_end(q: np.ndarray, d: np.ndarray, n_steps: int, *, gap_m: float) -> np.ndarray:
    """Per step, the distance d >= 0 of the outermost sample reached from the pivot through
    samples no more than ``gap_m`` apart (the first one within ``gap_m`` of the pivot), else NaN.
    q: (S,) step of each sample on this side; d: (S,) its distance from the pivot [m]."""
    out = np.full(n_steps, np.nan)
    if len(q) == 0:
        return out
    order = np.lexsort((d, q))
    q, d = q[order], d[order]
    new_step = np.ones(len(q), dtype=bool)
    new_step[1:] = q[1:] != q[:-1]
    gap = np.where(new_step, d, np.diff(d, prepend=0.0))
    brk = (gap > gap_m).astype(np.int64)
    cum = np.cumsum(brk)
    start = np.flatnonzero(new_step)
    # Breaks counted from the step's first sample (inclusive): 0 = still on the chain.
    cum_in_step = cum - np.repeat(cum[start] - brk[start], np.diff(np.r_[start, len(q)]))
    chain = cum_in_step == 0
    # Samples are sorted by d within a step, so the last chained sample per step is the outermost.
    qc, dc = q[chain], d[chain]
    if len(qc):
        is_last = np.ones(len(qc), dtype=bool)
        is_last[:-1] = qc[1:] != qc[:-1]
        out[qc[is_last]] = dc[is_last]
    return out


def _side_end(q: np.ndarray, d: np.ndarray, first: np.ndarray, *, config: SamplingConfig) -> np.ndarray:
    """Raw cut end per step on one side, as a distance >= 0 from the pivot (NaN: no border)."""
    n = len(first)
    in_group = np.isfinite(first[q]) & (d >= first[q]) & (d <= first[q] + _BORDER_WINDOW_M)
    qg, dg = q[in_group], d[in_group]
    cnt = np.bincount(qg, minlength=n).astype(float)
    s1 = np.bincount(qg, weights=dg, minlength=n)
    s2 = np.bincount(qg, weights=dg * dg, minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / cnt
        std = np.sqrt(np.maximum(s2 / cnt - mean * mean, 0.0))
    return mean + config.spread_factor * std + config.margin_m


def _causal_weighted_mean(values: np.ndarray, n: int, decay: float) -> np.ndarray:
    """Causal moving average over the last n values, weights decay^age; NaN values ignored.
    Steps with no value in their window become NaN."""
    w = decay ** np.arange(n)
    ok = np.isfinite(values)
    num = np.convolve(np.where(ok, values, 0.0), w)[: len(values)]
    den = np.convolve(ok.astype(float), w)[: len(values)]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def _fill(values: np.ndarray, default: float) -> np.ndarray:
    """Forward fill NaNs, then back fill the leading ones, then the default."""
    v = values.copy()
    ok = np.isfinite(v)
    if not ok.any():
        return np.full_like(v, default)
    idx = np.where(ok, np.arange(len(v)), -1)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.argmax(ok))
    idx[idx < 0] = first
    return v[idx]


def _border_support(step: np.ndarray, n_steps: int, config: SamplingConfig, drive: np.ndarray | None) -> np.ndarray:
    """(n_steps,) border samples needed in the window for a first border, per step."""
    support = np.full(n_steps, config.min_border_support, dtype=np.int64)
    if drive is not None and config.min_border_support_fraction > 0 and len(step):
        nd = int(drive.max()) + 1
        n_drives = np.bincount(np.unique(step * nd + drive) // nd, minlength=n_steps)
        support = np.maximum(support, np.ceil(config.min_border_support_fraction * n_drives).astype(np.int64))
    return support


def _side_reach(
    q: np.ndarray, d: np.ndarray, first: np.ndarray, qa: np.ndarray, da: np.ndarray, *, config: SamplingConfig
) -> np.ndarray:
    """``SamplingConfig.outer_border_reach`` on one side: per step, how far (distance >= 0 from
    the pivot) samples are kept beyond the refined cut, NaN where it adds nothing.

    On a side where no border sample has the support to be the first border (``first`` NaN), a
    border sample that is the outermost sample of the side (nothing of any type lies beyond it)
    is the road's edge as far as any drive saw: it cannot cut the road short, which is what the
    support rule guards against. Its group's end (spread and constant margins, as a first
    border's) is the reach. q, d: the side's border samples; qa, da: all its samples.
    """
    n_steps = len(first)
    outer = np.full(n_steps, -np.inf)
    np.maximum.at(outer, qa, da)
    # RULE outermost border: a border sample nothing lies beyond, on a side without a first border
    lone = np.isnan(first[q]) & (d >= outer[q])
    edge = np.full(n_steps, np.nan)
    edge[q[lone]] = d[lone]
    return _side_end(q, d, edge, config=config)


def refine_cuts(
    step: np.ndarray,
    t_m: np.ndarray,
    types: np.ndarray,
    n_steps: int,
    *,
    config: SamplingConfig,
    drive: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Refined (smoothed) cut midpoint offset and length per step.

    Args:
        step: (H,) step index of each sample; t_m: (H,) sample position along the initial cut
            from the pivot point, + = left [m]; types: (H,) FeatureType codes.
        n_steps: Q.
        drive: optional (H,) drive of each sample, for ``min_border_support_fraction``.

    Returns:
        (mid_m (Q,) midpoint offset from the pivot point along the cut [m], width_m (Q,) [m]).
    """
    mid, width, _, _ = _refine(step, t_m, types, n_steps, config=config, drive=drive)
    return mid, width


def _refine(
    step: np.ndarray,
    t_m: np.ndarray,
    types: np.ndarray,
    n_steps: int,
    *,
    config: SamplingConfig,
    drive: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``refine_cuts`` plus, with ``SamplingConfig.outer_border_reach``, the reach of each side
    along the initial cut from the pivot point (right < 0, left > 0; NaN: none, always NaN
    without the option): (mid_m, width_m, reach_right_m, reach_left_m), each (Q,)."""
    border = types == FeatureType.ROAD_BORDER
    support = _border_support(step, n_steps, config, drive)
    ends, reach = [], []
    for side, sign in ((t_m > 0, 1.0), (t_m < 0, -1.0)):
        mask = border & side
        q, d = step[mask], sign * t_m[mask]
        qa, da = step[side], sign * t_m[side]
        first = _side_first_border(q, d, n_steps, window_m=_BORDER_WINDOW_M, support=support)
        end = _side_end(q, d, first, config=config)
        if config.open_side_gap_m > 0 and np.isnan(end).any():
            chain = _side_chain_end(qa, da, n_steps, gap_m=config.open_side_gap_m)
            open_end = _side_end(qa, da, chain, config=config)
            end = np.where(np.isnan(end), open_end, end)
        ends.append(end)
        reach.append(
            sign * _side_reach(q, d, first, qa, da, config=config)
            if config.outer_border_reach
            else np.full(n_steps, np.nan)
        )
    left_end, right_end = ends[0], -ends[1]
    width_raw = left_end - right_end
    width = _fill(_causal_weighted_mean(width_raw, _WIDTH_SMOOTHING_STEPS, _WIDTH_DECAY), _DEFAULT_WIDTH_M)
    width = np.clip(width, _MIN_WIDTH_M, config.max_width_m)
    mid_raw = np.where(
        np.isfinite(width_raw),
        0.5 * (left_end + right_end),
        np.where(np.isfinite(left_end), left_end - 0.5 * width, right_end + 0.5 * width),
    )
    mid = _fill(_causal_weighted_mean(mid_raw, _MIDPOINT_SMOOTHING_STEPS, 1.0), 0.0)
    return mid, width, reach[1], reach[0]


def sample_pivot(
    index: DetectionIndex,
    pivot: Drive,
    *,
    config: SamplingConfig,
    skip: np.ndarray | None = None,
    shift: ShiftFn | None = None,
    cache: dict | None = None,
) -> PivotSamples:
    """Sample all steps of one pivot drive (Sec. IV-A), vectorised over steps.

    Args:
        index: the detection index (Sec. III).
        pivot: the pivot drive.
        config: sampling options.
        skip: optional (Q,) bool; True steps are not sampled (already processed). Q is the number
            of steps of ``pivot_walk(pivot, step_m=config.step_m)``.
        shift: optional ``f(drive_index (H,), drive_s_m (H,)) -> (H,)`` lateral correction [m]
            added to each sample before refinement (the global offset model of the adjustment pass).
        cache: optional dict, filled and reused across calls: the same-direction intersections
            of each pivot's steps (by drive id), so a second pass does not intersect again.

    Returns:
        The refined samples of every step.
    """
    s, pts, heading = pivot_walk(pivot, step_m=config.step_m)
    n = len(s)
    skip = np.zeros(n, dtype=bool) if skip is None else np.asarray(skip, dtype=bool)
    if skip.shape != (n,):
        raise ConfigError(f"skip mask has shape {skip.shape}, want ({n},)")
    normal = left_normal(heading).reshape(n, 2)
    done = np.zeros(n, dtype=bool)
    parts: list[tuple[np.ndarray, ...]] = []
    if cache is not None and pivot.drive_id in cache:
        done, old = cache[pivot.drive_id]
        parts.append(old)
    active = np.flatnonzero(~skip & ~done)
    if len(active):
        hits = index.intersect(pts[active], normal[active], np.full(len(active), config.initial_half_length_m))
        qn = active[hits.cut]
        same_dir = np.abs(wrap_angle(hits.drive_yaw - heading[qn])) <= np.deg2rad(config.max_heading_diff_deg)
        parts.append(
            (qn[same_dir], hits.t_m[same_dir], hits.types[same_dir], hits.drive[same_dir], hits.drive_s_m[same_dir])
        )
    if len(parts) > 1:
        merged = tuple(np.concatenate(v) for v in zip(*parts))
    elif parts:
        merged = parts[0]
    else:
        merged = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int8), np.zeros(0, np.int32), np.zeros(0))
    if cache is not None:
        now_done = done.copy()
        now_done[active] = True
        cache[pivot.drive_id] = (now_done, merged)
    sel = ~skip[merged[0]]
    q, t, types, drv, ds = (v[sel] for v in merged)
    if shift is not None and len(t):
        t = t + np.asarray(shift(drv, ds), dtype=float)
    mid, width, lo, hi = _refine(q, t, types, n, config=config, drive=drv)
    # the pivot's own position in the frame of its (shifted) samples: its offset along the cut
    own = np.zeros(n)
    if shift is not None and n and pivot.drive_id in index.drive_ids:
        k = index.drive_ids.index(pivot.drive_id)
        own = np.asarray(shift(np.full(n, k, dtype=np.int64), s), dtype=float)
    pose = pts + own[:, None] * normal
    lat = t - mid[q]
    keep = np.abs(lat) <= 0.5 * width[q]
    if config.outer_border_reach:
        # beyond the cut up to a far border one drive saw (NaN: no reach, the comparison is False)
        keep |= ((lat > 0) & (t <= hi[q])) | ((lat < 0) & (t >= lo[q]))
    q, lat, types, drv, ds = q[keep], lat[keep], types[keep], drv[keep], ds[keep]
    order = np.lexsort((lat, q))
    q, lat, types, drv, ds = q[order], lat[order], types[order], drv[order], ds[order]
    ptr = np.searchsorted(q, np.arange(n + 1))
    return PivotSamples(
        s_m=s,
        point=pts,
        heading=heading,
        midpoint=pts + mid[:, None] * normal,
        width_m=width,
        skipped=skip,
        ptr=ptr,
        lateral_m=lat,
        types=types,
        drive=drv,
        drive_s_m=ds,
        off_cut=np.abs(mid - own) > 0.5 * width + config.max_pivot_outside_m,
        pose=pose,
    )


# Independent pivot groups (for running the pivot passes on several cores). A pivot changes the
# state later pivots see only through the drives that have samples on its cut lines (their
# processed-stretch marks and remembered offsets). Two drives can only ever meet that way where one
# of them, as pivot, has a cut line that crosses a detection segment of the other going the same
# way. The pivots of different groups never share a drive, so the groups can run apart, each in
# the global pivot order (a highway's two carriageways are two groups).
_HEADING_BINS = 12  # 30 deg each
_OFF = 1 << 20  # cell index offset: keys stay non-negative for maps within +-2^20 cells
_SPAN = 1 << 22


def pivot_groups(index: DetectionIndex, drives: Sequence[Drive], *, config: SamplingConfig) -> np.ndarray:
    """(N,) group label per drive (0..G-1): drives in different groups never meet on a cut line.

    Drive j's detection segment can be sampled on pivot i's cut at step point p only if the
    crossing lies within ``initial_half_length_m`` of p and j's heading there (``seg_yaw``) is
    within ``max_heading_diff_deg`` of the pivot's step heading. So the segment's midpoint lies
    within R = half length + half the longest segment of p. Place is binned in square cells of
    side > R (a point within R of p is in p's cell or one of its 8 neighbours) and heading in 30
    degree bins (two headings within D degrees are at most ceil(D / 30) bins apart): a drive is
    linked to every drive with a segment in a neighbouring (cell, heading bin) of one of its
    steps. The test can only unite too much, never too little.
    """
    n = len(drives)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    seg_len = np.hypot(*(index.seg_b - index.seg_a).T) if index.n_segments else np.zeros(1)
    reach = config.initial_half_length_m + 0.5 * float(seg_len.max())
    cell = reach * (1.0 + 1e-6) + 1e-6
    bin_w = 2.0 * math.pi / _HEADING_BINS
    d_bins = math.ceil(math.radians(config.max_heading_diff_deg) / bin_w + 1e-9)

    def place(xy: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        c = np.floor(np.asarray(xy, dtype=float) / cell).astype(np.int64) + _OFF
        b = np.floor(np.mod(yaw, 2.0 * math.pi) / bin_w).astype(np.int64) % _HEADING_BINS
        return (c[:, 0] * _SPAN + c[:, 1]) * _HEADING_BINS + b

    # Where each drive's detections are: its distinct place keys (segments come drive by drive).
    seg_key = place(0.5 * (index.seg_a + index.seg_b), index.seg_yaw)
    seg_drive = index.seg_drive.astype(np.int64)
    if np.any(np.diff(seg_drive) < 0):
        by_drive = np.argsort(seg_drive, kind="stable")
        seg_key, seg_drive = seg_key[by_drive], seg_drive[by_drive]
    bounds = np.searchsorted(seg_drive, np.arange(n + 1), side="left")
    det_key: list[np.ndarray] = []
    det_drive: list[np.ndarray] = []
    for i in np.flatnonzero(np.diff(bounds)).tolist():
        k = np.unique(seg_key[bounds[i] : bounds[i + 1]])
        det_key.append(k)
        det_drive.append(np.full(len(k), i, dtype=np.int64))
    det_k = np.concatenate(det_key) if det_key else np.zeros(0, np.int64)
    det_d = np.concatenate(det_drive) if det_drive else np.zeros(0, np.int64)
    keys, det_node = np.unique(det_k, return_inverse=True)
    # Where each drive's cut lines may reach: its steps' keys grown by one cell and d_bins.
    shifts = sorted({s % _HEADING_BINS for s in range(-d_bins, d_bins + 1)})
    reach_node: list[np.ndarray] = []
    reach_drive: list[np.ndarray] = []
    for i, d in enumerate(drives):
        _, pts, heading = pivot_walk(d, step_m=config.step_m)
        k = np.unique(place(pts, heading))
        b, c = k % _HEADING_BINS, k // _HEADING_BINS
        grown = np.concatenate(
            [
                (c + dx * _SPAN + dy) * _HEADING_BINS + (b + db) % _HEADING_BINS
                for dx in (-1, 0, 1)
                for dy in (-1, 0, 1)
                for db in shifts
            ]
        )
        pos = np.minimum(np.searchsorted(keys, grown), max(len(keys) - 1, 0))
        hit = keys[pos] == grown if len(keys) else np.zeros(len(grown), dtype=bool)
        reach_node.append(pos[hit])
        reach_drive.append(np.full(int(hit.sum()), i, dtype=np.int64))
    # Bipartite graph drives -- place keys; its components are the groups.
    rows = np.concatenate([det_d, *reach_drive])
    cols = n + np.concatenate([det_node, *reach_node])
    m = len(keys)
    g = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n + m, n + m))
    _, label = connected_components(g, directed=False)
    _, group = np.unique(label[:n], return_inverse=True)
    return group.astype(np.int64)
