"""A fleet bag built tile by tile, out of core: the tile index, the runner, the tiled build.

``build_from_bag`` indexes the bag by tile in one streaming pass (``io.tileindex``), then runs
``hdmap_core.tiled.build.build_tiled`` over the index: in this process (``workers=1``), on a
``LocalCluster`` of ``workers`` processes, or on the Dask cluster at ``scheduler``
(``tcp://HOST:8786``). Used by ``hdmap bag2map --tiled`` and ``hdmap bench --tiled``.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hdmap_core.errors import NoUsableDataError
from hdmap_core.live.tiles import TileConfig
from hdmap_core.pipeline.config import PipelineConfig
from hdmap_core.tiled.build import TiledResult, build_tiled
from hdmap_core.tiled.cluster import DaskRunner, ProgressFn, Runner, SerialRunner
from hdmap_core.tiled.memory import peak_rss_mb
from hdmap_ros.io.tileindex import TileIndex, build_tile_index

__all__ = ["TiledBagResult", "make_runner", "build_from_bag"]


@dataclass(frozen=True)
class TiledBagResult:
    """The tiled build of a bag: the index (its counts and origin), what the bag reader rejected
    ((drive_id, reason, text) each), the build, the index pass's time and peak RSS, and (when
    asked for) the drives' trajectories (``TileIndex.trajectories``: poses only, every metre)."""

    index: TileIndex
    rejected: list[tuple[str, str, str]]
    result: TiledResult
    index_seconds: float
    index_peak_rss_mb: float
    trajectories: list[np.ndarray] = field(default_factory=list)


def make_runner(workers: int = 1, scheduler: str | None = None) -> Runner:
    """Where the tasks run: ``scheduler`` (a Dask cluster's address) if given, else this process
    for one worker, else a ``LocalCluster`` of ``workers`` processes."""
    if scheduler:
        return DaskRunner.connect(scheduler)
    if workers <= 1:
        return SerialRunner()
    return DaskRunner.local(workers)


def build_from_bag(
    bag: str | Path,
    *,
    config: PipelineConfig,
    tile_config: TileConfig | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    index_path: str | Path | None = None,
    progress: ProgressFn | None = None,
    block_tiles: int | None = None,
    stitch_tiles: int | None = None,
    trajectories: bool = False,
) -> TiledBagResult:
    """Index ``bag`` by tile (into ``index_path``, else a temporary file) and build its map by tiles
    (``block_tiles``: the adjustment block-wise, ``stitch_tiles``: the stitch per region,
    ``build_tiled``); ``trajectories``: also read the drives' poses back from the index (for the
    lanes' connectors; 16 bytes per metre driven).

    Raises:
        BagError: the bag is missing or not a bag.
        NoUsableDataError: no usable drive in it.
        ConfigError: no Dask scheduler at ``scheduler``.
    """
    runner = make_runner(workers, scheduler)  # first: an unreachable scheduler fails before the index pass
    try:
        with tempfile.TemporaryDirectory(prefix="hdmap-tiles-") as tmp:
            path = Path(index_path) if index_path else Path(tmp) / "tiles.sqlite"
            t0 = time.perf_counter()
            index = build_tile_index(
                bag,
                path,
                tile_config=tile_config,
                overwrite=True,
                progress=(lambda n: progress("index", n, 0)) if progress else None,
            )
            index_s = time.perf_counter() - t0
            index_rss = peak_rss_mb()
            rejected = index.rejected()
            if index.drive_count == 0:
                raise NoUsableDataError(
                    f"{bag}: no usable drive" + (f" ({index.bag_error})" if index.bag_error else "")
                )
            try:
                result = build_tiled(
                    index,
                    config=config,
                    runner=runner,
                    progress=progress,
                    block_tiles=block_tiles,
                    stitch_tiles=stitch_tiles,
                )
                poses = list(index.trajectories()) if trajectories else []
            finally:
                if not index_path:
                    index.close()
    finally:
        runner.close()
    return TiledBagResult(
        index=index,
        rejected=rejected,
        result=result,
        index_seconds=index_s,
        index_peak_rss_mb=index_rss,
        trajectories=poses,
    )
