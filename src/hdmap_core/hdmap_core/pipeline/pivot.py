"""Stages 2-4 along one pivot drive, and one pass over the pivots in order (Sec. IV).

A pivot is sampled at every step at once (``sampling.sample_pivot``), the EM runs step by step
(offsets carried along the pivot), and the accepted steps are aggregated at once. What all pivots
of a pass share (the detection index, the stage settings, the offset model of a final pass, the
counters and observations collected) is one :class:`PivotContext`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from hdmap_core.geometry import arc_length, wrap_angle
from hdmap_core.model import Drive
from hdmap_core.pipeline.aggregation import AggregationConfig, ManyAggregates, ProcessedStore, aggregate_many
from hdmap_core.pipeline.alignment import AlignmentConfig, StepAlignment, align_step, align_steps_gap, gap_batchable
from hdmap_core.pipeline.evidence import PROFILE_HALF_LENGTH_M, SEEN_WINDOW_M, EvidenceConfig, step_profiles
from hdmap_core.pipeline.preprocess import DetectionIndex
from hdmap_core.pipeline.sampling import PivotSamples, SamplingConfig, pivot_walk, sample_pivot
from hdmap_core.steps import Segment, StepObservations, StepResult, left_normal

__all__ = ["DriveTracks", "PassCounters", "PivotContext", "ProgressFn", "ShiftFn", "run_pass", "run_pivot"]

ProgressFn = Callable[[str, int, int], None]
#: ``shift(drive_index (N,), drive_s_m (N,)) -> (N,)`` lateral offsets to add to the drives' samples [m].
ShiftFn = Callable[[np.ndarray, np.ndarray], np.ndarray]

_EMPTY_F = np.zeros(0)
_EMPTY_I = np.zeros(0, dtype=np.int64)
# Tracked offsets are re-checked for lane-periodic lock-in every this many steps (50 m).
_RECHECK_EVERY_STEPS = 25
# A drive without an offset carried along the pivot starts from its offset through an earlier
# pivot within this distance along itself [m].
_MEMORY_REACH_M = 50.0
# Processed stretches: each mark is padded by half a step and marks closer than 3 steps merge.
_MARK_MERGE_STEPS = 3.0
# Step status along a pivot.
_REJECTED, _SKIPPED, _ACCEPTED = 0, 1, 2


@dataclass
class PassCounters:
    """Steps of one pass: all, rejected, skipped as processed before, accepted, off their road."""

    total: int = 0
    rejected: int = 0
    skipped: int = 0
    valid: int = 0
    off_road: int = 0

    def add(self, other: PassCounters) -> None:
        """Add ``other``'s counts to these."""
        self.total += other.total
        self.rejected += other.rejected
        self.skipped += other.skipped
        self.valid += other.valid
        self.off_road += other.off_road


def _runs(keys: np.ndarray) -> list[np.ndarray]:
    """The indices of ``keys`` grouped by key (ascending), each group in its original order."""
    order = np.argsort(keys, kind="stable")
    return np.split(order, np.flatnonzero(np.diff(keys[order])) + 1) if len(order) else []


