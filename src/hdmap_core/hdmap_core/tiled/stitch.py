"""The stitch (Sec. VI) per region of tiles, then joined across the region borders.

A region is a block of ``region_tiles`` x ``region_tiles`` tiles (``tiled.adjust.block_of``).
``stitch_region`` stitches the segment graphs of a region's tiles together with those of the
tiles within ``halo_tiles`` around it (``halo_tiles_for``: 1 km; ``MapGraph.integrate``, as the global stitch does) and
keeps the decisions for its own graphs only (``MapGraph.state``): which of their nodes stay and
the links that start at them, also those to a graph of the halo. ``join_regions`` puts every
region's graphs and decisions together (``MapGraph.from_states``) and exports the map.

Each decision is taken where the region sees the place with at least the halo around it: every
rule of the stitch looks at most ~1 km away (the 500-node short-cycle test; the other radii are
12-60 m, docs/graph.md), the halo covers 1 km. The global stitch also reads the whole map's
connectivity (whether two pieces are one component yet, in its order of the ends) and walks its
graphs in one order; a region sees only its part of both. So the joined map is the global
stitch's where those do not reach past the halo: compared on the bench fleets in docs/scale.md,
and checked in the tests on a synthetic network of several regions.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hdmap_core.graph.map_graph import MapGraph, StitchState
from hdmap_core.tiled.adjust import BlockKey, block_of, group_tiles

if TYPE_CHECKING:
    from hdmap_core.graph.segment_graph import SegmentGraph
    from hdmap_core.graph.stitch_config import StitchConfig
    from hdmap_core.model import HDMap

__all__ = [
    "RegionStitch",
    "stitch_region",
    "join_regions",
    "stitch_by_regions",
    "halo_tiles_for",
    "STITCH_HALO_M",
    "STITCH_HALO_TILES",
]

TileKey = tuple[int, int]
#: how far around a region its stitch sees the graphs too [m]: the farthest rule of the stitch,
#: the short-cycle test of 500 topology nodes (2 m steps)
STITCH_HALO_M = 1000.0
#: the halo in tiles of the tiled build's default size (1024 m)
STITCH_HALO_TILES = 1


def halo_tiles_for(tile_size_m: float) -> int:
    """The tiles around a region that cover ``STITCH_HALO_M`` with tiles of ``tile_size_m``."""
    return max(1, math.ceil(STITCH_HALO_M / float(tile_size_m) - 1e-9))


@dataclass(frozen=True)
class RegionStitch:
    """One region's stitch: its own segment graphs, the decisions for them and the CPU time the
    stitch took [s]."""

    region: BlockKey
    graphs: tuple[SegmentGraph, ...]
    state: StitchState
    cpu_seconds: float = 0.0


def stitch_region(
    region: BlockKey,
    parts: Sequence[tuple[TileKey, Sequence[SegmentGraph]]],
    config: StitchConfig,
    region_tiles: int,
) -> RegionStitch:
    """Stitch the graphs of ``parts`` (the region's tiles and its halo's, (tile, graphs) pairs)
    and keep the decisions for the graphs of the region's own tiles."""
    cpu0 = time.process_time()
    graphs = [g for _, gs in parts for g in gs]
    own = [g for key, gs in parts if block_of(key, region_tiles) == region for g in gs]
    mg = MapGraph(graphs, config=config)
    state = mg.state(g.key for g in own)
    return RegionStitch(region=region, graphs=tuple(own), state=state, cpu_seconds=time.process_time() - cpu0)


def join_regions(regions: Iterable[RegionStitch], config: StitchConfig) -> HDMap:
    """The map of all regions' graphs with their decisions (the join across the borders: a link
    from one region's graph to another's is its first node's region's)."""
    regions = list(regions)
    graphs = [g for r in regions for g in r.graphs]
    mg = MapGraph.from_states(graphs, [r.state for r in regions], config=config)
    return mg.to_hdmap()


def stitch_by_regions(
    graphs_by_tile: Sequence[tuple[TileKey, Sequence[SegmentGraph]]],
    config: StitchConfig,
    *,
    region_tiles: int,
    halo_tiles: int = STITCH_HALO_TILES,
) -> HDMap:
    """``stitch_region`` for every region and ``join_regions``, in this process (``tiled.build``
    runs them as tasks)."""
    by_tile = {(int(k[0]), int(k[1])): list(gs) for k, gs in graphs_by_tile}
    groups = group_tiles(by_tile, region_tiles, halo_tiles)
    return join_regions(
        [
            stitch_region(region, [(t, by_tile[t]) for t in tiles], config, region_tiles)
            for region, tiles in groups.items()
        ],
        config,
    )
