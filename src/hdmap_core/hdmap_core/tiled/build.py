"""A whole map built tile by tile: the method of ``pipeline.driver.build_map``, out of core.

1. Observation pass: every tile's pivots sample and align (per-step EM) over the tile and its
   margin; the observations of the tile proper come back (``tasks.observe``).
2. One network-wide offset adjustment over all observations (a single global solve, as
   ``build_map`` and ``hdmap_core.live.tiles.fleet_offsets`` do), its observations held in parts
   of consecutive tiles on the workers (``pipeline.adjustment_dist``): this process sums the
   parts' shares of the normal equations and solves; the same offsets up to the order of
   floating-point sums.
3. Final pass: every tile is sampled, aligned and aggregated with its drives shifted by the
   adjustment's offsets, and connected (``tasks.map_connect``); its segment graphs come back.
4. The segment graphs of all tiles, in tile order, are stitched into the map (Sec. VI); with
   ``stitch_tiles`` per region of tiles as tasks, then joined across the region borders
   (``tiled.stitch``), so the segment graphs stay on the workers.

Each tile is a pure function of its drives' clips, its key and the offsets, and results are
combined in tile order: the map is the same with any number of workers. It is the map the live
node suite settles on (``hdmap_core.live``), not byte for byte the one ``build_map`` makes from
the whole fleet at once (other pivots, other random order); docs/scale.md gives the difference.
A preset without the adjustment (``final_pass`` None) runs the tiles' one pass only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

from hdmap_core.errors import ConfigError, NoUsableDataError
from hdmap_core.graph.map_graph import stitch
from hdmap_core.model import HDMap
from hdmap_core.pipeline.adjustment_dist import AdjustPart, adjust_parts
from hdmap_core.pipeline.config import PipelineConfig
from hdmap_core.tiled import tasks
from hdmap_core.tiled.adjust import HALO_TILES, group_tiles
from hdmap_core.tiled.clips import TileSource
from hdmap_core.tiled.cluster import ProgressFn, Runner, SerialRunner
from hdmap_core.tiled.stitch import halo_tiles_for

__all__ = ["TiledReport", "TiledResult", "build_tiled", "PART_TILES"]

#: the one offset solve's observations are held in parts of this many consecutive tiles (key
#: order), one Dask actor each: fewer parts, fewer messages per solver step; more, less memory
#: per part (docs/scale.md)
PART_TILES = 4


@dataclass(frozen=True)
class TiledReport:
    """What a tiled build did.

    Attributes:
        tiles: tiles mapped.
        observations: step observations fed to the adjustment.
        graphs: segment graphs stitched.
        workers: worker processes (1: this process).
        seconds: wall time of the build [s].
        stage_seconds: wall time per stage [s].
        peak_rss_mb: peak RSS per process at the end [MB] ("main", "scheduler", "worker ADDR").
        cpu_seconds: CPU time per process during the build [s] ("main", "worker ADDR"; the
            workers' since they started): what the build cost on a machine shared with others.
        stitch_cpu_seconds: CPU time of the stitch [s]: "stitch" in this process, or with
            ``stitch_tiles`` of its tasks ("regions": all region tasks, "region_max": the
            largest, "join").
    """

    tiles: int = 0
    observations: int = 0
    graphs: int = 0
    workers: int = 1
    seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    peak_rss_mb: dict[str, float] = field(default_factory=dict)
    cpu_seconds: dict[str, float] = field(default_factory=dict)
    stitch_cpu_seconds: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        """A few readable lines."""
        rss = ", ".join(f"{k} {v:.0f}" for k, v in self.peak_rss_mb.items())
        return "\n".join(
            [
                f"tiles: {self.tiles}, {self.observations} step observations, {self.graphs} segment graphs, "
                f"{self.workers} worker(s)",
                f"time: {self.seconds:.2f} s ("
                + ", ".join(f"{k} {v:.2f}" for k, v in self.stage_seconds.items())
                + ")",
                f"peak RSS MB: {rss}",
                "CPU s: " + ", ".join(f"{k} {v:.1f}" for k, v in self.cpu_seconds.items()),
            ]
            + (
                ["stitch CPU s: " + ", ".join(f"{k} {v:.2f}" for k, v in self.stitch_cpu_seconds.items())]
                if self.stitch_cpu_seconds
                else []
            )
        )


@dataclass(frozen=True)
class TiledResult:
    """Output of :func:`build_tiled`."""

    map: HDMap
    report: TiledReport


def build_tiled(
    source: TileSource,
    *,
    config: PipelineConfig = PipelineConfig(),
    runner: Runner | None = None,
    progress: ProgressFn | None = None,
    block_tiles: int | None = None,
    halo_tiles: int = HALO_TILES,
    stitch_tiles: int | None = None,
) -> TiledResult:
    """Build the map of the drives of ``source`` tile by tile (see the module docstring).

    Args:
        source: the tiles' drives (``clips.MemorySource``, ``hdmap_ros.io.tileindex``); its
            ``tile_config`` sets the tiles, the margins and the seed.
        config: pipeline options (default: the recommended method).
        runner: where the tasks run (default: this process).
        progress: optional callback(stage, done, total).
        block_tiles: None: one network-wide offset adjustment over all tiles' observations in
            this process. N: the adjustment block-wise over blocks of N x N tiles with a global
            coarse solve (``tiled.adjust``), as tasks of the runner; the observations stay on the
            workers. ``halo_tiles``: the tiles around a block that its solve sees too.

    Raises:
        NoUsableDataError: the source has no tile.
        ConfigError: ``block_tiles`` or ``stitch_tiles`` not an integer >= 1.
    """
    if stitch_tiles is not None and (
        isinstance(stitch_tiles, bool) or not isinstance(stitch_tiles, int) or stitch_tiles < 1
    ):
        raise ConfigError(f"stitch_tiles must be an integer >= 1, got {stitch_tiles!r}")
    t_start = time.perf_counter()
    runner = runner or SerialRunner()
    cpu0 = runner.cpu_seconds()
    keys = source.tiles()
    if not keys:
        raise NoUsableDataError("no drive covers any tile: nothing to map")
    seconds: dict[str, float] = {}
    weights = [len(source.drive_ids(k)) for k in keys] if runner.workers > 1 else None  # heaviest tiles first
    model = None
    n_obs = 0
    stitch_cpu: dict[str, float] = {}
    if config.final_pass is not None and block_tiles is not None:
        if isinstance(block_tiles, bool) or not isinstance(block_tiles, int) or block_tiles < 1:
            raise ConfigError(f"block_tiles must be an integer >= 1, got {block_tiles!r}")
        t0 = time.perf_counter()
        groups = list(group_tiles(keys, block_tiles, halo_tiles).items())
        if weights is not None:  # heaviest blocks first
            w = dict(zip(keys, weights, strict=True))
            groups.sort(key=lambda g: -sum(w[k] for k in g[1]))
        model = runner.run_grouped(
            "observe",
            tasks.observe_keyed,
            groups,
            tasks.solve_block_of,
            tasks.coarse_merge,
            shared=(source, config),
            group_shared=(config, block_tiles),
            progress=progress,
        )
        n_obs = int(model.stats.get("observations", 0))
        seconds["observation_pass_and_adjustment"] = time.perf_counter() - t0
    elif config.final_pass is not None:
        t0 = time.perf_counter()
        # RULE the observations stay where they were made: parts of PART_TILES consecutive tiles
        # (in key order, so their concatenation is the one solve's observation sequence and the
        # partition does not depend on the workers), each held on a worker; the one solve runs
        # over them (pipeline.adjustment_dist)
        part_groups = [list(range(i, min(i + PART_TILES, len(keys)))) for i in range(0, len(keys), PART_TILES)]
        parts = runner.run_parts(
            "observe",
            tasks.observe,
            keys,
            part_groups,
            AdjustPart,
            shared=(source, config),
            progress=progress,
            weights=weights,
        )
        seconds["observation_pass"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        try:
            model = adjust_parts(parts.call, len(part_groups), replace(config.adjustment, compute_std=False))
        finally:
            parts.close()
        n_obs = int(model.stats.get("n_steps", 0))
        seconds["adjustment"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fleet_model = model

    def offsets(key: tuple[int, int]) -> tuple:
        return (tasks.model_of(fleet_model, source.drive_ids(key)) if fleet_model is not None else None,)

    if stitch_tiles is not None:
        halo = halo_tiles_for(source.tile_config.tile_size_m)
        regions = list(group_tiles(keys, stitch_tiles, halo).items())
        if weights is not None:  # heaviest regions first
            w = dict(zip(keys, weights, strict=True))
            regions.sort(key=lambda g: -sum(w[k] for k in g[1]))
        hdmap, n_graphs, stitch_cpu = runner.run_grouped(
            "map",
            tasks.map_connect_keyed,
            regions,
            tasks.stitch_region_of,
            tasks.join_stitched,
            shared=(source, config),
            group_shared=(config.stitching, stitch_tiles),
            progress=progress,
            per_item=offsets,
        )
        seconds["final_pass_and_stitching"] = time.perf_counter() - t0
    else:
        per_tile = runner.run(
            "map",
            tasks.map_connect,
            keys,
            shared=(source, config),
            per_item=offsets,
            progress=progress,
            weights=weights,
        )
        graphs = [g for gs in per_tile for g in gs]
        n_graphs = len(graphs)
        del per_tile
        seconds["final_pass"] = time.perf_counter() - t0
        t0, c0 = time.perf_counter(), time.process_time()
        hdmap = stitch(graphs, config=config.stitching)
        del graphs
        seconds["stitching"] = time.perf_counter() - t0
        stitch_cpu = {"stitch": time.process_time() - c0}
    report = TiledReport(
        tiles=len(keys),
        observations=n_obs,
        graphs=n_graphs,
        workers=runner.workers,
        seconds=time.perf_counter() - t_start,
        stage_seconds=seconds,
        peak_rss_mb=runner.peak_rss_mb(),
        cpu_seconds={k: v - cpu0.get(k, 0.0) for k, v in runner.cpu_seconds().items()},
        stitch_cpu_seconds=stitch_cpu,
    )
    return TiledResult(map=hdmap, report=report)
