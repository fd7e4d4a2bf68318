"""Incremental mapping by tiles: the map as a function of its inputs per place.

The live node suite (``hdmap_ros.nodes``) keeps the map up to date as drives arrive. To make the
incremental result converge to what the offline pipeline builds from the same drives, every piece
of the map is a pure function of the drives that cover its place:

- The plane is cut into square tiles of ``tile_size_m`` (key ``(ix, iy)``, ``ix = floor(x / size)``).
- A drive *covers* a tile when its trajectory comes within ``margin_m`` of the tile.
- A tile is mapped from all drives covering it, each clipped to the tile grown by the margin, with a
  seed derived from the tile key only (:func:`tile_seed`); of the resulting steps only those whose
  midpoint lies inside the tile proper are kept (:func:`select_steps`), so neighbouring tiles never
  map the same place twice and the margin gives every kept step its full cut line and context.
- A tile is re-estimated only when its drive count grew enough that the estimate improves
  (:func:`needs_update`, a debounce); when the input settles, every tile whose drive set changed is
  re-estimated once more, so the settled map depends on the final drive set only.
- Offsets: a tile can adjust them over its own drives (:func:`map_tile_observed`, which also returns
  its step observations in travelled distances of the full drives), or take one fleet-wide model
  (:func:`fleet_offsets` over the observations of all tiles, :func:`observe_tile`; the network-wide
  adjustment of the offline pipeline) and run only the final pass with it
  (``map_tile(..., offset_model=...)``). The live mapper settles with the latter.
- Feature ids are carried over from the previous map version where a feature persists
  (:func:`carry_over_ids`), so consumers can follow a feature across versions.

Stitching the tiles' segments into the complete map is Sec. VI of Immel et al. 2023 (the same
mechanism that inserts a new drive's result into an existing map); see ``hdmap_core.graph.map_graph``.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from hdmap_core.errors import ConfigError
from hdmap_core.geometry import arc_length, resample_evenly, split_long_segments, true_runs
from hdmap_core.model import Detection, Drive, HDMap
from hdmap_core.steps import Segment

if TYPE_CHECKING:  # the pipeline is heavy; tiles load it on first use
    from hdmap_core.pipeline.adjustment import OffsetSource
    from hdmap_core.pipeline.aggregation import ProcessedStore
    from hdmap_core.pipeline.config import PipelineConfig
    from hdmap_core.pipeline.offset_table import OffsetTable

__all__ = [
    "TileConfig",
    "TileKey",
    "tile_bounds",
    "tiles_of_drive",
    "road_cells",
    "ROAD_CELL_M",
    "tile_seed",
    "clip_drive",
    "clip_to_tile",
    "observe_clips",
    "map_clips",
    "select_steps",
    "steps_outside",
    "needs_update",
    "map_tile",
    "map_tile_observed",
    "observe_tile",
    "preview_tile",
    "TileWork",
    "fleet_offsets",
    "observations_signature",
    "carry_over_ids",
    "connect_tile",
    "stitch_graphs",
]

TileKey = tuple[int, int]


@dataclass(frozen=True)
class TileConfig:
    """How the plane is tiled for incremental mapping.

    Attributes:
        tile_size_m: edge length of a square tile [m].
        margin_m: context around a tile: drives within it cover the tile and are mapped with it [m].
            Must be below ``tile_size_m``; it should exceed the detection range ahead (~40 m) so that
            every kept step sees its full context.
        min_growth_fraction: re-estimate a mapped tile when its drive count grew by at least this
            fraction of the count at the last estimate ...
        min_growth_drives: ... and by at least this many drives. The estimate's noise falls as
            1/sqrt(N), so a 10 % growth improves it by ~5 %. With 1, every tile of fewer than 11
            drives (road ends, sparse stretches) was due after each drive that crossed it (13 of
            108 tiles for a 10 km drive on a 100-drive map); with 3 a single drive never makes a
            mapped tile due, sparse tiles are re-estimated every third drive, and settling
            re-estimates every stale tile once anyway.
        seed: base seed; each tile's seed is derived from it and the tile key.
        pivot_margin_m: when set, pivots walk (sample, align, aggregate) only their steps within
            this distance of the tile proper; drives stay clipped to ``margin_m`` (all of it is
            still context for the alignment). Steps further out are dropped by
            :func:`select_steps` anyway, so this only saves their work, at the price of the
            global offset adjustment seeing only the steps walked. None: walk the whole grown tile.
    """

    tile_size_m: float = 256.0
    margin_m: float = 128.0
    min_growth_fraction: float = 0.10
    min_growth_drives: int = 3
    seed: int = 0
    pivot_margin_m: float | None = None

    def __post_init__(self) -> None:
        if not (self.tile_size_m > 0 and math.isfinite(self.tile_size_m)):
            raise ConfigError(f"tile_size_m must be > 0, got {self.tile_size_m}")
        if not (0 <= self.margin_m < self.tile_size_m):
            raise ConfigError(f"margin_m must be in [0, tile_size_m), got {self.margin_m}")
        if self.min_growth_fraction < 0:
            raise ConfigError(f"min_growth_fraction must be >= 0, got {self.min_growth_fraction}")
        if self.min_growth_drives < 1:
            raise ConfigError(f"min_growth_drives must be >= 1, got {self.min_growth_drives}")
        if self.pivot_margin_m is not None and not (0 <= self.pivot_margin_m <= self.margin_m):
            raise ConfigError(f"pivot_margin_m must be None or in [0, margin_m], got {self.pivot_margin_m}")


def tile_bounds(key: TileKey, *, tile_size_m: float, margin_m: float = 0.0) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of a tile grown by ``margin_m`` on every side [m]."""
    ix, iy = key
    return (
        ix * tile_size_m - margin_m,
        iy * tile_size_m - margin_m,
        (ix + 1) * tile_size_m + margin_m,
        (iy + 1) * tile_size_m + margin_m,
    )