class _OffsetMemory:
    """Offsets of drives from accepted steps of earlier pivots, by the drive's own distance.

    A drive entering a step without an offset carried along the current pivot starts from the
    offset it had nearby (within ``reach_m``) through an earlier pivot, instead of being
    registered from scratch (which can lock a drive that sees only dashed lines onto the
    neighbouring lane).
    """

    def __init__(self, n_drives: int, *, reach_m: float = _MEMORY_REACH_M) -> None:
        self.reach_m = reach_m
        self._s: list[list[np.ndarray]] = [[] for _ in range(n_drives)]
        self._o: list[list[np.ndarray]] = [[] for _ in range(n_drives)]
        self._sorted: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def add(self, drive: np.ndarray, s_m: np.ndarray, offset_m: np.ndarray) -> None:
        # grouped by one stable sort, not a mask per drive (quadratic in the drives of a pass)
        for part in _runs(drive):
            d = int(drive[part[0]])
            self._s[d].append(s_m[part])
            self._o[d].append(offset_m[part])
            self._sorted.pop(d, None)

    def lookup(self, uniq: np.ndarray, sample_s: np.ndarray, local: np.ndarray, want: np.ndarray) -> np.ndarray:
        """Offsets of the step's drives ``uniq`` (K,) through earlier pivots (NaN: none within
        reach), where ``want`` (K,) (elsewhere NaN); ``sample_s``, ``local``: the step's samples'
        travelled distances and drive codes 0..K-1."""
        out = np.full(len(uniq), np.nan)
        todo = [k for k in np.flatnonzero(want).tolist() if self._s[int(uniq[k])]]
        if not todo:
            return out
        # each drive's samples as a run of one stable sort (a mask per drive was quadratic in
        # the drives of a step): the same values in the same order, so the same means
        order = np.argsort(local, kind="stable")
        s_by = sample_s[order]
        ptr = np.searchsorted(local[order], np.arange(len(uniq) + 1))
        for k in todo:
            d = int(uniq[k])
            if d not in self._sorted:
                s_all = np.concatenate(self._s[d])
                o_all = np.concatenate(self._o[d])
                srt = np.argsort(s_all)
                self._sorted[d] = (s_all[srt], o_all[srt])
            s_all, o_all = self._sorted[d]
            s = float(s_by[ptr[k] : ptr[k + 1]].mean())
            i = int(np.clip(np.searchsorted(s_all, s), 1, len(s_all) - 1)) if len(s_all) > 1 else 0
            j = i - 1 if i > 0 and abs(s_all[i - 1] - s) < abs(s_all[i] - s) else i
            if abs(s_all[j] - s) <= self.reach_m:
                out[k] = o_all[j]
        return out


class DriveTracks:
    """The recorded trajectories of all drives, flat, for positions at travelled distances."""

    def __init__(self, drives: Sequence[Drive]) -> None:
        s_parts, xy_parts = [], []
        self.length_m = np.zeros(len(drives))
        for k, d in enumerate(drives):
            xy = np.asarray(d.xy, dtype=float)
            s = arc_length(xy)
            s_parts.append(s)
            xy_parts.append(xy)
            self.length_m[k] = s[-1] if len(s) else 0.0
        self.start = np.concatenate([[0], np.cumsum([len(v) for v in s_parts])]).astype(np.int64)
        self.s = np.concatenate(s_parts) if s_parts else np.zeros(0)
        self.xy = np.concatenate(xy_parts) if xy_parts else np.zeros((0, 2))
        # Each drive's (sorted) distances offset by its index, so one search serves all drives.
        self._big = float(self.length_m.max()) + 1.0 if len(drives) else 1.0
        self._key = self.s + self._big * np.repeat(np.arange(len(drives)), np.diff(self.start))

    def position(self, drive: np.ndarray, s_m: np.ndarray) -> np.ndarray:
        """(N, 2) positions of drives ``drive`` (N,) at their travelled distances ``s_m`` (N,) [m]
        (linear interpolation, clamped to the trajectory)."""
        drive = np.asarray(drive, dtype=np.int64)
        s = np.clip(np.asarray(s_m, dtype=float), 0.0, self.length_m[drive])
        lo, hi = self.start[drive], self.start[drive + 1]
        out = np.empty((len(drive), 2))
        single = hi - lo < 2
        out[single] = self.xy[lo[single]]
        m = ~single
        if m.any():
            j = np.searchsorted(self._key, s[m] + self._big * drive[m], side="right")
            j = np.clip(j, lo[m] + 1, hi[m] - 1)
            s0, s1 = self.s[j - 1], self.s[j]
            w = np.where(s1 > s0, (s[m] - s0) / np.where(s1 > s0, s1 - s0, 1.0), 0.0)[:, None]
            out[m] = (1.0 - w) * self.xy[j - 1] + w * self.xy[j]
        return out


