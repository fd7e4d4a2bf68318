"""The whole method (Immel et al. 2023): drives in, hierarchical map out.

``map_stretches`` runs stages 1-4 (preprocessing, lateral sampling, EM offset estimation,
aggregation) along random pivot drives (``hdmap_core.pipeline.pivot``), in one pass, or, with
``PipelineConfig.final_pass``, in two: a first pass collects per-step observations, one global
adjustment (``hdmap_core.pipeline.adjustment``) estimates every drive's offset curve, and the final
pass samples and aggregates with the samples shifted by it. ``build_map`` adds the connection
(Sec. V, ``hdmap_core.graph.connection``) and stitching (Sec. VI, ``hdmap_core.graph.map_graph``)
stages and a run report. Configurations: ``hdmap_core.pipeline.config`` (the defaults are the
recommended method), ``presets`` and ``overrides``.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, cast

import numpy as np

from hdmap_core.errors import ConfigError, NoUsableDataError
from hdmap_core.graph.connection import connect_segment
from hdmap_core.graph.map_graph import stitch
from hdmap_core.model import Drive, HDMap
from hdmap_core.parallel import ForkWorker, can_fork, map_balanced, one_blas_thread, split_order
from hdmap_core.pipeline.adjustment import OffsetModel, OffsetSource, adjust_offsets
from hdmap_core.pipeline.adjustment_dist import AdjustPart, adjust_parts
from hdmap_core.pipeline.aggregation import ProcessedStore
from hdmap_core.pipeline.config import PipelineConfig
from hdmap_core.pipeline.evidence import EvidenceConfig
from hdmap_core.pipeline.pivot import DriveTracks, PassCounters, PivotContext, ProgressFn, ShiftFn, run_pass
from hdmap_core.pipeline.preprocess import DetectionIndex, preprocess, trajectory_index
from hdmap_core.pipeline.sampling import pivot_groups
from hdmap_core.plausibility import prepare_drives
from hdmap_core.steps import Segment, StepObservations

__all__ = [
    "BuildReport",
    "BuildResult",
    "MappingResult",
    "build_map",
    "map_segments",
    "map_stretches",
    "prepare_drives",
    "StagedPasses",
]

# A pass's results: segments, the processed-stretch store, observations (or None), step counts.
_PassResult = tuple[list[Segment], ProcessedStore, list[StepObservations] | None, PassCounters]


class _Channel(Protocol):
    """The pipe between this process and a forked worker (``parallel.ForkWorker``)."""

    def send(self, obj: object) -> None: ...

    def recv(self) -> object: ...


@dataclass(frozen=True)
class BuildReport:
    """What a run did.

    Attributes:
        n_drives_in: drives given.
        n_drives_used: valid, distinct drives used.
        rejected: (drive_id, reason) per rejected drive.
        km_mapped: pivot distance of accepted steps [km].
        steps_total: sampling steps of all pivots (incl. skipped ones).
        steps_rejected: steps without a result (EM gate failed, no samples, or off the road).
        steps_off_road: of those, the steps whose pivot lay beyond its refined cut
            (``SamplingConfig.max_pivot_outside_m``): not aligned.
        steps_skipped_processed: steps skipped as already processed through another pivot.
        seconds: wall time of the whole run [s].
        stage_seconds: wall time per stage [s].
    """

    n_drives_in: int = 0
    n_drives_used: int = 0
    rejected: list[tuple[str, str]] = field(default_factory=list)
    km_mapped: float = 0.0
    steps_total: int = 0
    steps_rejected: int = 0
    steps_off_road: int = 0
    steps_skipped_processed: int = 0
    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        """A few readable lines."""
        lines = [
            f"drives: {self.n_drives_used} used of {self.n_drives_in} ({len(self.rejected)} rejected)",
            f"steps: {self.steps_total} total, {self.steps_rejected} rejected"
            + (f" ({self.steps_off_road} off their pivot's road)" if self.steps_off_road else "")
            + ", "
            f"{self.steps_skipped_processed} skipped (processed before); {self.km_mapped:.2f} km mapped",
            f"time: {self.seconds:.2f} s (" + ", ".join(f"{k} {v:.2f}" for k, v in self.stage_seconds.items()) + ")",
        ]
        for did, reason in self.rejected[:10]:
            lines.append(f"  rejected {did!r}: {reason}")
        if len(self.rejected) > 10:
            lines.append(f"  ... and {len(self.rejected) - 10} more rejected")
        return "\n".join(lines)


@dataclass(frozen=True)
class BuildResult:
    """Output of ``build_map``: the map, the per-pivot segments, the report and the drives the map
    was built from (the input drives ``prepare_drives`` kept, in their order, the same objects)."""

    map: HDMap
    segments: list[Segment]
    report: BuildReport
    drives: list[Drive]


@dataclass(frozen=True)
class MappingResult:
    """Output of ``map_stretches`` (stages 1-4).

    Attributes:
        segments: one per pivot drive, in pivot order. A run of steps skipped as processed
            before is represented by its first and last step (``processed_before=True``).
        processed: the processed-stretch store after the run (input store plus new stretches).
        observations: one per accepted step of the first (observation) pass; empty unless
            requested or used by the global adjustment in this process (with several workers and
            not requested, each worker keeps its share's for the adjustment: empty).
        offset_model: the global offset model (None without global adjustment).
        counters: steps_total, steps_rejected, steps_skipped_processed, steps_valid,
            steps_off_road.
        stage_seconds: wall time per stage [s].
    """

    segments: list[Segment]
    processed: ProcessedStore
    observations: list[StepObservations]
    offset_model: OffsetSource | None
    counters: dict[str, int]
    stage_seconds: dict[str, float]


# ----------------------------------------------------------------------------- input


def _check_workers(workers: int) -> int:
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}")
    return int(workers)


def _merge_parts(
    parts: list[_PassResult], order: np.ndarray, drives: list[Drive], store_in: ProcessedStore
) -> _PassResult:
    """One pass's results of independent pivot shares, as one process in ``order`` gives them.

    A share's pivots only mark drives of its own groups, so each drive's intervals come from the
    share that owns it (from the input store when no share has its pivots' groups: unchanged).
    """
    if len(parts) == 1:
        return parts[0]
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    pos = {d.drive_id: int(rank[i]) for i, d in enumerate(drives)}
    segments = sorted((seg for p in parts for seg in p[0]), key=lambda seg: pos[seg.pivot_id])
    obs = None
    if parts[0][2] is not None:
        obs = sorted((o for p in parts for o in p[2] or []), key=lambda o: pos[o.pivot_id])
    counters = PassCounters()
    for p in parts:
        counters.add(p[3])
    intervals = dict(store_in.intervals)
    for p in parts:
        for did, iv in p[1].intervals.items():
            if iv != store_in.intervals.get(did):
                intervals[did] = iv
    return segments, ProcessedStore(intervals), obs, counters


def _shift_fn(model: OffsetSource, drive_ids: tuple[str, ...]) -> ShiftFn:
    """The offset model as ``shift(drive index (N,), drive s (N,)) -> (N,)`` [m]."""
    # RULE linear in the drives per place: a model with a table is read for all drives at once
    # (``offset_table``), not one Python call per drive of every pivot's samples
    table = model.table(drive_ids)
    if table is not None:
        return cast(ShiftFn, table.offset)
    # else drive by drive: a source without a table (a live tile's clip of a clip, whose sums
    # would be in another order; a test's spy)

    def shift(drive_idx: np.ndarray, s_m: np.ndarray) -> np.ndarray:
        out = np.zeros(len(drive_idx))
        if len(drive_idx) == 0:
            return out
        order = np.argsort(drive_idx, kind="stable")
        di = drive_idx[order]
        cut = np.flatnonzero(np.diff(di)) + 1
        for part in np.split(order, cut):
            out[part] = model.offset(drive_ids[int(drive_idx[part[0]])], s_m[part])
        return out

    return shift


def map_stretches(
    drives: Sequence[Drive],
    *,
    config: PipelineConfig = PipelineConfig(),
    seed: int = 0,
    processed: ProcessedStore | None = None,
    collect_observations: bool = False,
    progress: ProgressFn | None = None,
    validated: bool = False,
    offset_model: OffsetSource | None = None,
    observations_only: bool = False,
    workers: int = 1,
) -> MappingResult:
    """Stages 1-4 on valid drives, with the processed-stretch store in and out.

    Args:
        drives: drives (invalid ones are skipped silently here; use ``build_map`` for a report,
            or pass ``validated=True`` when they were checked already).
        config: pipeline options.
        seed: seeds the random pivot order.
        processed: stretches processed earlier (skipped as pivots' steps); not modified.
        collect_observations: also return the per-step observations of the (first) pass.
        progress: optional callback(stage, done, total).
        offset_model: a fleet-wide ``adjustment.OffsetModel`` estimated elsewhere (e.g. from the
            observations of every tile of a live map): only the final pass runs, with the drives
            shifted by it (``config.final_pass``); no first pass, no adjustment here.
        observations_only: the caller uses only the observations (e.g. a live tile's
            observation pass feeding a fleet-wide adjustment): the EM runs at
            ``config.observation_stride`` as in the first pass of an adjusted build, and the
            segments are those of that pass.
        workers: processes for the pivot passes (this one plus forked children, on systems with
            ``fork``). Only independent pivot groups (``sampling.pivot_groups``, e.g. the two
            carriageways of a highway) run apart, so the result is the one-process result. Do not
            fork from a process with native threads of its own (a ROS node): keep 1 there.

    Returns:
        The segments, the updated store, observations and counters.

    Raises:
        NoUsableDataError: no valid drive.
        ConfigError: ``offset_model`` with a config without a final pass, or bad ``workers``.
    """
    if not validated:
        drives, _ = prepare_drives(drives, bounds=config.plausibility)
    drives = list(drives)
    if not drives:
        raise NoUsableDataError("no valid drive to map")
    if offset_model is not None and config.final_pass is None:
        raise ConfigError("map_stretches: an offset_model needs a config with a final pass (final_pass is None)")
    with one_blas_thread():
        return _TwoPasses(
            drives,
            config,
            seed=seed,
            processed=processed,
            collect_observations=collect_observations,
            observations_only=observations_only,
            workers=_check_workers(workers),
        ).run(offset_model, progress)


class StagedPasses:
    """The two passes of one ``map_stretches`` call run apart: the first (observation) pass now,
    the final pass later with an offset model estimated elsewhere.

    What a live tile needs (``hdmap_core.live.tiles.TileWork``): its observation pass feeds a
    fleet-wide adjustment over every tile, and its final pass runs with that model once it is
    there. Kept in one object, the preprocessing and the pivots' cut intersections are made once
    for both passes, as ``build_map`` makes them once for its two passes (``_TwoPasses``).

    :meth:`first` gives what ``map_stretches(..., collect_observations=True,
    observations_only=True)`` gives; :meth:`final` what ``map_stretches(..., offset_model=model)``
    gives on the same drives: the same segments whatever ran before (the cut intersections of a
    step do not depend on the pass).

    Args:
        drives: valid drives (``prepare_drives``); config: with a final pass; seed, processed:
            as ``map_stretches``.

    Raises:
        NoUsableDataError: no drive; ConfigError: a config without a final pass.
    """

    def __init__(
        self,
        drives: Sequence[Drive],
        *,
        config: PipelineConfig,
        seed: int = 0,
        processed: ProcessedStore | None = None,
    ) -> None:
        drives = list(drives)
        if not drives:
            raise NoUsableDataError("no valid drive to map")
        if config.final_pass is None:
            raise ConfigError("StagedPasses needs a config with a final pass (final_pass is None)")
        with one_blas_thread():
            self._passes = _TwoPasses(
                drives,
                config,
                seed=seed,
                processed=processed,
                collect_observations=True,
                observations_only=True,
                workers=1,
            )

    def first(self) -> MappingResult:
        """The observation pass: its segments and its step observations (no adjustment)."""
        p = self._passes
        with one_blas_thread():
            t0 = time.perf_counter()
            segments, store, obs, counters = p._all([], None, None, None)
            p.seconds["sampling_em"] = time.perf_counter() - t0
        return p.result(segments, store, obs, None, counters)

    def final(self, model: OffsetSource) -> MappingResult:
        """The final pass with ``model`` (travelled distances of these drives)."""
        p = self._passes
        with one_blas_thread():
            p.with_evidence()
            t0 = time.perf_counter()
            segments, store, _, counters = p._all([], model, None, None)
            p.seconds["final_pass"] = time.perf_counter() - t0
        return p.result(segments, store, None, model, counters)


class _LatestOnly(dict):
    """A dict that holds only the entry set last."""

    def __setitem__(self, key: Any, value: Any) -> None:
        self.clear()
        super().__setitem__(key, value)


class _TwoPasses:
    """The passes of one ``map_stretches`` call over shares of pivots, in this process and in
    forked workers (each share's first pass, the adjustment here, each share's final pass)."""

    def __init__(
        self,
        drives: list[Drive],
        config: PipelineConfig,
        *,
        seed: int,
        processed: ProcessedStore | None,
        collect_observations: bool,
        observations_only: bool,
        workers: int,
    ) -> None:
        self.drives = drives
        self.config = config
        self.store_in = processed if processed is not None else ProcessedStore()
        self.seconds: dict[str, float] = {}
        t0 = time.perf_counter()
        self.index = preprocess(drives, config=config.preprocess, workers=workers)
        self.seconds["preprocess"] = time.perf_counter() - t0
        self.order = np.random.default_rng(seed).permutation(len(drives))
        two = config.final_pass is not None
        self.keep_observations = collect_observations or two
        # with several workers the adjustment runs over the shares' observations where they are
        # made (adjustment_dist), unless the caller wants them all here
        self.observations_stay = two and not collect_observations and not observations_only
        self.hit_cache: dict | None = {} if two else None
        self.tracks = DriveTracks(drives) if config.mark_on_cut_only else None
        self.observations_only = observations_only
        self.first_stride = config.observation_stride if (two or observations_only) else 1
        self.evidence: tuple[DetectionIndex, EvidenceConfig] | None = None
        if not observations_only:
            self.with_evidence()
        self.shares = [self.order]
        if workers > 1 and len(drives) > 1 and can_fork():
            t0 = time.perf_counter()
            group = pivot_groups(self.index, drives, config=config.sampling)
            self.shares = split_order(self.order, group, np.array([d.length_m for d in drives]), workers)
            self.seconds["grouping"] = time.perf_counter() - t0

    def with_evidence(self) -> None:
        """Make the negative-evidence index (``config.evidence``) if it is not there yet."""
        if self.config.evidence is not None and self.evidence is None:
            t0 = time.perf_counter()
            self.evidence = (
                trajectory_index(self.drives, cell_m=self.config.preprocess.grid_cell_m),
                self.config.evidence,
            )
            self.seconds["preprocess"] += time.perf_counter() - t0

    def _context(self, final: OffsetSource | None, counters: PassCounters, observations: list | None) -> PivotContext:
        """The pivots' shared settings of the first pass, or of the final pass shifted by ``final``."""
        cfg = self.config
        if final is None:
            # the first pass's segments are returned (and get the profiles) only without a final pass
            ends = cfg.final_pass is None or self.observations_only
            # RULE an observation pass (it only feeds the adjustment) counts a drive within the
            # pivot's own tolerance beyond a cut (``max_pivot_outside_m``, a GNSS error) as on it:
            # else each badly localised drive between two roads (a gore, the median) becomes a
            # pivot there, and its steps sample every drive of the place again: that work grows
            # with the square of the drives per place
            feeds_adjustment = cfg.final_pass is not None or self.observations_only
            return PivotContext(
                index=self.index,
                sampling=cfg.sampling,
                alignment=cfg.alignment,
                aggregation=cfg.aggregation,
                observations=observations,
                counters=counters,
                hit_cache=self.hit_cache,
                tracks=self.tracks,
                mark_outside_m=cfg.sampling.max_pivot_outside_m if feeds_adjustment else 0.0,
                stride=self.first_stride,
                evidence=self.evidence if ends else None,
            )
        return PivotContext(
            index=self.index,
            sampling=cfg.final_sampling,
            alignment=cfg.final_alignment,
            aggregation=cfg.aggregation,
            shift=_shift_fn(final, self.index.drive_ids),
            counters=counters,
            hit_cache=self.hit_cache,
            tracks=self.tracks,
            evidence=self.evidence,
        )

    def _ranks(self, observations: Sequence[StepObservations]) -> np.ndarray:
        """The place of each observation's pivot in the pivot order."""
        rank = np.empty(len(self.order), dtype=np.int64)
        rank[self.order] = np.arange(len(self.order))
        index = {d.drive_id: i for i, d in enumerate(self.drives)}
        return rank[np.array([index[o.pivot_id] for o in observations], dtype=np.int64)]

    def _adjust(self, obs: list[StepObservations], workers: list[ForkWorker]) -> OffsetModel:
        """The adjustment: the one solve over ``obs`` (this process's shares' observations) and
        the observations the workers kept (``_job``), as parts of ``adjustment_dist`` (parts of
        different pivot groups share no drive: the one solve's offsets to the last bit). A worker
        lost on the way: the shares of the workers that held parts are run here again (their
        first pass) and the one solve runs here."""
        cfg = self.config.adjustment
        live = [w for w in workers if not w.failed] if self.observations_stay else []
        ranks = [self._ranks(obs)] + [w.result() for w in live]
        if live and not any(w.failed for w in live):
            numbers = np.empty(sum(r.size for r in ranks), dtype=np.int64)
            numbers[np.argsort(np.concatenate(ranks), kind="stable")] = np.arange(numbers.size)
            steps = np.split(numbers, np.cumsum([r.size for r in ranks])[:-1])
            try:
                return adjust_parts(_fork_call(AdjustPart(obs), live), 1 + len(live), cfg, steps=steps)
            except _WorkerLost:
                pass
        for w, share in zip(workers, self.shares[1:]):
            if any(w is x for x in live):  # (a worker lost before holds no part: its share ran here)
                obs = obs + (self._pass(share, None, None)[2] or [])
        rank = self._ranks(obs)
        return adjust_offsets([obs[i] for i in np.argsort(rank, kind="stable")], config=cfg)

    def _pass(self, share: np.ndarray, model: OffsetSource | None, report: ProgressFn | None) -> _PassResult:
        counters = PassCounters()
        obs: list[StepObservations] | None = [] if (model is None and self.keep_observations) else None
        ctx = self._context(model, counters, obs)
        segs, store = run_pass(self.drives, share, self.store_in, ctx, progress=report)
        return segs, store, obs, counters

    def run(self, offset_model: OffsetSource | None, progress: ProgressFn | None) -> MappingResult:
        model = offset_model
        adjust = model is None and self.config.final_pass is not None
        if model is not None and self.hit_cache is not None:
            # RULE bounded memory: the hit cache saves the final pass the first pass's
            # intersections. With the model given only the final pass runs: a pivot's entry is
            # read back only by that pivot's own profiles, so keeping the latest one gives the
            # same result without holding every hit of every pivot (a tiled build's final pass).
            self.hit_cache = _LatestOnly()
        workers = [
            ForkWorker(functools.partial(self._job, share=sh, model=model, adjust=adjust)) for sh in self.shares[1:]
        ]
        report: ProgressFn | None = None
        if progress is not None:
            total, outer = len(self.order), progress

            def report(stage: str, done: int, _n: int) -> None:
                outer(stage, done, total)  # the whole order's count, not the share's

        try:
            obs: list[StepObservations] | None = None
            if model is None:
                t0 = time.perf_counter()
                segments, store, obs, counters = self._all(workers, None, report, progress)
                self.seconds["sampling_em"] = time.perf_counter() - t0
            if adjust:
                t0 = time.perf_counter()
                model = self._adjust(obs or [], workers)
                self.seconds["adjustment"] = time.perf_counter() - t0
                if self.observations_stay and workers:
                    obs = None  # the workers' stayed with them
                for w in workers:
                    w.send(model)
            if model is not None:
                t0 = time.perf_counter()
                segments, store, _, counters = self._all(workers, model, report, progress)
                self.seconds["final_pass"] = time.perf_counter() - t0
        finally:
            for w in workers:
                w.close()
        return self.result(segments, store, obs, model, counters)

    def result(
        self,
        segments: list[Segment],
        store: ProcessedStore,
        obs: list[StepObservations] | None,
        model: OffsetSource | None,
        counters: PassCounters,
    ) -> MappingResult:
        return MappingResult(
            segments=segments,
            processed=store,
            observations=obs if obs is not None else [],
            offset_model=model,
            counters={
                "steps_total": counters.total,
                "steps_rejected": counters.rejected,
                "steps_skipped_processed": counters.skipped,
                "steps_valid": counters.valid,
                "steps_off_road": counters.off_road,
            },
            stage_seconds=dict(self.seconds),
        )

    def _job(self, channel: _Channel, share: np.ndarray, model: OffsetSource | None, adjust: bool) -> None:
        """In a worker process: the same passes on its share, results sent back."""
        if model is None:
            segs, st, o, c = self._pass(share, None, None)
            stay = adjust and self.observations_stay
            channel.send((segs if not adjust else [], st, None if stay else o, c))
            if not adjust:
                return
            if stay:
                channel.send(self._ranks(o or []))
                model = _serve(channel, AdjustPart(o or []))
            else:
                model = cast(OffsetModel, channel.recv())
        channel.send(self._pass(share, model, None))

    def _all(
        self,
        workers: list[ForkWorker],
        model: OffsetSource | None,
        report: ProgressFn | None,
        progress: ProgressFn | None,
    ) -> _PassResult:
        """One pass over every share: this process's here, the others' from their workers (or
        here, if one failed)."""
        parts = [self._pass(self.shares[0], model, report)]
        for w, sh in zip(workers, self.shares[1:]):
            got = w.result()
            parts.append(self._pass(sh, model, None) if w.failed else got)
        if progress is not None and len(self.shares) > 1:
            progress("pivots", len(self.order), len(self.order))
        return _merge_parts(parts, self.order, self.drives, self.store_in)


class _WorkerLost(Exception):
    """A worker holding a part of the adjustment failed."""


def _fork_call(here: AdjustPart, workers: list[ForkWorker]) -> Callable[[str, Sequence[tuple]], list]:
    """``adjustment_dist``'s ``call`` over ``here`` (the first part) and the parts the ``workers``
    hold (``_serve``): the workers' calls sent first, so that they run while this one does."""

    def call(method: str, args: Sequence[tuple]) -> list:
        for w, a in zip(workers, args[1:]):
            w.send(("call", method, a))
        out = [getattr(here, method)(*args[0])]
        for w in workers:
            got = w.result()
            if w.failed:
                raise _WorkerLost(method)
            out.append(got)
        return out

    return call


def _serve(channel: _Channel, part: AdjustPart) -> OffsetModel:
    """In a worker: answer the adjustment's calls on its part until the offset model comes."""
    while True:
        msg = channel.recv()
        if not (isinstance(msg, tuple) and msg[:1] == ("call",)):
            return cast(OffsetModel, msg)
        _, method, args = msg
        channel.send(getattr(part, method)(*args))


def map_segments(
    drives: Sequence[Drive],
    *,
    config: PipelineConfig = PipelineConfig(),
    seed: int = 0,
    processed: ProcessedStore | None = None,
) -> list[Segment]:
    """Stages 1-4 only: one ``Segment`` per pivot drive (see ``map_stretches`` for the store)."""
    return map_stretches(drives, config=config, seed=seed, processed=processed).segments


def build_map(
    drives: Sequence[Drive],
    *,
    config: PipelineConfig = PipelineConfig(),
    seed: int = 0,
    progress: ProgressFn | None = None,
    workers: int = 1,
) -> BuildResult:
    """Build the hierarchical map from fleet drives (the whole method).

    Invalid drives (``validate_drive`` fails), implausible ones (``config.plausibility``) and
    repeated drive ids are rejected with a reason
    in the report; the run goes on with the rest.

    Args:
        drives: the fleet drives.
        config: pipeline options (default: the recommended method).
        seed: seeds the random pivot order.
        progress: optional callback(stage, done, total).
        workers: processes for the pivot passes (see ``map_stretches``); the map is the same.

    Returns:
        The map, the per-pivot segments and the report.

    Raises:
        NoUsableDataError: no usable drive.
    """
    t_start = time.perf_counter()
    drives_in = list(drives)
    usable, rejected = prepare_drives(drives_in, bounds=config.plausibility, workers=_check_workers(workers))
    if not usable:
        raise NoUsableDataError(
            f"none of the {len(drives_in)} drive(s) is usable: " + "; ".join(f"{d!r}: {r}" for d, r in rejected[:5])
        )
    res = map_stretches(usable, config=config, seed=seed, progress=progress, validated=True, workers=workers)
    seconds = dict(res.stage_seconds)
    t0 = time.perf_counter()
    ccfg = config.connection
    segs = res.segments
    # segments are connected one by one: over the workers by their step counts
    graphs = map_balanced(lambda i: connect_segment(segs[i], config=ccfg), [len(g.steps) for g in segs], workers)
    seconds["connection"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    hdmap = stitch(graphs, config=config.stitching)
    seconds["stitching"] = time.perf_counter() - t0
    c = res.counters
    report = BuildReport(
        n_drives_in=len(drives_in),
        n_drives_used=len(usable),
        rejected=rejected,
        km_mapped=c["steps_valid"] * config.sampling.step_m / 1000.0,
        steps_total=c["steps_total"],
        steps_rejected=c["steps_rejected"],
        steps_skipped_processed=c["steps_skipped_processed"],
        steps_off_road=c["steps_off_road"],
        seconds=time.perf_counter() - t_start,
        stage_seconds=seconds,
    )
    return BuildResult(map=hdmap, segments=res.segments, report=report, drives=usable)