def tiles_of_drive(drive: Drive, *, config: TileConfig) -> set[TileKey]:
    """The tiles a drive covers: its trajectory comes within ``margin_m`` of them.

    Args:
        drive: a valid drive (trajectory (N, 2) in the map frame [m]).
        config: tiling.

    Returns:
        Set of tile keys (ix, iy).
    """
    size, margin = config.tile_size_m, config.margin_m
    step = max(1.0, margin / 2 if margin else size / 4)
    # at most 4096 points per step (262 km at the default margin): only a defective drive has a
    # longer one, and it must not size the output (a pose at 1e12 m asked for 233 GiB)
    xy, _ = split_long_segments(np.asarray(drive.xy, dtype=float), np.zeros(1, dtype=np.int64), step, max_pieces=4096)
    if len(xy) == 0:
        return set()
    lo = np.floor((xy - margin) / size).astype(np.int64)
    hi = np.floor((xy + margin) / size).astype(np.int64)
    rows = np.concatenate([lo, hi], axis=1)
    rows = rows[np.concatenate([[True], np.any(rows[1:] != rows[:-1], axis=1)])]  # runs of points: once
    keys: set[TileKey] = set()
    # margin < size: each axis spans at most two tiles per point.
    for ax in (rows[:, 0], rows[:, 2]):
        for ay in (rows[:, 1], rows[:, 3]):
            keys.update(zip(ax.tolist(), ay.tolist()))
    return keys


ROAD_CELL_M = 16.0  # RULE: cell of the road-coverage grid [m]: a drive adding cells to a tile drove new road there


def road_cells(drive: Drive, *, config: TileConfig) -> dict[TileKey, frozenset[tuple[int, int]]]:
    """Where a drive drove, per tile proper: the cells of a ``ROAD_CELL_M`` grid its trajectory
    passes (tiles' edges are multiples of it when ``tile_size_m`` is). A drive whose cells a tile's
    estimate has not seen brings new road to that tile."""
    xy, _ = split_long_segments(np.asarray(drive.xy, dtype=float), np.zeros(1, dtype=np.int64), ROAD_CELL_M / 2)
    if len(xy) == 0:
        return {}
    cells = np.floor(xy / ROAD_CELL_M).astype(np.int64)
    tiles = np.floor(xy / config.tile_size_m).astype(np.int64)
    rows = np.concatenate([tiles, cells], axis=1)
    # consecutive points mostly share their cell (poses ~1 m apart): each run once
    rows = rows[np.concatenate([[True], np.any(rows[1:] != rows[:-1], axis=1)])]
    out: dict[TileKey, set[tuple[int, int]]] = {}
    for tx, ty, cx, cy in rows.tolist():
        out.setdefault((tx, ty), set()).add((cx, cy))
    return {k: frozenset(v) for k, v in out.items()}


def tile_seed(key: TileKey, *, seed: int = 0) -> int:
    """Deterministic 31-bit seed of a tile: the same tile always draws the same random choices."""
    return zlib.crc32(f"{int(seed)}:{int(key[0])}:{int(key[1])}".encode()) & 0x7FFFFFFF


def _inside(xy: np.ndarray, bounds: Sequence[float]) -> np.ndarray:
    xmin, ymin, xmax, ymax = bounds
    return (xy[:, 0] >= xmin) & (xy[:, 0] < xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] < ymax)