@dataclass
class PivotContext:
    """What every pivot of one pass shares.

    Attributes:
        index: the preprocessed detections of all drives.
        sampling, alignment, aggregation: this pass's stage settings.
        shift: the final pass's offset model as a function (None: raw samples).
        observations: filled with one ``StepObservations`` per accepted step (None: not kept).
        counters: filled with the pass's step counts.
        hit_cache: same-direction cut intersections per pivot, shared by the two passes.
        tracks: with ``mark_on_cut_only``, the drives' trajectories (only drives on a step's cut
            are marked processed there).
        mark_outside_m: with ``tracks``, a drive this far beyond a step's cut still counts as on it.
        stride: the EM runs at steps whose index is a multiple of it (the others count as rejected).
        evidence: (trajectory index, settings) of the negative-evidence profiles, or None.
    """

    index: DetectionIndex
    sampling: SamplingConfig
    alignment: AlignmentConfig
    aggregation: AggregationConfig
    shift: ShiftFn | None = None
    observations: list[StepObservations] | None = None
    counters: PassCounters = field(default_factory=PassCounters)
    hit_cache: dict | None = None
    tracks: DriveTracks | None = None
    mark_outside_m: float = 0.0
    stride: int = 1
    evidence: tuple[DetectionIndex, EvidenceConfig] | None = None
    memory: _OffsetMemory | None = None


@dataclass
class _Accepted:
    """The samples of a pivot's accepted steps, offsets applied, in step order.

    Attributes (all (M,)): lateral_m, step, label (unique along the pivot, -1 dropped), types,
    drive, drive_s_m. ``step_ids``: per step, the ids of the drives sampled there.
    """

    lateral_m: np.ndarray
    step: np.ndarray
    label: np.ndarray
    types: np.ndarray
    drive: np.ndarray
    drive_s_m: np.ndarray
    step_ids: list[tuple[str, ...]]


def run_pivot(pivot: Drive, skip: np.ndarray, ctx: PivotContext) -> tuple[Segment, np.ndarray, np.ndarray]:
    """Stages 2-4 along one pivot.

    Args:
        pivot: the pivot drive.
        skip: (Q,) steps already processed through another pivot.
        ctx: the pass's shared settings and collectors (counters, observations are added to).

    Returns:
        (segment, (K,) drive indices to mark processed, (K,) their travelled distances [m]).
    """
    ps = sample_pivot(ctx.index, pivot, config=ctx.sampling, skip=skip, shift=ctx.shift, cache=ctx.hit_cache)
    status = np.zeros(ps.n_steps, dtype=np.int8)
    status[ps.skipped] = _SKIPPED
    acc = _align_steps(ps, _em_steps(ps, ctx.stride), pivot.drive_id, status, ctx)
    agg = aggregate_many(acc.lateral_m, acc.step, acc.label, acc.types, acc.drive, config=ctx.aggregation)
    ptr = np.searchsorted(agg.step, np.arange(ps.n_steps + 1))
    status[(status == _ACCEPTED) & ~(np.diff(ptr) > 0)] = _REJECTED
    steps = _step_results(ps, pivot.drive_id, status, acc.step_ids, agg, ptr, ctx)
    _count(ctx.counters, ps, status)
    md, ms = _processed_marks(ps, pivot.drive_id, status, acc, ctx)
    return Segment(pivot_id=pivot.drive_id, steps=tuple(steps)), md, ms


def _em_steps(ps: PivotSamples, stride: int) -> np.ndarray:
    """The steps the EM runs at: not skipped, on the pivot's road, on the stride."""
    todo = np.flatnonzero(~ps.skipped)
    if ps.off_cut is not None:
        todo = todo[~ps.off_cut[todo]]  # RULE: the pivot is not on the road its cut describes
    if stride > 1:
        todo = todo[todo % stride == 0]
    return todo


