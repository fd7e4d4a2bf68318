"""A fleet bag indexed by spatial tile on disk: one streaming pass, then reads per tile.

:func:`build_tile_index` reads a fleet bag message by message (``bagio.iter_fleet_bag``; one
drive in memory at a time) and writes, per tile a drive covers (``live.tiles.tiles_of_drive``),
the drive clipped to the tile grown by the margin (``live.tiles.clip_to_tile``) into an SQLite
file, with where the clip starts on its drive. :class:`TileIndex` reads it back per tile: it is the
``hdmap_core.tiled.clips.TileSource`` of a tiled build, so a worker holds only the clips of the
tile it maps. A ``TileIndex`` pickles as its path: on a cluster the file must be readable at the
same path on every worker (shared storage); docs/scale.md.

Tables: ``meta`` (tiling, origin, counts), ``drives`` (id, length), ``clips`` (tile, drive id,
start of the clip [m], the clip as a ``persistence.store.drive_to_blob``), ``rejected`` (what the
bag reader skipped, with its reason), ``poses`` (each drive's trajectory alone, every POSE_STEP_M,
float64 x, y: the drives' connector lanes, ``lanes/connectors.py``, read them without the clips).
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path

import numpy as np

from hdmap_core.errors import BagError, ConfigError
from hdmap_core.geometry import resample_evenly
from hdmap_core.lanes.connectors import STEP_M
from hdmap_core.live.tiles import TileConfig, TileKey, clip_to_tile, tiles_of_drive
from hdmap_core.model import MAP_FRAME, Drive, GeoOrigin
from hdmap_ros.io.bagio import Rejection, iter_fleet_bag
from hdmap_ros.persistence.store import blob_to_drive, drive_to_blob

__all__ = ["TileIndex", "build_tile_index", "POSE_STEP_M"]

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE drives (seq INTEGER PRIMARY KEY, drive_id TEXT NOT NULL UNIQUE, length_m REAL NOT NULL);
CREATE TABLE clips (
    tx INTEGER NOT NULL, ty INTEGER NOT NULL, drive_id TEXT NOT NULL, s0_m REAL NOT NULL, blob BLOB NOT NULL,
    PRIMARY KEY (tx, ty, drive_id)
);
CREATE TABLE rejected (seq INTEGER PRIMARY KEY, drive_id TEXT, reason TEXT, detail TEXT);
CREATE TABLE poses (seq INTEGER PRIMARY KEY, drive_id TEXT NOT NULL, xy BLOB NOT NULL)
"""
POSE_STEP_M = STEP_M  # the trajectories kept for the lanes' connectors: every metre, as they use them

_COMMIT_EVERY = 32  # drives per transaction