def clip_drive(drive: Drive, bounds: Sequence[float]) -> Drive | None:
    """The part of a drive inside a box, or None when fewer than 2 poses lie inside.

    The trajectory keeps the poses from the first to the last one inside the box (a drive that
    leaves and comes back keeps its excursion, so it stays one drive with one id); every detection
    polyline is cut to its runs of points inside the box (runs of fewer than 2 points dropped).

    Args:
        drive: the drive (not modified).
        bounds: (xmin, ymin, xmax, ymax) [m], half-open.
    """
    clipped, _ = _clip(drive, bounds)
    return clipped


def _clip(drive: Drive, bounds: Sequence[float]) -> tuple[Drive | None, float]:
    """:func:`clip_drive` and the travelled distance of the full drive where the clipped one starts [m]."""
    xy = np.asarray(drive.xy, dtype=float)
    inside = _inside(xy, bounds)
    idx = np.flatnonzero(inside)
    if len(idx) < 2:
        return None, 0.0
    a, b = int(idx[0]), int(idx[-1]) + 1
    s0 = float(arc_length(xy[: a + 1])[-1])
    dets: list[Detection] = []
    for det in drive.detections:
        pts = np.asarray(det.points, dtype=float)
        for s, e in true_runs(_inside(pts, bounds)):
            if e - s >= 2:
                dets.append(Detection(type=det.type, points=pts[s:e]))
    clipped = replace(
        drive,
        xy=xy[a:b],
        yaw=np.asarray(drive.yaw)[a:b],
        stamps_ns=np.asarray(drive.stamps_ns)[a:b],
        detections=tuple(dets),
    )
    return clipped, s0


def select_steps(segments: Iterable[Segment], bounds: Sequence[float]) -> list[Segment]:
    """Keep the steps whose midpoint lies inside ``bounds``; split segments where steps were cut.

    A segment whose kept steps are not consecutive (the pivot left the box and came back) becomes
    several segments of the same pivot, so the connection stage never bridges across the gap.
    """
    out: list[Segment] = []
    for seg in segments:
        if not seg.steps:
            continue
        mids = np.array([np.asarray(st.midpoint, dtype=float) for st in seg.steps]).reshape(-1, 2)
        for s, e in true_runs(_inside(mids, bounds)):
            out.append(Segment(pivot_id=seg.pivot_id, steps=tuple(seg.steps[s:e])))
    return out


def needs_update(count_at_estimate: int, count_now: int, *, config: TileConfig) -> bool:
    """Whether a tile's estimate improves enough to re-estimate it (the debounce).

    A tile never estimated (count 0) with drives is always due. Otherwise the count must have grown
    by ``max(min_growth_drives, ceil(min_growth_fraction * count_at_estimate))``.
    """
    if count_now <= 0:
        return False
    if count_at_estimate <= 0:
        return True
    need = max(config.min_growth_drives, math.ceil(config.min_growth_fraction * count_at_estimate - 1e-9))
    return count_now - count_at_estimate >= need


@dataclass(frozen=True)
class _TileInput:
    """The drives of a tile clipped to it, where each clip starts on its drive, and its pivot skips."""

    clipped: list
    s0: dict[str, float]
    processed: ProcessedStore | None
    seed: int
    core: tuple[float, float, float, float]


def clip_to_tile(drive: Drive, key: TileKey, *, tile_config: TileConfig) -> tuple[Drive | None, float]:
    """A drive clipped to a tile grown by its margin (:func:`clip_drive`), and the travelled
    distance of the full drive where the clip starts [m] ((None, 0.0) when it does not reach in).

    What a tile is mapped from: :func:`observe_clips` and :func:`map_clips` take these pairs, so
    a tile's drives can be clipped once and stored (``hdmap_ros.io.tileindex``)."""
    return _clip(drive, tile_bounds(key, tile_size_m=tile_config.tile_size_m, margin_m=tile_config.margin_m))


def _tile_input(
    drives: Sequence[Drive], key: TileKey, tile_config: TileConfig, pipeline_config: PipelineConfig
) -> _TileInput:
    clips = []
    for d in drives:
        c, start = clip_to_tile(d, key, tile_config=tile_config)
        if c is not None:
            clips.append((c, start))
    return _clips_input(clips, key, tile_config, pipeline_config)


