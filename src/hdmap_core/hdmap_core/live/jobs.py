"""One job of the live mapper run on its input: a plain function, so a process pool can run it.

The schedule (:mod:`hdmap_core.live.scheduler`) says what to run; :func:`run_job` runs it with the
functions of :mod:`hdmap_core.live.tiles` and returns plain data the mapper stores and publishes.
Results depend on the job's input only, so they are the same in any process.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from hdmap_core.errors import ConfigError
from hdmap_core.live.fuse import fuse_drive
from hdmap_core.live.region import map_region
from hdmap_core.live.scheduler import FUSE, MAP, MODEL, OBSERVE, PART, REGION, REMAP, Job
from hdmap_core.live.tiles import (
    TileConfig,
    TileKey,
    TileWork,
    fleet_offsets,
    map_tile,
    map_tile_observed,
)
from hdmap_core.model import Drive

if TYPE_CHECKING:
    from hdmap_core.pipeline.adjustment import OffsetSource
    from hdmap_core.pipeline.config import PipelineConfig

__all__ = ["JobResult", "run_job", "warm_up", "WORK_KEPT"]

WORK_KEPT = 64  # RULE: tiles whose prepared work (TileWork) a process keeps for their settle job, least recent dropped

# tile -> (its drive set, the configs, its TileWork): the observation pass's work, reused by the
# tile's final pass when the drive set and the configs are still the same (else made afresh)
_work: OrderedDict[TileKey, tuple[tuple[str, ...], TileConfig, PipelineConfig, TileWork]] = OrderedDict()


@dataclass
class JobResult:
    """What a job made.

    Attributes:
        segments: MAP / REMAP: the tile's segments.
        observations: MAP with the fleet model, OBSERVE: the tile's step observations.
        model: MODEL: the fleet-wide ``OffsetModel``; REGION: the region's.
        tiles: REGION, PART: every tile of the job -> its segments; FUSE: the drive's tiles with it fused
            in (None: refused, see ``refused``).
        refused: FUSE: why the drive goes the normal way ('' when fused).
        seconds: the job's own run time [s].
    """

    segments: list | None = None
    observations: list | None = None
    model: Any = None
    tiles: dict[TileKey, list] | None = None
    refused: str = ""
    seconds: float = 0.0


def run_job(
    job: Job,
    drives: Sequence[Drive],
    *,
    tile_config: TileConfig,
    pipeline_config: PipelineConfig,
    use_fleet_model: bool,
    offset_model: OffsetSource | None = None,
    observations: Sequence | None = None,
    region_workers: int = 1,
    tile_segments: dict | None = None,
    load_drives: Callable[[], Sequence[Drive]] | None = None,
) -> JobResult:
    """Run one job.

    Args:
        job: from :meth:`LiveScheduler.next_jobs`.
        drives: the drives ``job.drive_ids`` names (MAP, OBSERVE, REMAP).
        use_fleet_model: a MAP job also returns the tile's observations (for the fleet model).
        offset_model: REMAP: the fleet-wide model ``job.sig`` names.
        observations: MODEL: every tile's observations.
        region_workers: REGION: processes of its build (this one plus forked children; keep 1 in
            a process with native threads of its own, e.g. a ROS node).
        tile_segments: FUSE: every tile of the job -> its current (settled) segments.
        load_drives: REGION: read the drives in this process instead of ``drives`` (the
            mapper's store, read-only: no decoding and pickling of every drive in the mapper's
            process); those ``job.drive_ids`` names are used. Either way they are the mapper's
            stored drives, checked when they came (``map_region``'s ``checked``).

    Raises:
        ConfigError: a job of unknown kind, or a REMAP without a model.
        HdmapError: the pipeline's own errors on the tile's data.
    """
    t0 = time.perf_counter()
    tc, pc = tile_config, pipeline_config
    if job.kind == MODEL:
        out = JobResult(model=fleet_offsets(list(observations or ()), pipeline_config=pc))
    elif job.kind == FUSE:
        fused = fuse_drive(drives[0], dict(tile_segments or {})) if drives else None
        if fused is None:
            out = JobResult(refused="drive not in the store")
        else:
            out = JobResult(tiles=fused.tiles, refused=fused.reason)
    elif job.kind == PART:  # a drive alone on new road: its tiles from one build of it
        reg = map_region(drives, [k for k, _ in job.tiles], tile_config=tc, pipeline_config=pc, workers=1)
        out = JobResult(tiles=reg.segments)
    elif job.kind == REGION:
        _work.clear()  # the region makes every tile: no kept observation pass is used any more
        if load_drives is not None:
            wanted = set(job.drive_ids)
            drives = [d for d in load_drives() if d.drive_id in wanted]
        reg = map_region(
            drives,
            [k for k, _ in job.tiles],
            tile_config=tc,
            pipeline_config=pc,
            workers=region_workers,
            checked=True,  # the mapper's stored drives: checked with these bounds when they came
        )
        out = JobResult(tiles=reg.segments, model=reg.model)
    elif job.key is None:
        raise ConfigError(f"a {job.kind} job needs a tile")
    elif job.kind == OBSERVE:
        out = JobResult(observations=_tile_work(job, drives, tc, pc).preview()[1])
    elif job.kind == REMAP:
        if offset_model is None:
            raise ConfigError(f"tile {job.key}: a remap job needs the fleet offset model")
        work = _kept_work(job, tc, pc)
        segments = (
            work.final(offset_model)
            if work is not None
            else map_tile(drives, job.key, tile_config=tc, pipeline_config=pc, offset_model=offset_model)
        )
        out = JobResult(segments=segments)
    elif job.kind == MAP and use_fleet_model and not job.final:
        # RULE: a tile's estimate while drives come is its observation pass (half the work of its
        # own adjustment and final pass); the settled map re-makes it with the fleet model anyway
        segments, obs = _tile_work(job, drives, tc, pc).preview()
        out = JobResult(segments=segments, observations=obs)
    elif job.kind == MAP and use_fleet_model:
        segments, obs = map_tile_observed(drives, job.key, tile_config=tc, pipeline_config=pc)
        out = JobResult(segments=segments, observations=obs)
    elif job.kind == MAP:
        out = JobResult(segments=map_tile(drives, job.key, tile_config=tc, pipeline_config=pc))
    else:
        raise ConfigError(f"unknown job kind {job.kind!r}")
    out.seconds = time.perf_counter() - t0
    return out


def _tile_work(job: Job, drives: Sequence[Drive], tc: TileConfig, pc: PipelineConfig) -> TileWork:
    """The tile's work for its observation pass, kept (:data:`WORK_KEPT`) for its final pass."""
    assert job.key is not None
    work = TileWork(drives, job.key, tile_config=tc, pipeline_config=pc)
    _work[job.key] = (job.drive_ids, tc, pc, work)
    _work.move_to_end(job.key)
    while len(_work) > WORK_KEPT:
        _work.popitem(last=False)
    return work


def _kept_work(job: Job, tc: TileConfig, pc: PipelineConfig) -> TileWork | None:
    """The kept work of the job's tile if made from the same drives with the same configs (taken
    out: a final pass is the last use of a drive set's work)."""
    kept = _work.pop(job.key, None) if job.key is not None else None
    if kept is None or kept[0] != job.drive_ids or kept[1] != tc or kept[2] != pc:
        return None
    return kept[3]


def warm_up() -> None:
    """Import the pipeline (what a worker process's first job would), so it is ready before drives come."""
    import hdmap_core.graph.connection  # noqa: F401, PLC0415
    import hdmap_core.pipeline.driver  # noqa: F401, PLC0415