def _align_steps(ps: PivotSamples, todo: np.ndarray, pid: str, status: np.ndarray, ctx: PivotContext) -> _Accepted:
    """The EM at each step of ``todo`` (``status`` set to accepted where it passes)."""
    alignment = ctx.alignment
    n_all = len(ctx.index.drive_ids)
    ids = np.asarray(ctx.index.drive_ids, dtype=object)
    prev = np.full(n_all, np.nan)  # last accepted offset per drive along this pivot
    use_prior = alignment.prior_weight > 0 or alignment.clustering == "auto"
    step_ids: list[tuple[str, ...]] = [()] * ps.n_steps
    parts: list[tuple[np.ndarray, ...]] = []
    mem: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    base = 0
    # Without offset estimation the steps are independent: all of them clustered and scored at
    # once; the ones a special rule judges are left to align_step.
    batch = (
        align_steps_gap(ps.lateral_m, ps.types, ps.drive, ps.ptr, todo, config=alignment)
        if gap_batchable(alignment)
        else {}
    )
    # every step's distinct drives and local drive codes at once (a per-step np.unique each)
    owner = np.repeat(np.arange(ps.n_steps, dtype=np.int64), np.diff(ps.ptr))
    step_drive, sample_code = np.unique(owner * np.int64(n_all) + ps.drive, return_inverse=True)
    code_ptr = np.searchsorted(step_drive, np.arange(ps.n_steps + 1, dtype=np.int64) * n_all)
    step_drive %= n_all
    for q in todo:
        a, b = int(ps.ptr[q]), int(ps.ptr[q + 1])
        if b - a < 2:
            continue
        x, ty, dg = ps.lateral_m[a:b], ps.types[a:b], ps.drive[a:b]
        c0 = int(code_ptr[q])
        uniq, local = step_drive[c0 : int(code_ptr[q + 1])], sample_code[a:b] - c0
        al = batch.get(int(q))
        if al is None:
            prior = prev[uniq] if use_prior else None
            init = None
            if ctx.memory is not None and prior is not None and np.isnan(prior).any():
                init = ctx.memory.lookup(uniq, ps.drive_s_m[a:b], local, ~np.isfinite(prior))
            al = align_step(
                x,
                ty,
                local,
                config=alignment,
                prior=prior,
                init=init,
                recheck=bool(q % _RECHECK_EVERY_STEPS < ctx.stride),
            )
        step_ids[q] = tuple(ids[uniq])
        if not al.valid:
            continue
        status[q] = _ACCEPTED
        prev[uniq] = al.offsets_m
        lab = np.where(al.labels >= 0, al.labels + base, -1)
        base += int(al.labels.max()) + 1
        if ctx.memory is not None:
            cnt = np.bincount(local, minlength=len(uniq))
            s_mean = np.bincount(local, weights=ps.drive_s_m[a:b], minlength=len(uniq)) / np.maximum(cnt, 1)
            mem.append((uniq, s_mean, al.offsets_m))
        types = ty if al.types is None else al.types
        parts.append((x + al.offsets_m[local], np.full(b - a, q), lab, types, dg, ps.drive_s_m[a:b]))
        if ctx.observations is not None:
            ctx.observations.append(_observation(ps, int(q), pid, ids, a, b, al, local))
    if ctx.memory is not None and mem:
        ctx.memory.add(*(np.concatenate(v) for v in zip(*mem)))
    if not parts:
        return _Accepted(_EMPTY_F, _EMPTY_I, _EMPTY_I, _EMPTY_I, _EMPTY_I, _EMPTY_I, step_ids)
    xs, st, lb, ty, dv, ds = (np.concatenate(v) for v in zip(*parts))
    return _Accepted(xs, st, lb, ty, dv, ds, step_ids)


def _observation(
    ps: PivotSamples, q: int, pid: str, ids: np.ndarray, a: int, b: int, al: StepAlignment, local: np.ndarray
) -> StepObservations:
    """Step ``q``'s samples ``a:b`` with their clusters and offsets, for the adjustment."""
    x, ty = ps.lateral_m[a:b], ps.types[a:b]
    return StepObservations(
        pivot_id=pid,
        index=q,
        midpoint=ps.midpoint[q],
        heading=float(ps.heading[q]),
        drive_ids=tuple(ids[ps.drive[a:b]]),
        drive_s_m=ps.drive_s_m[a:b],
        lateral_m=x,
        types=ty,
        # a type clash kept as a line of unknown type is no cluster of these types
        cluster=al.labels if al.types is None else np.where(al.types == ty, al.labels, -1),
        offsets_m=al.offsets_m[local],
    )