def _clips_input(
    clips: Sequence[tuple[Drive, float]], key: TileKey, tile_config: TileConfig, pipeline_config: PipelineConfig
) -> _TileInput:
    """The tile's input from its drives' clips (:func:`clip_to_tile`), in any order."""
    clipped, s0 = [], {}
    for c, start in sorted(clips, key=lambda cs: cs[0].drive_id):
        clipped.append(c)
        s0[c.drive_id] = start
    from hdmap_core.pipeline.driver import prepare_drives  # noqa: PLC0415 - the pipeline is heavy; import on first use

    # A clip can be degenerate (e.g. repeated poses): as map_stretches does. The drives passed the
    # physical bounds when they came in; a clip (e.g. a few metres in a corner) need not.
    clipped, _ = prepare_drives(clipped, bounds=None)
    processed = None
    if clipped and tile_config.pivot_margin_m is not None:
        near = tile_bounds(key, tile_size_m=tile_config.tile_size_m, margin_m=tile_config.pivot_margin_m)
        processed = steps_outside(clipped, near, step_m=float(pipeline_config.sampling.step_m))
    return _TileInput(
        clipped,
        s0,
        processed,
        tile_seed(key, seed=tile_config.seed),
        tile_bounds(key, tile_size_m=tile_config.tile_size_m),
    )


class _ClippedOffsets:
    """A fleet-wide offset model seen from drives clipped to a tile: ``s`` counts from the clip."""

    def __init__(self, model: OffsetSource, s0: dict[str, float]) -> None:
        self.model, self.s0 = model, s0

    def offset(self, drive_id: str, s_m: np.ndarray) -> np.ndarray:
        return self.model.offset(drive_id, np.asarray(s_m, dtype=float) + self.s0.get(drive_id, 0.0))

    def table(self, drive_ids: Sequence[str]) -> OffsetTable | None:
        """The model's ``OffsetTable`` read from the clips' starts (None: the model has none)."""
        base = self.model.table(drive_ids)
        if base is None or base.s0_m is not None:
            return None  # (a clip of a clip: its sums would be in another order)
        return base.with_start(np.array([self.s0.get(d, 0.0) for d in drive_ids], dtype=float))


def _core_observations(observations: Sequence, inp: _TileInput, key: TileKey) -> list:
    """The observations of steps inside the tile proper, with travelled distances of the full drives.

    Neighbouring tiles observe their margins too; keeping only the core steps, every place is
    observed once in the union over all tiles (as in the offline pipeline's single first pass).
    Pivot ids get the tile key as suffix (the same pivot is walked in every tile it crosses).
    """
    out = []
    xmin, ymin, xmax, ymax = inp.core
    for ob in observations:
        mx, my = (float(v) for v in np.asarray(ob.midpoint, dtype=float)[:2])
        if not (xmin <= mx < xmax and ymin <= my < ymax):
            continue
        shift = np.array([inp.s0.get(d, 0.0) for d in ob.drive_ids], dtype=float)
        out.append(
            replace(
                ob,
                pivot_id=f"{ob.pivot_id}#{int(key[0])},{int(key[1])}",
                drive_s_m=np.asarray(ob.drive_s_m, dtype=float) + shift,
            )
        )
    return out


def _whole_drive_s(segments: list[Segment], s0: dict[str, float]) -> list[Segment]:
    """The segments with each step's ``s_m`` counted from the start of the whole pivot drive,
    not of its clip to the tile (``s0``: where each clip starts on its drive).

    So the pieces of one pivot's path in the tiles it crosses share one order (the stitcher
    follows a pivot's track across tiles by it). The shift is rounded to 1/1024 m: the steps'
    distances are multiples of the step length, so their differences (the connection's gap
    tests) stay exactly what they were.
    """
    out = []
    for seg in segments:
        shift = round(float(s0.get(seg.pivot_id, 0.0)) * 1024.0) / 1024.0
        if shift == 0.0:
            out.append(seg)
            continue
        out.append(
            Segment(pivot_id=seg.pivot_id, steps=tuple(replace(st, s_m=float(st.s_m) + shift) for st in seg.steps))
        )
    return out


def map_tile(
    drives: Sequence[Drive],
    key: TileKey,
    *,
    tile_config: TileConfig,
    pipeline_config: PipelineConfig,
    offset_model: OffsetSource | None = None,
) -> list[Segment]:
    """Map one tile from the drives covering it (stages of Sec. III-V up to the segments).

    Every drive is clipped to the tile grown by the margin; drives are ordered by id and the seed is
    derived from the tile key, so the result is a function of the drive set and the tile only
    (and of ``offset_model`` when given).

    Args:
        drives: drives covering the tile (any order; not modified).
        key: the tile.
        tile_config: tiling.
        pipeline_config: a ``hdmap_core.pipeline.driver.PipelineConfig``.
        offset_model: a fleet-wide ``adjustment.OffsetModel`` (travelled distances of the full
            drives, e.g. from :func:`fleet_offsets`). With it and a config using the global
            adjustment, the tile runs only the final pass, its samples shifted by that model,
            instead of the observation pass plus an adjustment over the tile's own steps.

    Returns:
        Segments of the steps inside the tile proper (may be empty); the steps' ``s_m`` are
        travelled distances of the whole pivot drives (not of their clips).
    """
    if offset_model is not None and pipeline_config.final_pass is not None:
        return _map_input(_tile_input(drives, key, tile_config, pipeline_config), pipeline_config, offset_model)
    return map_tile_observed(drives, key, tile_config=tile_config, pipeline_config=pipeline_config)[0]


