"""The live settle's region path: every tile of the map made by one offline build, cut into tiles.

With the fleet-wide offset model the settle re-makes every tile of the map (every drive moves the
network-wide solve). Tile by tile (``live.tiles``: each tile's observation pass, the model, each
tile's final pass) every drive is clipped to 2-4 tiles grown by their margins and every place is
walked about 1.4 times, so the settle costs about 2.5x the offline build of the same drives. As
one region the settle is that offline build: ``pipeline.driver.map_stretches`` on the whole
drives (observation pass, network-wide adjustment, final pass; its fork workers over independent
pivot groups), then each step goes to the tile its midpoint lies in (:func:`cut_into_tiles`,
what ``tiles.select_steps`` keeps of a tile's own estimate), so the stitcher gets the per-tile
estimates it always gets.

The result is a function of the drive set only: drives are ordered by id, the seed is the
tiling's base seed, and every tile of the map is made in the one region.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hdmap_core.live.tiles import TileConfig, TileKey
from hdmap_core.model import Drive
from hdmap_core.steps import Segment

if TYPE_CHECKING:
    from hdmap_core.pipeline.config import PipelineConfig

__all__ = ["RegionResult", "map_region", "cut_into_tiles"]


@dataclass
class RegionResult:
    """What a region build made.

    Attributes:
        segments: per tile of the region, its segments (steps whose midpoint lies in the tile
            proper; ``s_m`` travelled distances of the whole pivot drives).
        model: the region's network-wide ``OffsetModel`` (None without a final pass).
    """

    segments: dict[TileKey, list[Segment]]
    model: Any = None


def cut_into_tiles(
    segments: Iterable[Segment], keys: Iterable[TileKey], *, tile_size_m: float
) -> dict[TileKey, list[Segment]]:
    """Each segment's steps to the tile their midpoint lies in (``floor(midpoint / tile_size_m)``).

    A segment becomes one segment per run of consecutive steps in the same tile (as
    ``tiles.select_steps`` splits a segment whose kept steps are not consecutive), in input
    order; steps in a tile not among ``keys`` are dropped.

    Returns:
        Every key of ``keys`` (empty lists included) -> its segments.
    """
    out: dict[TileKey, list[Segment]] = {(int(k[0]), int(k[1])): [] for k in keys}
    for seg in segments:
        if not seg.steps:
            continue
        mids = np.array([np.asarray(st.midpoint, dtype=float)[:2] for st in seg.steps]).reshape(-1, 2)
        cell = np.floor(mids / float(tile_size_m)).astype(np.int64)
        change = np.flatnonzero(np.any(cell[1:] != cell[:-1], axis=1)) + 1
        starts = np.concatenate([[0], change])
        stops = np.concatenate([change, [len(cell)]])
        for s, e in zip(starts.tolist(), stops.tolist()):
            key = (int(cell[s, 0]), int(cell[s, 1]))
            if key in out:
                out[key].append(Segment(pivot_id=seg.pivot_id, steps=tuple(seg.steps[s:e])))
    return out


def map_region(
    drives: Sequence[Drive],
    keys: Iterable[TileKey],
    *,
    tile_config: TileConfig,
    pipeline_config: PipelineConfig,
    workers: int = 1,
    checked: bool = False,
) -> RegionResult:
    """The tiles ``keys`` made from ``drives`` in one build (see the module docstring).

    Args:
        drives: every drive covering the tiles (any order; not modified).
        keys: the tiles to return.
        tile_config: the tiling (``tile_size_m``; ``seed`` seeds the build).
        pipeline_config: the pipeline's options (as ``bag2map``'s).
        workers: processes for the passes (this one plus forked children; see ``map_stretches``).
        checked: every drive passed ``validate_drive`` and ``check_plausible`` with
            ``pipeline_config.plausibility`` already and no id repeats (the live mapper's store
            keeps only such drives): not checked again.

    Raises:
        HdmapError: the pipeline's own errors.
    """
    from hdmap_core.pipeline.driver import map_stretches  # noqa: PLC0415 - the pipeline is heavy
    from hdmap_core.plausibility import prepare_drives  # noqa: PLC0415

    keys = [(int(k[0]), int(k[1])) for k in keys]
    usable = sorted(drives, key=lambda d: d.drive_id)
    if not checked:
        usable, _ = prepare_drives(usable, bounds=pipeline_config.plausibility)
    if not usable:
        return RegionResult({k: [] for k in keys})
    res = map_stretches(usable, config=pipeline_config, seed=tile_config.seed, validated=True, workers=workers)
    return RegionResult(
        cut_into_tiles(res.segments, keys, tile_size_m=tile_config.tile_size_m),
        res.offset_model,
    )