def build_tile_index(
    bag: str | Path,
    path: str | Path,
    *,
    tile_config: TileConfig | None = None,
    expected_frame: str | None = MAP_FRAME,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> TileIndex:
    """Index a fleet bag by tile in one pass (see the module docstring).

    Args:
        bag: fleet bag (rosbag2 directory or ``.mcap``).
        path: SQLite file to write.
        tile_config: tiles and margins (stored with the index; the build uses them); None: ``TileConfig()``.
        expected_frame: frame id the drives must have (None: any).
        overwrite: replace an existing file at ``path``.
        progress: optional callback(drives indexed so far).

    Returns:
        The index, for reading. A damaged bag is indexed up to the damage; ``TileIndex.bag_error``
        says what went wrong.

    Raises:
        ConfigError: ``path`` exists and not ``overwrite``.
        BagError: the bag does not exist or is not a bag.
    """
    path = Path(path)
    tile_config = tile_config or TileConfig()
    if path.exists():
        if not overwrite:
            raise ConfigError(f"{path} exists already (choose another tile index path, or overwrite)")
        path.unlink()
    path.parent.mkdir(parents=True, exist_ok=True)
    con = sqlite3.connect(str(path), isolation_level=None)
    try:
        con.execute("PRAGMA journal_mode=OFF")  # a scratch file: rebuilt, never repaired
        con.execute("PRAGMA synchronous=OFF")
        for stmt in filter(None, (s.strip() for s in _SCHEMA.split(";"))):
            con.execute(stmt)
        origin: GeoOrigin | None = None
        error = ""
        n_drives, km = 0, 0.0
        con.execute("BEGIN")
        try:
            for item in iter_fleet_bag(bag, expected_frame=expected_frame):
                if isinstance(item, Drive):
                    _add_drive(con, item, tile_config)
                    n_drives += 1
                    km += item.length_m / 1000.0
                    if n_drives % _COMMIT_EVERY == 0:
                        con.execute("COMMIT")
                        con.execute("BEGIN")
                        if progress is not None:
                            progress(n_drives)
                elif isinstance(item, Rejection):
                    con.execute(
                        "INSERT INTO rejected(drive_id, reason, detail) VALUES (?, ?, ?)",
                        (item.drive_id, item.reason, str(item)),
                    )
                else:
                    origin = item
        except BagError as err:
            if n_drives == 0 and origin is None:  # not a bag at all, or nothing intact in it
                raise
            error = str(err)
        meta = {
            "tile_size_m": tile_config.tile_size_m,
            "margin_m": tile_config.margin_m,
            "seed": tile_config.seed,
            "pivot_margin_m": tile_config.pivot_margin_m,
            "origin": asdict(origin) if origin else None,
            "bag": str(bag),
            "bag_error": error,
            "drives": n_drives,
            "drive_km": km,
        }
        con.executemany("INSERT INTO meta(key, value) VALUES (?, ?)", [(k, json.dumps(v)) for k, v in meta.items()])
        con.execute("COMMIT")
        if progress is not None:
            progress(n_drives)
    except BaseException:
        con.close()
        path.unlink(missing_ok=True)
        raise
    con.close()
    return TileIndex(path)


def _add_drive(con: sqlite3.Connection, drive: Drive, tile_config: TileConfig) -> None:
    con.execute("INSERT INTO drives(drive_id, length_m) VALUES (?, ?)", (drive.drive_id, float(drive.length_m)))
    rows = []
    for key in sorted(tiles_of_drive(drive, config=tile_config)):
        clip, s0 = clip_to_tile(drive, key, tile_config=tile_config)
        if clip is not None:
            rows.append((int(key[0]), int(key[1]), drive.drive_id, float(s0), drive_to_blob(clip)))
    con.executemany("INSERT INTO clips(tx, ty, drive_id, s0_m, blob) VALUES (?, ?, ?, ?, ?)", rows)
    xy = np.asarray(drive.xy, dtype=float).reshape(-1, 2)
    xy = resample_evenly(xy[np.isfinite(xy).all(axis=1)], POSE_STEP_M)
    con.execute("INSERT INTO poses(drive_id, xy) VALUES (?, ?)", (drive.drive_id, xy.astype("<f8").tobytes()))


class TileIndex:
    """A tile index file, read per tile (a ``hdmap_core.tiled.clips.TileSource``).

    Opened read-only, lazily in each process; pickles as its path.

    Raises:
        BagError: the file is not a tile index (on opening).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self._con: sqlite3.Connection | None = None
        try:
            meta = dict(self._query("SELECT key, value FROM meta"))
        except sqlite3.Error as err:
            raise BagError(f"{self.path}: not a tile index: {err}") from err
        self.meta = {k: json.loads(v) for k, v in meta.items()}
        m = self.meta
        self.tile_config = TileConfig(
            tile_size_m=float(m["tile_size_m"]),
            margin_m=float(m["margin_m"]),
            seed=int(m["seed"]),
            pivot_margin_m=m.get("pivot_margin_m"),
        )

    def __getstate__(self) -> dict:
        return {"path": self.path}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"])  # type: ignore[misc]

    def _query(self, sql: str, args: tuple = ()) -> list[tuple]:
        if self._con is None:
            if not Path(self.path).is_file():
                raise BagError(f"{self.path}: no such tile index")
            self._con = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, check_same_thread=False)
        return self._con.execute(sql, args).fetchall()

    @property
    def origin(self) -> GeoOrigin | None:
        o = self.meta.get("origin")
        return GeoOrigin(**o) if o else None

    @property
    def drive_count(self) -> int:
        return int(self.meta["drives"])

    @property
    def drive_km(self) -> float:
        return float(self.meta["drive_km"])

    @property
    def bag_error(self) -> str:
        return str(self.meta.get("bag_error") or "")

    def rejected(self) -> list[tuple[str, str, str]]:
        """(drive_id, reason, text) of every message the bag reader skipped, in bag order."""
        return [(r[0], r[1], r[2]) for r in self._query("SELECT drive_id, reason, detail FROM rejected ORDER BY seq")]

    def tiles(self) -> list[TileKey]:
        return [(int(x), int(y)) for x, y in self._query("SELECT DISTINCT tx, ty FROM clips ORDER BY tx, ty")]

    def clips(self, key: TileKey) -> list[tuple[Drive, float]]:
        rows = self._query(
            "SELECT s0_m, blob FROM clips WHERE tx=? AND ty=? ORDER BY drive_id", (int(key[0]), int(key[1]))
        )
        return [(blob_to_drive(blob), float(s0)) for s0, blob in rows]

    def trajectories(self) -> Iterator[np.ndarray]:
        """Each drive's (N, 2) trajectory [m, map frame, time ordered, every POSE_STEP_M], in bag
        order, one at a time (an index written before the poses were kept gives none)."""
        if self._con is None:
            self._query("SELECT 1")
        assert self._con is not None
        try:
            rows = self._con.execute("SELECT xy FROM poses ORDER BY seq")
        except sqlite3.OperationalError:
            return
        for (blob,) in rows:
            yield np.frombuffer(blob, dtype="<f8").reshape(-1, 2)

    def drive_ids(self, key: TileKey) -> list[str]:
        return [
            r[0]
            for r in self._query(
                "SELECT drive_id FROM clips WHERE tx=? AND ty=? ORDER BY drive_id", (int(key[0]), int(key[1]))
            )
        ]

    def close(self) -> None:
        if self._con is not None:
            self._con.close()
            self._con = None
