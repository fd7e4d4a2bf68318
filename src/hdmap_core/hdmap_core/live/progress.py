"""Which drives a live map holds: a drive counts once every tile it touches is mapped with it.

A map is stitched from one estimate per tile, each made from the drives that covered the tile then
(``drive_ids``), each drive named with the number of tiles it covers (``tile_counts``, known to the
mapper from the drive's trajectory). ``Map.drive_ids`` lists exactly the drives all of whose tiles
are in the map with them; a subscriber waiting for its drives then gets them fully mapped.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

__all__ = ["LiveStatus", "integrated_drives", "map_status"]


@dataclass(frozen=True)
class LiveStatus:
    """Progress of the live map (hdmap_msgs/MapStatus).

    Attributes:
        map_version: version of the latest map (0: none yet).
        drives_received: drives the mapper stored.
        drives_integrated: drives in that map's ``drive_ids`` (:func:`integrated_drives`).
        drives_rejected: drives refused as invalid.
        tiles_pending: tiles waiting to be mapped, re-estimated or stitched.
        tile_versions: tile estimates made (mapper) or stitched (the map's status).
        settled: nothing waits; the map is made from every received drive.
        stamp_ns: when a field above last changed [ns since the epoch].
    """

    map_version: int = 0
    drives_received: int = 0
    drives_integrated: int = 0
    drives_rejected: int = 0
    tiles_pending: int = 0
    tile_versions: int = 0
    settled: bool = False
    stamp_ns: int = 0

    def same(self, other: LiveStatus | None) -> bool:
        """Equal apart from the stamp."""
        return other is not None and _fields(self) == _fields(other)


def _fields(st: LiveStatus) -> tuple:
    return (
        st.map_version,
        st.drives_received,
        st.drives_integrated,
        st.drives_rejected,
        st.tiles_pending,
        st.tile_versions,
        st.settled,
    )


def map_status(
    mapper: LiveStatus,
    *,
    map_version: int,
    drives_integrated: int,
    tile_versions: int,
    tiles_unstitched: int,
    stitched: bool,
) -> LiveStatus:
    """The map's status: the mapper's part completed with the stitcher's.

    Args:
        mapper: the mapper's status (its ``tile_versions``: estimates made).
        map_version, drives_integrated: of the latest map.
        tile_versions: the versions of the tile estimates the stitcher holds, summed.
        tiles_unstitched: tiles whose stored estimate is not in the latest map yet.
        stitched: the latest map is made from every stored estimate (or they cannot be stitched).
    """
    settled = mapper.settled and stitched and tile_versions >= mapper.tile_versions
    return LiveStatus(
        map_version=map_version,
        drives_received=mapper.drives_received,
        drives_integrated=drives_integrated,
        drives_rejected=mapper.drives_rejected,
        tiles_pending=mapper.tiles_pending + tiles_unstitched,
        tile_versions=tile_versions,
        settled=settled,
        stamp_ns=mapper.stamp_ns,
    )


def integrated_drives(tiles: Iterable[tuple[Sequence[str], Sequence[int]]]) -> set[str]:
    """The drives every tile of which is among ``tiles`` with that drive.

    Args:
        tiles: per tile estimate in the map, (its drive ids, per drive id the number of tiles that
            drive covers). An estimate without counts (``()``, e.g. from a store of before the
            counts) vouches only for itself: its drives count when no estimate names a count.

    Returns:
        The integrated drive ids.
    """
    seen: dict[str, int] = {}
    need: dict[str, int] = {}
    for ids, counts in tiles:
        known = len(counts) == len(ids)
        for i, d in enumerate(ids):
            seen[d] = seen.get(d, 0) + 1
            if known:
                need[d] = max(need.get(d, 0), int(counts[i]))
    return {d for d, n in seen.items() if n >= need.get(d, 1)}
