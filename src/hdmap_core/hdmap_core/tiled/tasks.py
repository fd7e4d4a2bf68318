"""The per-tile tasks of a tiled build; each a pure function of its tile's clips.

``observe`` runs the observation pass of one tile (sampling and the per-step EM along the pivots
of the tile and its margin; ``hdmap_core.live.tiles.observe_clips``) and returns the step
observations of the tile proper. ``map_connect`` runs the final pass with the fleet-wide offset
model (aggregation included), keeps the steps of the tile proper and connects them (Sec. V):
the tile's segment graphs. Both read their clips from the ``TileSource`` on the worker, so a task
carries a tile key, the source's address and, for the final pass, the offsets of the tile's drives.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import replace
from typing import TYPE_CHECKING

from hdmap_core.live.tiles import TileKey, connect_tile, map_clips, observe_clips
from hdmap_core.pipeline.adjustment import OffsetModel
from hdmap_core.tiled.adjust import BlockKey, block_of, coarse_shifts, merge_blocks, solve_block
from hdmap_core.tiled.memory import trim_memory
from hdmap_core.tiled.stitch import RegionStitch, join_regions, stitch_region

if TYPE_CHECKING:
    from hdmap_core.graph.segment_graph import SegmentGraph
    from hdmap_core.graph.stitch_config import StitchConfig
    from hdmap_core.model import HDMap
    from hdmap_core.pipeline.config import PipelineConfig
    from hdmap_core.steps import StepObservations
    from hdmap_core.tiled.clips import TileSource

__all__ = [
    "observe",
    "observe_keyed",
    "solve_block_of",
    "coarse_merge",
    "map_connect",
    "map_connect_keyed",
    "stitch_region_of",
    "join_stitched",
    "model_of",
]


def observe(source: TileSource, pipeline_config: PipelineConfig, key: TileKey) -> list[StepObservations]:
    """The observation pass of one tile: its steps' observations, in full-drive distances."""
    return observe_clips(source.clips(key), key, tile_config=source.tile_config, pipeline_config=pipeline_config)


def observe_keyed(
    source: TileSource, pipeline_config: PipelineConfig, key: TileKey
) -> tuple[TileKey, list[StepObservations]]:
    """``observe`` with the tile's key (the block-wise adjustment groups them by block)."""
    return key, observe(source, pipeline_config, key)


def solve_block_of(
    block: BlockKey,
    parts: list[tuple[TileKey, list[StepObservations]]],
    pipeline_config: PipelineConfig,
    block_tiles: int,
) -> tuple[BlockKey, OffsetModel]:
    """The adjustment of one block (its tiles and halo) from their ``observe_keyed`` results
    (``tiled.adjust``); ``stats["observations"]``: those of the block's own tiles."""
    observations = [o for _, obs in parts for o in obs]
    own = sum(len(obs) for key, obs in parts if block_of(key, block_tiles) == block)
    model = solve_block(observations, pipeline_config.adjustment)
    return block, replace(model, stats={**model.stats, "observations": own})


def coarse_merge(
    blocks: list[tuple[BlockKey, OffsetModel]], pipeline_config: PipelineConfig, block_tiles: int
) -> OffsetModel:
    """The coarse solve over the blocks' models and their merge: the fleet's offset model."""
    models = dict(blocks)
    model = merge_blocks(models, coarse_shifts(models, pipeline_config.adjustment))
    n_obs = sum(int(m.stats.get("observations", 0)) for m in models.values())
    return replace(model, stats={**model.stats, "observations": n_obs})


def map_connect(
    source: TileSource, pipeline_config: PipelineConfig, key: TileKey, offset_model: OffsetModel | None
) -> list[SegmentGraph]:
    """The final pass of one tile with ``offset_model``, connected: its segment graphs (without a
    model, e.g. a preset without the adjustment: the tile's one pass)."""
    # RULE a dense tile's final pass is a worker's peak (16x paper_like: about 450 MB on top of
    # what the worker held before it): start it from a trimmed heap, not above the freed pages
    # of the adjustment's parts and of the tiles before
    trim_memory()
    segments = map_clips(
        source.clips(key),
        key,
        tile_config=source.tile_config,
        pipeline_config=pipeline_config,
        offset_model=offset_model,
    )
    return connect_tile(segments, key, pipeline_config=pipeline_config)


def map_connect_keyed(
    source: TileSource, pipeline_config: PipelineConfig, key: TileKey, offset_model: OffsetModel | None
) -> tuple[TileKey, list[SegmentGraph]]:
    """``map_connect`` with the tile's key (the regional stitch groups them by region)."""
    return key, map_connect(source, pipeline_config, key, offset_model)


def stitch_region_of(
    region: BlockKey,
    parts: list[tuple[TileKey, list[SegmentGraph]]],
    stitch_config: StitchConfig,
    region_tiles: int,
) -> RegionStitch:
    """The stitch of one region (its tiles and halo) from their ``map_connect_keyed`` results
    (``tiled.stitch``)."""
    return stitch_region(region, parts, stitch_config, region_tiles)


def join_stitched(
    regions: list[RegionStitch], stitch_config: StitchConfig, region_tiles: int
) -> tuple[HDMap, int, dict[str, float]]:
    """The regions joined across their borders: the map, how many segment graphs it has and the
    stitch's CPU time [s] ("regions": all region tasks, "region_max": the largest, "join")."""
    cpu0 = time.process_time()
    hdmap = join_regions(regions, stitch_config)
    cpu = [r.cpu_seconds for r in regions]
    seconds = {"regions": sum(cpu), "region_max": max(cpu, default=0.0), "join": time.process_time() - cpu0}
    return hdmap, sum(len(r.graphs) for r in regions), seconds


def model_of(model: OffsetModel, drive_ids: Iterable[str]) -> OffsetModel:
    """``model`` restricted to some drives (a tile's): the same offsets for them, less to ship."""
    curves = model.drives
    return replace(model, drives={d: curves[d] for d in drive_ids if d in curves}, stats={})