def _step_results(
    ps: PivotSamples,
    pid: str,
    status: np.ndarray,
    step_ids: list[tuple[str, ...]],
    agg: ManyAggregates,
    ptr: np.ndarray,
    ctx: PivotContext,
) -> list[StepResult]:
    """One ``StepResult`` per step; a run of skipped (processed before) steps is represented by
    its first and last step only: they carry no data, and connection only needs to see where such
    a run starts and ends."""
    sk = status == _SKIPPED
    inner = sk.copy()
    inner[:-1] &= sk[1:]
    inner[1:] &= sk[:-1]
    if len(inner):
        inner[0] = inner[-1] = False
    empty: dict[int, np.ndarray] = {}
    if ctx.evidence is not None:
        cached = ctx.hit_cache.get(pid, (None, None))[1] if ctx.hit_cache is not None else None
        empty = _profiles(ctx, ps, np.flatnonzero(status != _SKIPPED), cached)
    steps: list[StepResult] = []
    for q in range(ps.n_steps):
        if inner[q]:
            continue
        if status[q] != _ACCEPTED:
            steps.append(
                _step(pid, q, ps, processed=bool(status[q] == _SKIPPED), drive_ids=step_ids[q], empty=empty.get(q))
            )
            continue
        a, b = ptr[q], ptr[q + 1]
        maxima = (agg.lateral_m[a:b], agg.types[a:b], agg.counts[a:b], agg.std_m[a:b])
        steps.append(_step(pid, q, ps, drive_ids=step_ids[q], maxima=maxima, empty=empty.get(q)))
    return steps


def _count(counters: PassCounters, ps: PivotSamples, status: np.ndarray) -> None:
    counters.total += ps.n_steps
    counters.skipped += int((status == _SKIPPED).sum())
    counters.valid += int((status == _ACCEPTED).sum())
    counters.rejected += int((status == _REJECTED).sum())
    if ps.off_cut is not None:
        counters.off_road += int((ps.off_cut & ~ps.skipped).sum())


def _processed_marks(
    ps: PivotSamples, pid: str, status: np.ndarray, acc: _Accepted, ctx: PivotContext
) -> tuple[np.ndarray, np.ndarray]:
    """Processed stretches: every drive that took part in an accepted step, keyed by its own
    travelled distance there (mean of its samples), plus the pivot itself. With ``ctx.tracks``
    (``mark_on_cut_only``) only drives that were themselves on the refined cut.

    Returns:
        ((K,) drive indices, (K,) travelled distances [m]).
    """
    n_all = len(ctx.index.drive_ids)
    st, lb, dv, ds = acc.step, acc.label, acc.drive, acc.drive_s_m
    ok = (lb >= 0) & (status[st] == _ACCEPTED) if len(lb) else np.zeros(0, bool)
    key = st[ok] * np.int64(n_all) + dv[ok]
    uk, inv = np.unique(key, return_inverse=True)
    s_mean = np.bincount(inv, weights=ds[ok], minlength=len(uk)) / np.maximum(np.bincount(inv, minlength=len(uk)), 1)
    if ctx.tracks is not None and len(uk):
        uq, ud = uk // n_all, uk % n_all
        pos = ctx.tracks.position(ud, s_mean)
        lat = ((pos - ps.midpoint[uq]) * left_normal(ps.heading[uq]).reshape(-1, 2)).sum(axis=1)
        if ctx.shift is not None:
            lat = lat + np.asarray(ctx.shift(ud, s_mean), dtype=float)
        on_cut = np.abs(lat) <= 0.5 * ps.width_m[uq] + ctx.mark_outside_m
        uk, s_mean = uk[on_cut], s_mean[on_cut]
    valid_q = np.flatnonzero(status == _ACCEPTED)
    pidx = ctx.index.drive_ids.index(pid)
    md = np.concatenate([uk % n_all, np.full(len(valid_q), pidx)]).astype(np.int64)
    ms = np.concatenate([s_mean, ps.s_m[valid_q]])
    return md, ms


def _step(
    pivot_id: str,
    q: int,
    ps: PivotSamples,
    *,
    drive_ids: tuple[str, ...] = (),
    processed: bool = False,
    maxima: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    empty: np.ndarray | None = None,
) -> StepResult:
    """Step ``q`` of a pivot: valid with ``maxima`` (lateral_m, types, counts, std_m), else a
    placeholder (rejected, or ``processed`` before) that carries only the step's geometry."""
    lateral_m, types, counts, std_m = maxima if maxima is not None else (_EMPTY_F, _EMPTY_I, _EMPTY_I, _EMPTY_F)
    return StepResult(
        pivot_id=pivot_id,
        index=q,
        s_m=float(ps.s_m[q]),
        midpoint=ps.midpoint[q],
        heading=float(ps.heading[q]),
        width_m=float(ps.width_m[q]),
        valid=maxima is not None,
        processed_before=processed,
        lateral_m=lateral_m,
        types=types,
        counts=counts,
        std_m=std_m,
        drive_ids=drive_ids,
        empty_m=empty,
        pose=(ps.point if ps.pose is None else ps.pose)[q],
    )