def map_clips(
    clips: Sequence[tuple[Drive, float]],
    key: TileKey,
    *,
    tile_config: TileConfig,
    pipeline_config: PipelineConfig,
    offset_model: OffsetSource | None = None,
) -> list[Segment]:
    """:func:`map_tile` from the tile's clips (:func:`clip_to_tile` pairs, any order): the same
    segments as ``map_tile`` on the full drives with the same ``offset_model``."""
    inp = _clips_input(clips, key, tile_config, pipeline_config)
    if offset_model is not None and pipeline_config.final_pass is not None:
        return _map_input(inp, pipeline_config, offset_model)
    return _observed_input(inp, pipeline_config, key)[0]


def _map_input(inp: _TileInput, pipeline_config: PipelineConfig, offset_model: OffsetSource) -> list[Segment]:
    if not inp.clipped:
        return []
    segments = _final_pass(inp, pipeline_config, _ClippedOffsets(offset_model, inp.s0))
    return _whole_drive_s(select_steps(segments, inp.core), inp.s0)


def map_tile_observed(
    drives: Sequence[Drive], key: TileKey, *, tile_config: TileConfig, pipeline_config: PipelineConfig
) -> tuple[list[Segment], list]:
    """:func:`map_tile` with the tile's own adjustment, and the observations of its steps.

    Returns:
        (segments of the tile proper, the first pass's ``StepObservations`` of the steps inside
        the tile proper with travelled distances of the full drives: see :func:`observe_tile`).
    """
    return _observed_input(_tile_input(drives, key, tile_config, pipeline_config), pipeline_config, key)


def _observed_input(inp: _TileInput, pipeline_config: PipelineConfig, key: TileKey) -> tuple[list[Segment], list]:
    from hdmap_core.pipeline.driver import map_stretches  # the pipeline is heavy; import on first use

    if not inp.clipped:
        return [], []
    res = map_stretches(
        inp.clipped,
        config=pipeline_config,
        seed=inp.seed,
        processed=inp.processed,
        collect_observations=True,
        validated=True,
    )
    return _whole_drive_s(select_steps(res.segments, inp.core), inp.s0), _core_observations(res.observations, inp, key)


def observe_tile(
    drives: Sequence[Drive], key: TileKey, *, tile_config: TileConfig, pipeline_config: PipelineConfig
) -> list:
    """The tile's observation pass: per-step EM along its pivots, no adjustment, no final pass.

    Returns the ``StepObservations`` of the steps inside the tile proper; their ``drive_s_m`` are
    travelled distances of the full (unclipped) drives, so the observations of all tiles together
    feed one fleet-wide adjustment (:func:`fleet_offsets`). A function of the tile's drive set.
    """
    return _observe_input(_tile_input(drives, key, tile_config, pipeline_config), pipeline_config, key)


def observe_clips(
    clips: Sequence[tuple[Drive, float]], key: TileKey, *, tile_config: TileConfig, pipeline_config: PipelineConfig
) -> list:
    """:func:`observe_tile` from the tile's clips (:func:`clip_to_tile` pairs, any order)."""
    return _observe_input(_clips_input(clips, key, tile_config, pipeline_config), pipeline_config, key)


def _observe_input(inp: _TileInput, pipeline_config: PipelineConfig, key: TileKey) -> list:
    if not inp.clipped:
        return []
    return _core_observations(_first_pass(inp, pipeline_config), inp, key)


def preview_tile(
    drives: Sequence[Drive], key: TileKey, *, tile_config: TileConfig, pipeline_config: PipelineConfig
) -> tuple[list[Segment], list]:
    """The tile's observation pass (:func:`observe_tile`) and the segments of that pass.

    About half the work of :func:`map_tile_observed` (no adjustment, no final pass): a first
    estimate that puts a new road on the map while drives come, when the settled map is made with
    the fleet-wide model anyway. Returns (segments of the tile proper, its observations).
    """
    inp = _tile_input(drives, key, tile_config, pipeline_config)
    if not inp.clipped:
        return [], []
    res = _first_pass_result(inp, pipeline_config)
    return (
        _whole_drive_s(select_steps(res.segments, inp.core), inp.s0),
        _core_observations(res.observations, inp, key),
    )


