"""Where a tiled build reads its drives: the clips of each tile's drives (``TileSource``).

A tile is mapped from the drives that come within the margin of it, each clipped to the tile grown
by the margin (``hdmap_core.live.tiles.clip_to_tile``). A source hands out exactly those clips per
tile, so a task holds one tile's working set, never the fleet. ``MemorySource`` clips drives held
in memory (tests, small fleets); ``hdmap_ros.io.tileindex`` stores the clips on disk in one
streaming pass over a bag and reads them back per tile.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from hdmap_core.live.tiles import TileConfig, TileKey, clip_to_tile, tiles_of_drive
from hdmap_core.model import Drive

__all__ = ["TileSource", "MemorySource"]


class TileSource(Protocol):
    """The drives of a tiled build, per tile. Pickled into every task: keep it small (a path)."""

    tile_config: TileConfig

    def tiles(self) -> list[TileKey]:
        """Every tile some drive covers, sorted."""
        ...

    def clips(self, key: TileKey) -> list[tuple[Drive, float]]:
        """The clips of the drives covering ``key`` and where each starts on its drive [m]."""
        ...

    def drive_ids(self, key: TileKey) -> list[str]:
        """Ids of the drives covering ``key``, sorted."""
        ...


class MemorySource:
    """A ``TileSource`` over drives held in memory (valid drives; clipped on demand)."""

    def __init__(self, drives: Sequence[Drive], tile_config: TileConfig) -> None:
        self.tile_config = tile_config
        self._drives = list(drives)
        self._cover: dict[TileKey, list[int]] = {}
        for i, d in enumerate(self._drives):
            for key in tiles_of_drive(d, config=tile_config):
                self._cover.setdefault(key, []).append(i)

    def tiles(self) -> list[TileKey]:
        return sorted(self._cover)

    def clips(self, key: TileKey) -> list[tuple[Drive, float]]:
        out = []
        for i in self._cover.get(key, []):
            clip, s0 = clip_to_tile(self._drives[i], key, tile_config=self.tile_config)
            if clip is not None:
                out.append((clip, s0))
        return out

    def drive_ids(self, key: TileKey) -> list[str]:
        return sorted(self._drives[i].drive_id for i in self._cover.get(key, []))