def _profiles(
    ctx: PivotContext, ps: PivotSamples, steps: np.ndarray, hits: tuple[np.ndarray, ...] | None
) -> dict[int, np.ndarray]:
    """Empty intervals (``hdmap_core.pipeline.evidence.step_profiles``) of the pivot's ``steps``, from
    the step's midpoint. ``hits``: the pivot's raw same-direction detection crossings (step, t,
    type, drive, drive s) when cached, else intersected here."""
    assert ctx.evidence is not None  # noqa: S101 - the caller checks
    tindex, cfg = ctx.evidence
    if len(steps) == 0:
        return {}
    normal = left_normal(ps.heading).reshape(-1, 2)
    max_diff = np.deg2rad(ctx.sampling.max_heading_diff_deg)

    def crossings(idx: DetectionIndex, half_m: float) -> tuple[np.ndarray, ...]:
        # same-direction crossings of the steps' cuts: (step, t, drive, drive s)
        c = idx.intersect(ps.point[steps], normal[steps], np.full(len(steps), half_m))
        ok = np.abs(wrap_angle(c.drive_yaw - ps.heading[steps[c.cut]])) <= max_diff
        return steps[c.cut[ok]], c.t_m[ok], c.drive[ok], c.drive_s_m[ok]

    cq, ct, cd, cs = crossings(tindex, PROFILE_HALF_LENGTH_M)
    if hits is None:
        hq, ht, hd, hs = crossings(ctx.index, PROFILE_HALF_LENGTH_M + SEEN_WINDOW_M)
    else:
        want = np.zeros(ps.n_steps, dtype=bool)
        want[steps] = True
        ok = want[hits[0]]
        hq, ht, hd, hs = hits[0][ok], hits[1][ok], hits[3][ok], hits[4][ok]
    if ctx.shift is not None:
        if len(ct):
            ct = ct + np.asarray(ctx.shift(cd.astype(np.int64), cs), dtype=float)
        if len(ht):
            ht = ht + np.asarray(ctx.shift(hd.astype(np.int64), hs), dtype=float)
    prof = step_profiles(ps.n_steps, cq, ct, cd, hq, ht, hd, config=cfg)
    mid = np.einsum("ij,ij->i", ps.midpoint - ps.point, normal)
    return {int(q): prof[q] - mid[q] if len(prof[q]) else prof[q] for q in steps.tolist()}


def run_pass(
    drives: Sequence[Drive],
    order: np.ndarray,
    processed: ProcessedStore,
    ctx: PivotContext,
    *,
    progress: ProgressFn | None = None,
) -> tuple[list[Segment], ProcessedStore]:
    """The pivots ``order`` (indices into ``drives``) one after the other; each pivot's accepted
    stretches are marked processed for the pivots after it.

    Returns:
        (one segment per pivot in ``order``, the store with the new marks; ``processed`` is not
        modified).
    """
    segments: list[Segment] = []
    step_m = ctx.sampling.step_m
    carried = ctx.alignment.clustering == "auto" and ctx.alignment.estimate_offsets
    ctx.memory = _OffsetMemory(len(drives)) if carried else None
    for n_done, di in enumerate(order):
        pivot = drives[int(di)]
        s, _, _ = pivot_walk(pivot, step_m=step_m)
        seg, md, ms = run_pivot(pivot, processed.contains(pivot.drive_id, s), ctx)
        segments.append(seg)
        if len(md):
            marks = {ctx.index.drive_ids[int(md[part[0]])]: ms[part] for part in _runs(md)}
            processed = processed.with_marks(marks, pad_m=0.5 * step_m, merge_gap_m=_MARK_MERGE_STEPS * step_m)
        if progress is not None:
            progress("pivots", n_done + 1, len(order))
    return segments, processed