class TileWork:
    """One tile's drive set prepared once for both of its passes (the live mapper's settle).

    With the fleet-wide model a tile runs its observation pass (:func:`preview_tile` /
    :func:`observe_tile`) while drives come, and its final pass with the model
    (``map_tile(..., offset_model=...)``) at the settle. Each of those clips the drives,
    preprocesses their detections and intersects every pivot step's cut with them again; kept in
    one object (``pipeline.driver.StagedPasses``), the final pass reuses all of it, as the final
    pass of ``build_map`` reuses its first pass's. The results are those of the functions named
    above on the same drives.

    Args:
        drives: the drives covering the tile (any order; not modified).
        key, tile_config, pipeline_config: as :func:`map_tile`; the config must have a final pass.
    """

    def __init__(
        self, drives: Sequence[Drive], key: TileKey, *, tile_config: TileConfig, pipeline_config: PipelineConfig
    ) -> None:
        from hdmap_core.pipeline.driver import StagedPasses  # noqa: PLC0415

        self.key = key
        self.pipeline_config = pipeline_config
        self._inp = _tile_input(drives, key, tile_config, pipeline_config)
        inp = self._inp
        self._passes = (
            StagedPasses(inp.clipped, config=pipeline_config, seed=inp.seed, processed=inp.processed)
            if inp.clipped
            else None
        )
        self._first: tuple[list[Segment], list] | None = None

    def preview(self) -> tuple[list[Segment], list]:
        """:func:`preview_tile`: (segments of the observation pass, observations), made once."""
        if self._first is None:
            if self._passes is None:
                self._first = ([], [])
            else:
                res = self._passes.first()
                self._first = (
                    _whole_drive_s(select_steps(res.segments, self._inp.core), self._inp.s0),
                    _core_observations(res.observations, self._inp, self.key),
                )
        return self._first

    def final(self, offset_model: OffsetSource) -> list[Segment]:
        """``map_tile(..., offset_model=offset_model)``: the final pass with the fleet model."""
        if self._passes is None:
            return []
        res = self._passes.final(_ClippedOffsets(offset_model, self._inp.s0))
        return _whole_drive_s(select_steps(res.segments, self._inp.core), self._inp.s0)


def fleet_offsets(observations: Sequence, *, pipeline_config: PipelineConfig):
    """The network-wide offset adjustment over the observations of all tiles (as ``bag2map`` does).

    Same settings as the pipeline's own adjustment, without the posterior std (unused by the
    mapping; O(p^3) in the fleet's knots). Deterministic for the same observations in the same order.
    """
    from hdmap_core.pipeline.adjustment import adjust_offsets  # noqa: PLC0415

    cfg = pipeline_config.adjustment
    return adjust_offsets(list(observations), config=replace(cfg, compute_std=False))


def observations_signature(parts: Iterable[tuple[TileKey, Sequence[str]]]) -> str:
    """A digest of which drive set each tile's observations were made from (any order in)."""
    import hashlib  # noqa: PLC0415

    h = hashlib.sha256()
    for key, ids in sorted((tuple(int(v) for v in k), tuple(sorted(i))) for k, i in parts):
        h.update(f"{key[0]},{key[1]}:{'|'.join(ids)};".encode())
    return h.hexdigest()[:32]


def _first_pass(inp: _TileInput, pipeline_config: PipelineConfig) -> list:
    """The step observations of the pipeline's first pass on a tile's drives (no adjustment)."""
    return _first_pass_result(inp, pipeline_config).observations


def _first_pass_result(inp: _TileInput, pipeline_config: PipelineConfig):
    """The pipeline's first pass on a tile's drives (no adjustment): segments and observations."""
    from hdmap_core.pipeline.driver import map_stretches  # noqa: PLC0415

    first_only = replace(pipeline_config, final_pass=None)
    return map_stretches(
        inp.clipped,
        config=first_only,
        seed=inp.seed,
        processed=inp.processed,
        collect_observations=True,
        validated=True,
        observations_only=True,
    )


def _final_pass(inp: _TileInput, pipeline_config: PipelineConfig, model: OffsetSource) -> list[Segment]:
    """The pipeline's final pass on a tile's drives with the fleet-wide offset ``model``."""
    from hdmap_core.pipeline.driver import map_stretches  # noqa: PLC0415

    return map_stretches(
        inp.clipped, config=pipeline_config, seed=inp.seed, processed=inp.processed, validated=True, offset_model=model
    ).segments


def steps_outside(drives: Sequence[Drive], bounds: Sequence[float], *, step_m: float):
    """A ``ProcessedStore`` holding every pivot step of ``drives`` outside ``bounds``.

    Passed to the pipeline as "processed before", these steps are skipped as pivot steps (the
    drives' detections there still count as context). Step positions are those of
    ``sampling.pivot_walk`` with ``step_m``; each mark covers a quarter step either side, so a
    step inside ``bounds`` is never covered.
    """
    from hdmap_core.pipeline.aggregation import ProcessedStore  # noqa: PLC0415
    from hdmap_core.pipeline.sampling import pivot_walk  # noqa: PLC0415

    marks: dict[str, np.ndarray] = {}
    for d in drives:
        s, pts, _ = pivot_walk(d, step_m=step_m)
        out = ~_inside(np.asarray(pts, dtype=float).reshape(-1, 2), bounds)
        if out.any():
            marks[d.drive_id] = np.asarray(s, dtype=float)[out]
    return ProcessedStore().with_marks(marks, pad_m=0.25 * step_m, merge_gap_m=1.5 * step_m)


def connect_tile(segments: Sequence[Segment], key: TileKey, *, pipeline_config: PipelineConfig) -> list:
    """Sec. V for every segment of a tile: ``connection.connect_segment`` per segment.

    The same pivot drive is mapped in every tile it crosses, and its step indices count from where
    the drive was clipped to each tile; the segment graphs' keys (and the stable ids derived from
    them) would collide across tiles. So each pivot id is suffixed with the tile key here
    (``"<pivot>#<ix>,<iy>"``); drive ids of the steps stay as they are, and the graph's
    ``pivot_drive`` names the pivot's drive, so the stitcher follows one pivot's track over all
    the tiles it crosses (ordered by the steps' ``s_m``, travelled distances of the whole drive:
    :func:`map_tile`).

    Returns:
        One ``SegmentGraph`` per segment with at least one step, in input order.
    """
    from hdmap_core.graph.connection import connect_segment  # noqa: PLC0415

    out = []
    for seg in segments:
        if not seg.steps:
            continue
        pivot = f"{seg.pivot_id}#{int(key[0])},{int(key[1])}"
        renamed = Segment(pivot_id=pivot, steps=tuple(replace(st, pivot_id=pivot) for st in seg.steps))
        out.append(replace(connect_segment(renamed, config=pipeline_config.connection), pivot_drive=seg.pivot_id))
    return out


def stitch_graphs(graphs: Sequence, *, pipeline_config: PipelineConfig, drive_ids: Iterable[str] = ()) -> HDMap:
    """Sec. VI: the segment graphs of all tiles stitched into the complete map.

    Args:
        graphs: the tiles' segment graphs, in a deterministic order (by tile key, then segment).
        pipeline_config: the ``PipelineConfig`` whose stitching options apply.
        drive_ids: the drives integrated so far (stored in the map, sorted).
    """
    from hdmap_core.graph.map_graph import stitch  # noqa: PLC0415

    hdmap = stitch(list(graphs), config=pipeline_config.stitching)
    return replace(hdmap, drive_ids=tuple(sorted(set(drive_ids))))


# --- feature ids -----------------------------------------------------------------------------------


class _NearLine:
    """A polyline, asked which points lie within a distance of it: ``shapely.distance(point, line)
    <= d`` for each point, found through an STRtree of the line's segments instead of measuring
    every point against every segment (the id carry-over of a 12 km map spent 90 % there)."""

    def __init__(self, points: np.ndarray) -> None:
        import shapely  # noqa: PLC0415

        pts = np.asarray(points, dtype=float)
        self.point = shapely.Point(pts[0]) if len(pts) < 2 else None
        self.tree = (
            shapely.STRtree(shapely.linestrings(np.stack([pts[:-1], pts[1:]], axis=1))) if len(pts) >= 2 else None
        )

    def share_within(self, points: np.ndarray, distance_m: float) -> float:
        """The share of ``points`` ((N, 2), N >= 1) within ``distance_m`` of the line."""
        import shapely  # noqa: PLC0415

        geoms = shapely.points(np.asarray(points, dtype=float))
        if self.tree is None:
            return float(np.mean(shapely.distance(geoms, self.point) <= distance_m))
        hit = self.tree.query(geoms, predicate="dwithin", distance=distance_m)
        return len(np.unique(hit[0])) / len(geoms)


def _shape_key(f) -> tuple:
    """A feature's type and points, as a dict key (equal for the same line)."""
    return (int(f.type), np.ascontiguousarray(f.points, dtype=np.float64).tobytes())


def carry_over_ids(
    new_map: HDMap,
    old_map: HDMap | None,
    *,
    max_distance_m: float = 0.75,
    min_overlap: float = 0.5,
    spacing_m: float = 2.0,
) -> HDMap:
    """Give the features of a new map version the ids of the old features they continue.

    A new feature equal to an old one (same type and points) keeps its id. Otherwise, a new
    feature continues an old one of the same type when at least ``min_overlap`` of the
    shorter of the two (resampled every ``spacing_m``) lies within ``max_distance_m`` of the other.
    Pairs are taken greedily by overlap (largest first); every old id is used at most once. Ids of
    new features without a match stay as the stitcher made them unless that id is taken by a carried
    one or named a feature of the old version (the stitcher's ids come from pivot, step and slot, so
    a different line can get the id of one that vanished), in which case the next free id is used:
    between two versions an id never names two different lines. Feature references (predecessors,
    successors, topology ``features``) are rewritten accordingly.

    Args:
        new_map: the freshly stitched map (not modified).
        old_map: the previous version, or None.

    Returns:
        ``new_map`` with renumbered features (same geometry, same order).
    """
    if old_map is None or not old_map.features or not new_map.features:
        return new_map
    from scipy.spatial import cKDTree  # noqa: PLC0415

    new_id: dict[int, int] = {}
    used_old: set[int] = set()
    # RULE: a feature the same as in the old version (type and every point) keeps its id at once:
    # the stitch re-makes unchanged places exactly, so only the changed places are matched below
    same: dict[tuple, list[int]] = {}
    for i, f in enumerate(old_map.features):
        same.setdefault(_shape_key(f), []).append(i)
    for j, f in enumerate(new_map.features):
        olds = same.get(_shape_key(f))
        if olds:
            i = olds.pop(0)
            new_id[j] = int(old_map.features[i].id)
            used_old.add(i)
    rest_old = [i for i in range(len(old_map.features)) if i not in used_old]
    rest_new = [j for j in range(len(new_map.features)) if j not in new_id]
    pairs: list[tuple[float, int, int]] = []
    if rest_old and rest_new:
        old_pts = {i: resample_evenly(old_map.features[i].points, spacing_m) for i in rest_old}
        all_old = np.vstack([old_pts[i] for i in rest_old])
        owner = np.repeat(np.asarray(rest_old), [len(old_pts[i]) for i in rest_old])
        tree_all = cKDTree(all_old)
        old_lines: dict[int, _NearLine] = {}  # made once, when first a candidate
        for j in rest_new:
            nf = new_map.features[j]
            npnt = resample_evenly(nf.points, spacing_m)
            # candidate old features: a point within max_distance_m of an old line lies within
            # max_distance_m + spacing_m / 2 of one of its resampled points
            near = tree_all.query_ball_point(npnt, r=max_distance_m + 0.5 * spacing_m)
            cands = {int(owner[k]) for lst in near for k in lst}
            new_line: _NearLine | None = None
            for i in sorted(cands):
                of = old_map.features[i]
                if of.type != nf.type:
                    continue
                # distances to the other polyline, not to its resampled points: the same line begun
                # a metre further back is resampled a metre out of phase
                if len(npnt) <= len(old_pts[i]):
                    if i not in old_lines:
                        old_lines[i] = _NearLine(of.points)
                    ov = old_lines[i].share_within(npnt, max_distance_m)
                else:
                    new_line = new_line or _NearLine(nf.points)
                    ov = new_line.share_within(old_pts[i], max_distance_m)
                if ov >= min_overlap:
                    pairs.append((ov, j, i))
    pairs.sort(key=lambda p: (-p[0], p[1], p[2]))
    for _, j, i in pairs:
        if j in new_id or i in used_old:
            continue
        new_id[j] = int(old_map.features[i].id)
        used_old.add(i)
    taken = set(new_id.values()) | {int(f.id) for f in old_map.features}
    for j, f in enumerate(new_map.features):
        if j in new_id:
            continue
        cand = int(f.id)
        while cand in taken:
            cand = (cand + 1) % (1 << 64)
        new_id[j] = cand
        taken.add(cand)

    # ids in the new map are unique, so old id -> index is a function
    remap = {int(f.id): new_id[j] for j, f in enumerate(new_map.features)}

    def _r(ids: Iterable[int]) -> tuple[int, ...]:
        return tuple(remap.get(int(i), int(i)) for i in ids)

    features = tuple(
        replace(f, id=new_id[j], predecessors=_r(f.predecessors), successors=_r(f.successors))
        for j, f in enumerate(new_map.features)
    )
    topology = tuple(replace(t, features=_r(t.features)) for t in new_map.topology)
    return replace(new_map, features=features, topology=topology)
