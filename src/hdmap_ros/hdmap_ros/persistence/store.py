"""SQLite persistence of the live node suite (stdlib ``sqlite3``, WAL, one transaction per update).

Two stores, one file each:

- :class:`DriveStore` (``segment_mapper``): every accepted drive, the tiles it covers (the spatial
  index: "which stored drives cover tile k" is an indexed query), whether it has been processed,
  and per tile the latest estimate (segments, version, the drive count it was made from).
  A drive is *acknowledged* once :meth:`DriveStore.add_drive` has committed it.
- :class:`MapStore` (``map_stitcher``): the latest segments of every tile as received, and the
  current map (features with their ids, topology, version).

Model objects are stored as compact ``.npz`` blobs of their arrays (plus a little JSON), not as CDR:
exact round trips, no dependency on rclpy serialization (whose buffers were seen to carry trailing
junk bytes, shared notes ros-wheels.md), and readable without ROS.

Crash safety: every method that changes state is one transaction; SIGKILL at any point leaves the
file at the last committed state (WAL journal). ``synchronous=FULL`` makes commits durable across
power loss too, at the cost of one fsync per update.
"""

from __future__ import annotations

import io
import json
import sqlite3
import threading
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from hdmap_core.live.tiles import TileKey
from hdmap_core.model import Detection, Drive, FeatureType, HDMap, MapFeature, TopologyNode
from hdmap_core.segment_columns import SegmentColumns, columns_to_segments, segment_columns, split_by, take_segments
from hdmap_core.steps import Segment, StepObservations

__all__ = [
    "drive_to_blob",
    "read_drives",
    "blob_to_drive",
    "segments_to_blob",
    "blob_to_segments",
    "columns_to_blob",
    "blob_to_columns",
    "map_to_blob",
    "blob_to_map",
    "observations_to_blob",
    "blob_to_observations",
    "DriveStore",
    "MapStore",
    "TileEstimate",
]


# --- blobs -----------------------------------------------------------------------------------------


def _pack(arrays: dict[str, np.ndarray], meta: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8), **arrays)
    return buf.getvalue()


def _unpack(blob: bytes) -> tuple[dict[str, np.ndarray], dict]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes().decode())
    return arrays, meta


def drive_to_blob(drive: Drive) -> bytes:
    """Serialize a drive exactly (float64 coordinates, int64 stamps)."""
    dets = drive.detections
    pts = [np.asarray(d.points, dtype=np.float64).reshape(-1, 2) for d in dets]
    return _pack(
        {
            "xy": np.asarray(drive.xy, dtype=np.float64).reshape(-1, 2),
            "yaw": np.asarray(drive.yaw, dtype=np.float64),
            "stamps": np.asarray(drive.stamps_ns, dtype=np.int64),
            "det_types": np.array([int(d.type) for d in dets], dtype=np.int64),
            "det_lens": np.array([len(p) for p in pts], dtype=np.int64),
            "det_pts": np.vstack(pts) if pts else np.zeros((0, 2)),
        },
        {"drive_id": drive.drive_id, "vehicle_id": drive.vehicle_id, "frame_id": drive.frame_id},
    )


def blob_to_drive(blob: bytes) -> Drive:
    a, m = _unpack(blob)
    dets = tuple(
        Detection(type=FeatureType(int(t)), points=p)
        for t, p in zip(a["det_types"], split_by(a["det_pts"], a["det_lens"]))
    )
    return Drive(
        drive_id=m["drive_id"],
        xy=a["xy"],
        yaw=a["yaw"],
        stamps_ns=a["stamps"],
        detections=dets,
        vehicle_id=m["vehicle_id"],
        frame_id=m["frame_id"],
    )


def segments_to_blob(segments: Sequence[Segment]) -> bytes:
    """Serialize segments (every StepResult field) exactly."""
    return columns_to_blob(segment_columns(segments))


def columns_to_blob(c: SegmentColumns) -> bytes:
    """Segments in columns -> the blob :func:`segments_to_blob` makes of them."""
    return _pack(
        {
            "nsteps": c.nsteps,
            "index": c.index,
            "s_m": c.s_m,
            "midpoint": c.midpoint,
            "pose": c.pose,
            "heading": c.heading,
            "width_m": c.width_m,
            "valid": c.valid,
            "processed_before": c.processed_before,
            "k": c.k,
            "lateral_m": c.lateral_m,
            "types": c.types,
            "counts": c.counts,
            "std_m": c.std_m,
            "judged": c.judged,
            "n_empty": c.n_empty,
            "empty_m": c.empty_m,
        },
        {"pivots": list(c.pivots), "drive_ids": [list(ids) for ids in c.step_drive_ids()]},
    )


def blob_to_columns(blob: bytes) -> SegmentColumns:
    """A blob of :func:`segments_to_blob` -> its segments in columns."""
    a, m = _unpack(blob)
    n = len(a["k"])
    names: dict[str, int] = {}
    index = [names.setdefault(d, len(names)) for ids in m["drive_ids"] for d in ids]
    return SegmentColumns(
        pivots=tuple(m["pivots"]),
        nsteps=a["nsteps"],
        index=a["index"],
        s_m=a["s_m"],
        midpoint=a["midpoint"].reshape(-1, 2),
        pose=a["pose"] if "pose" in a else np.full((n, 2), np.nan),  # blobs written before poses
        heading=a["heading"],
        width_m=a["width_m"],
        valid=a["valid"],
        processed_before=a["processed_before"],
        judged=a["judged"] if "judged" in a else np.zeros(n, dtype=bool),  # blobs written before evidence
        k=a["k"],
        lateral_m=a["lateral_m"],
        types=a["types"],
        counts=a["counts"],
        std_m=a["std_m"],
        n_empty=a["n_empty"] if "n_empty" in a else np.zeros(n, dtype=np.int64),
        empty_m=a["empty_m"].reshape(-1, 2) if "empty_m" in a else np.zeros((0, 2)),
        drive_names=tuple(names),
        n_drives=np.array([len(ids) for ids in m["drive_ids"]], dtype=np.int64),
        drive_index=np.array(index, dtype=np.int64),
    )


def blob_to_segments(blob: bytes) -> list[Segment]:
    return columns_to_segments(blob_to_columns(blob))


def observations_to_blob(observations: Sequence[StepObservations]) -> bytes:
    """Serialize step observations (every field) exactly; drive ids as indices into one id table."""
    obs = list(observations)
    ids: dict[str, int] = {}
    for ob in obs:
        for d in ob.drive_ids:
            ids.setdefault(d, len(ids))

    def cat(attr: str, dtype) -> np.ndarray:
        parts = [np.asarray(getattr(ob, attr), dtype=dtype).reshape(-1) for ob in obs]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=dtype)

    return _pack(
        {
            "index": np.array([ob.index for ob in obs], dtype=np.int64),
            "midpoint": np.array([np.asarray(ob.midpoint, dtype=np.float64).reshape(-1)[:2] for ob in obs]).reshape(
                -1, 2
            ),
            "heading": np.array([ob.heading for ob in obs], dtype=np.float64),
            "k": np.array([len(ob.drive_ids) for ob in obs], dtype=np.int64),
            "k_off": np.array([np.asarray(ob.offsets_m).size for ob in obs], dtype=np.int64),
            "drive": np.array([ids[d] for ob in obs for d in ob.drive_ids], dtype=np.int64),
            "drive_s_m": cat("drive_s_m", np.float64),
            "lateral_m": cat("lateral_m", np.float64),
            "types": cat("types", np.int64),
            "cluster": cat("cluster", np.int64),
            "offsets_m": cat("offsets_m", np.float64),
        },
        {"pivots": [ob.pivot_id for ob in obs], "drive_ids": list(ids)},
    )


def blob_to_observations(blob: bytes) -> list[StepObservations]:
    a, m = _unpack(blob)
    table = np.array(m["drive_ids"], dtype=object)
    k = a["k"]
    drv, ds, lat, typ, clu = (split_by(a[n], k) for n in ("drive", "drive_s_m", "lateral_m", "types", "cluster"))
    off = split_by(a["offsets_m"], a["k_off"])
    return [
        StepObservations(
            pivot_id=m["pivots"][i],
            index=int(a["index"][i]),
            midpoint=a["midpoint"][i],
            heading=float(a["heading"][i]),
            drive_ids=tuple(table[drv[i]].tolist()),
            drive_s_m=ds[i],
            lateral_m=lat[i],
            types=typ[i],
            cluster=clu[i],
            offsets_m=off[i],
        )
        for i in range(len(k))
    ]


def _ids(lists: Iterable[Sequence[int]]) -> tuple[np.ndarray, np.ndarray]:
    lists = [list(map(int, x)) for x in lists]
    flat = [i for x in lists for i in x]
    return np.array(flat, dtype=np.uint64), np.array([len(x) for x in lists], dtype=np.int64)


def map_to_blob(hdmap: HDMap) -> bytes:
    """Serialize a map (features, topology, ids, version) exactly; ``extra`` is kept if JSON-able."""
    fs, ts = hdmap.features, hdmap.topology
    pred, pred_n = _ids(f.predecessors for f in fs)
    succ, succ_n = _ids(f.successors for f in fs)
    tsucc, tsucc_n = _ids(t.successors for t in ts)
    tfeat, tfeat_n = _ids(t.features for t in ts)
    pts = [np.asarray(f.points, dtype=np.float64).reshape(-1, 2) for f in fs]
    try:
        extra = json.loads(json.dumps(hdmap.extra))
    except (TypeError, ValueError):
        extra = {}
    return _pack(
        {
            "f_id": np.array([f.id for f in fs], dtype=np.uint64),
            "f_type": np.array([int(f.type) for f in fs], dtype=np.int64),
            "f_n": np.array([len(p) for p in pts], dtype=np.int64),
            "f_pts": np.vstack(pts) if pts else np.zeros((0, 2)),
            "f_count": np.concatenate([np.asarray(f.drive_count, dtype=np.int64) for f in fs])
            if fs
            else np.zeros(0, np.int64),
            "f_std": np.concatenate([np.asarray(f.lateral_std, dtype=np.float64) for f in fs]) if fs else np.zeros(0),
            "f_pred": pred,
            "f_pred_n": pred_n,
            "f_succ": succ,
            "f_succ_n": succ_n,
            "t_id": np.array([t.id for t in ts], dtype=np.uint64),
            "t_pos": np.array([np.asarray(t.position, dtype=np.float64) for t in ts]).reshape(-1, 2),
            "t_heading": np.array([t.heading for t in ts], dtype=np.float64),
            "t_width": np.array([t.width for t in ts], dtype=np.float64),
            "t_succ": tsucc,
            "t_succ_n": tsucc_n,
            "t_feat": tfeat,
            "t_feat_n": tfeat_n,
        },
        {
            "drive_ids": list(hdmap.drive_ids),
            "version": int(hdmap.version),
            "frame_id": hdmap.frame_id,
            "stamp_ns": int(hdmap.stamp_ns),
            "extra": extra,
        },
    )


def blob_to_map(blob: bytes) -> HDMap:
    a, m = _unpack(blob)
    n = a["f_n"]
    pts, cnt, std = split_by(a["f_pts"], n), split_by(a["f_count"], n), split_by(a["f_std"], n)
    pred, succ = split_by(a["f_pred"], a["f_pred_n"]), split_by(a["f_succ"], a["f_succ_n"])
    features = tuple(
        MapFeature(
            id=int(a["f_id"][i]),
            type=FeatureType(int(a["f_type"][i])),
            points=pts[i],
            drive_count=cnt[i],
            lateral_std=std[i],
            predecessors=tuple(int(x) for x in pred[i]),
            successors=tuple(int(x) for x in succ[i]),
        )
        for i in range(len(n))
    )
    tsucc, tfeat = split_by(a["t_succ"], a["t_succ_n"]), split_by(a["t_feat"], a["t_feat_n"])
    topology = tuple(
        TopologyNode(
            id=int(a["t_id"][i]),
            position=a["t_pos"][i],
            heading=float(a["t_heading"][i]),
            width=float(a["t_width"][i]),
            successors=tuple(int(x) for x in tsucc[i]),
            features=tuple(int(x) for x in tfeat[i]),
        )
        for i in range(len(a["t_id"]))
    )
    return HDMap(
        features=features,
        topology=topology,
        drive_ids=tuple(m["drive_ids"]),
        version=m["version"],
        frame_id=m["frame_id"],
        stamp_ns=m["stamp_ns"],
        extra=m.get("extra", {}),
    )


# --- stores ----------------------------------------------------------------------------------------


def _connect(path: str | Path) -> sqlite3.Connection:
    if str(path) != ":memory:":
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    # isolation_level=None: we open transactions ourselves (BEGIN IMMEDIATE), one per update.
    con = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False)
    con.execute("PRAGMA journal_mode=WAL")  # readers never block the writer; crash leaves last commit
    con.execute("PRAGMA synchronous=FULL")  # a committed (acknowledged) drive survives power loss too
    con.execute("PRAGMA foreign_keys=ON")
    return con


class _Store:
    _SCHEMA: str = ""

    def __init__(self, path: str | Path) -> None:
        self.path = str(path)
        self._lock = threading.RLock()  # the executor may call from several threads
        self._con = _connect(path)
        with self._tx() as con:
            for stmt in filter(None, (s.strip() for s in self._SCHEMA.split(";"))):
                con.execute(stmt)

    def _tx(self):
        store = self

        class _Tx:
            def __enter__(self_inner):
                store._lock.acquire()
                store._con.execute("BEGIN IMMEDIATE")
                return store._con

            def __exit__(self_inner, exc_type, exc, tb):
                try:
                    store._con.execute("ROLLBACK" if exc_type else "COMMIT")
                finally:
                    store._lock.release()
                return False

        return _Tx()

    def _query(self, sql: str, args: Sequence = ()) -> list[tuple]:
        with self._lock:
            return self._con.execute(sql, args).fetchall()

    def get_meta(self, key: str, default: str | None = None) -> str | None:
        rows = self._query("SELECT value FROM meta WHERE key=?", (key,))
        return rows[0][0] if rows else default

    def set_meta(self, key: str, value: str) -> None:
        with self._tx() as con:
            con.execute("INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)", (key, value))

    def version_total(self) -> int:
        """Sum of all tile versions: equal in mapper and stitcher when the stitcher has every estimate."""
        return int(self._query("SELECT COALESCE(SUM(version), 0) FROM tiles")[0][0])

    def tile_version(self, key: TileKey) -> int:
        """The stored version of a tile's estimate (0: none)."""
        rows = self._query("SELECT version FROM tiles WHERE tx=? AND ty=?", key)
        return int(rows[0][0]) if rows else 0

    def close(self) -> None:
        with self._lock:
            self._con.close()


class TileEstimate:
    """The stored estimate of one tile."""

    __slots__ = ("key", "version", "drive_ids", "segments_blob", "model_sig")

    def __init__(
        self, key: TileKey, version: int, drive_ids: Sequence[str], segments_blob: bytes | None, model_sig: str = ""
    ) -> None:
        self.key = key
        self.version = version
        self.drive_ids = tuple(drive_ids)
        self.segments_blob = segments_blob
        self.model_sig = model_sig  # the fleet offset model it was made with ('' = the tile's own adjustment)

    @property
    def drive_count(self) -> int:
        """Number of drives the estimate was made from."""
        return len(self.drive_ids)

    def segments(self) -> list[Segment]:
        return blob_to_segments(self.segments_blob) if self.segments_blob else []


class DriveStore(_Store):
    """segment_mapper's state: drives, their tiles, tile estimates."""

    _SCHEMA = """
    CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    CREATE TABLE IF NOT EXISTS drives (
        seq INTEGER PRIMARY KEY AUTOINCREMENT,
        drive_id TEXT NOT NULL UNIQUE,
        blob BLOB NOT NULL,
        processed INTEGER NOT NULL DEFAULT 0
    );
    CREATE TABLE IF NOT EXISTS drive_tiles (
        tx INTEGER NOT NULL, ty INTEGER NOT NULL, drive_id TEXT NOT NULL,
        PRIMARY KEY (tx, ty, drive_id)
    );
    CREATE TABLE IF NOT EXISTS tiles (
        tx INTEGER NOT NULL, ty INTEGER NOT NULL,
        version INTEGER NOT NULL,
        drive_count INTEGER NOT NULL,
        drive_ids TEXT NOT NULL,
        segments BLOB,
        model_sig TEXT NOT NULL DEFAULT '',
        PRIMARY KEY (tx, ty)
    );
    CREATE TABLE IF NOT EXISTS tile_obs (
        tx INTEGER NOT NULL, ty INTEGER NOT NULL,
        drive_count INTEGER NOT NULL,
        drive_ids TEXT NOT NULL,
        blob BLOB NOT NULL,
        PRIMARY KEY (tx, ty)
    )
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        cols = {r[1] for r in self._query("PRAGMA table_info(tiles)")}
        if "model_sig" not in cols:  # a store of before the fleet-wide offset model
            with self._tx() as con:
                con.execute("ALTER TABLE tiles ADD COLUMN model_sig TEXT NOT NULL DEFAULT ''")

    def add_drive(self, drive: Drive, tiles: Iterable[TileKey]) -> bool:
        """Store a drive and its tiles in one transaction; False (nothing stored) for a known id.

        Once this returns True the drive is acknowledged: it survives any crash.
        """
        blob = drive_to_blob(drive)
        with self._tx() as con:
            try:
                con.execute("INSERT INTO drives(drive_id, blob) VALUES (?, ?)", (drive.drive_id, blob))
            except sqlite3.IntegrityError:
                return False
            con.executemany(
                "INSERT OR IGNORE INTO drive_tiles(tx, ty, drive_id) VALUES (?, ?, ?)",
                [(int(x), int(y), drive.drive_id) for x, y in tiles],
            )
        return True

    def drives_after(self, seq: int) -> Iterable[tuple[int, str, bytes]]:
        """(seq, drive_id, blob) of the drives stored after arrival number ``seq``, in arrival order."""
        return self._query("SELECT seq, drive_id, blob FROM drives WHERE seq > ? ORDER BY seq", (int(seq),))

    def last_seq(self) -> int:
        """The arrival number of the latest stored drive (0: none)."""
        return int(self._query("SELECT COALESCE(MAX(seq), 0) FROM drives")[0][0])

    def remove_drives(self, drive_ids: Iterable[str]) -> set[TileKey]:
        """Forget drives (e.g. ones that fail bounds they were not checked against when stored),
        in one transaction; returns the tiles they covered.

        The estimates and observations of those tiles are marked stale (made from no drive), so
        the mapper makes them again from the drives left; a tile no drive covers any more keeps its
        estimate until :meth:`put_tile` replaces it (with nothing).
        """
        ids = list(drive_ids)
        tiles = self.tiles_of(ids)
        with self._tx() as con:
            con.executemany("DELETE FROM drives WHERE drive_id=?", [(d,) for d in ids])
            con.executemany("DELETE FROM drive_tiles WHERE drive_id=?", [(d,) for d in ids])
            for key in tiles:
                con.execute("UPDATE tiles SET drive_count=0, drive_ids='[]' WHERE tx=? AND ty=?", key)
                con.execute("UPDATE tile_obs SET drive_count=0, drive_ids='[]' WHERE tx=? AND ty=?", key)
        return tiles

    def has_drive(self, drive_id: str) -> bool:
        return bool(self._query("SELECT 1 FROM drives WHERE drive_id=?", (drive_id,)))

    def drive_count(self) -> int:
        return int(self._query("SELECT COUNT(*) FROM drives")[0][0])

    def drive_ids(self) -> list[str]:
        """All stored drive ids in arrival order."""
        return [r[0] for r in self._query("SELECT drive_id FROM drives ORDER BY seq")]

    def pending(self) -> list[str]:
        """Acknowledged but not yet processed drive ids, in arrival order."""
        return [r[0] for r in self._query("SELECT drive_id FROM drives WHERE processed=0 ORDER BY seq")]

    def mark_processed(self, drive_ids: Iterable[str]) -> None:
        with self._tx() as con:
            con.executemany("UPDATE drives SET processed=1 WHERE drive_id=?", [(d,) for d in drive_ids])

    def tiles_of(self, drive_ids: Iterable[str]) -> set[TileKey]:
        ids = list(drive_ids)
        out: set[TileKey] = set()
        for i in range(0, len(ids), 500):
            chunk = ids[i : i + 500]
            q = ",".join("?" * len(chunk))
            out.update((x, y) for x, y in self._query(f"SELECT tx, ty FROM drive_tiles WHERE drive_id IN ({q})", chunk))
        return out

    def tiles_per_drive(self, drive_ids: Iterable[str]) -> dict[str, list[TileKey]]:
        """The tiles each of these drives covers (every id a key, [] when unknown)."""
        ids = list(drive_ids)
        out: dict[str, list[TileKey]] = {d: [] for d in ids}
        for i in range(0, len(ids), 500):
            chunk = ids[i : i + 500]
            q = ",".join("?" * len(chunk))
            for x, y, d in self._query(f"SELECT tx, ty, drive_id FROM drive_tiles WHERE drive_id IN ({q})", chunk):
                out[d].append((x, y))
        return out

    def tile_drive_count(self, key: TileKey) -> int:
        return int(self._query("SELECT COUNT(*) FROM drive_tiles WHERE tx=? AND ty=?", key)[0][0])

    def drives_covering(self, key: TileKey) -> list[Drive]:
        """The stored drives covering a tile, ordered by drive id."""
        rows = self._query(
            "SELECT d.blob FROM drive_tiles t JOIN drives d ON d.drive_id = t.drive_id "
            "WHERE t.tx=? AND t.ty=? ORDER BY d.drive_id",
            key,
        )
        return [blob_to_drive(r[0]) for r in rows]

    def tile(self, key: TileKey) -> TileEstimate | None:
        rows = self._query("SELECT version, drive_ids, segments, model_sig FROM tiles WHERE tx=? AND ty=?", key)
        return TileEstimate(key, rows[0][0], json.loads(rows[0][1]), rows[0][2], rows[0][3]) if rows else None

    def tiles(self) -> list[TileEstimate]:
        rows = self._query("SELECT tx, ty, version, drive_ids, segments, model_sig FROM tiles ORDER BY tx, ty")
        return [TileEstimate((r[0], r[1]), r[2], json.loads(r[3]), r[4], r[5]) for r in rows]

    def tile_drive_sets(self) -> dict[TileKey, list[str]]:
        """Every tile with the stored drives covering it."""
        out: dict[TileKey, list[str]] = {}
        for x, y, d in self._query("SELECT tx, ty, drive_id FROM drive_tiles ORDER BY tx, ty, drive_id"):
            out.setdefault((x, y), []).append(d)
        return out

    def estimates(self) -> list[tuple[TileKey, list[str], str]]:
        """(tile, the drives its estimate was made from, the model signature it was made with) per tile."""
        rows = self._query("SELECT tx, ty, drive_ids, model_sig FROM tiles ORDER BY tx, ty")
        return [((r[0], r[1]), json.loads(r[2]), r[3]) for r in rows]

    def drives(self, drive_ids: Iterable[str]) -> list[Drive]:
        """The stored drives of these ids (unknown ids skipped), ordered by drive id."""
        ids = sorted(set(drive_ids))
        out: list[Drive] = []
        for i in range(0, len(ids), 500):
            chunk = ids[i : i + 500]
            q = ",".join("?" * len(chunk))
            rows = self._query(f"SELECT blob FROM drives WHERE drive_id IN ({q}) ORDER BY drive_id", chunk)
            out.extend(blob_to_drive(r[0]) for r in rows)
        return out

    def tiles_signature(self) -> str:
        """Every (tile, version), as :meth:`MapStore.tiles_signature` names them."""
        rows = self._query("SELECT tx, ty, version FROM tiles ORDER BY tx, ty")
        return ";".join(f"{x},{y}:{v}" for x, y, v in rows)

    def stale_tiles(self) -> list[TileKey]:
        """Tiles whose estimate was made from fewer drives than now cover them (or never made)."""
        rows = self._query(
            "SELECT c.tx, c.ty FROM (SELECT tx, ty, COUNT(*) AS n FROM drive_tiles GROUP BY tx, ty) c "
            "LEFT JOIN tiles t ON t.tx = c.tx AND t.ty = c.ty "
            "WHERE t.drive_count IS NULL OR t.drive_count < c.n ORDER BY c.tx, c.ty"
        )
        return [(r[0], r[1]) for r in rows]

    def put_tile(
        self,
        key: TileKey,
        segments: Sequence[Segment],
        drive_ids: Sequence[str],
        *,
        model_sig: str = "",
        observations: Sequence[StepObservations] | None = None,
    ) -> TileEstimate:
        """Replace a tile's estimate (made from ``drive_ids``) in one transaction; returns it with its new version.

        Args:
            model_sig: the signature of the fleet offset model the estimate was made with ('' = the
                tile's own adjustment).
            observations: when given, the tile's observations (made from the same drives) are
                replaced in the same transaction.
        """
        with self._tx() as con:
            est = self._put_tile(con, key, segments, drive_ids, model_sig)
            if observations is not None:
                self._put_obs(con, key, observations, est.drive_ids)
        return est

    def put_tiles(
        self,
        tiles: Sequence[tuple[TileKey, Sequence[Segment], Sequence[str]]],
        *,
        model_sig: str = "",
        columns: SegmentColumns | None = None,
    ) -> list[TileEstimate]:
        """Replace the estimates of many tiles (key, segments, drive ids) in one transaction (the
        live settle's region: all of them or none after a crash, one commit instead of one per
        tile); returns them with their new versions, in order. ``columns``: the tiles' segments
        in columns, in order (``segment_columns``), when at hand: the blobs are cut from them."""
        if columns is None:
            blobs = [segments_to_blob(segs) for _, segs, _ in tiles]
        else:
            ends = np.cumsum([0] + [len(segs) for _, segs, _ in tiles])
            if int(ends[-1]) != len(columns.pivots):
                raise ValueError(
                    f"put_tiles: {len(columns.pivots)} segments in the columns, {int(ends[-1])} in the tiles"
                )
            blobs = [columns_to_blob(take_segments(columns, int(a), int(b))) for a, b in zip(ends[:-1], ends[1:])]
        with self._tx() as con:
            return [
                self._put_tile(con, key, blob, ids, model_sig) for (key, _, ids), blob in zip(tiles, blobs, strict=True)
            ]

    @staticmethod
    def _put_tile(
        con, key: TileKey, segments: Sequence[Segment] | bytes, drive_ids: Sequence[str], model_sig: str
    ) -> TileEstimate:
        blob = segments if isinstance(segments, bytes) else segments_to_blob(segments)
        ids = list(drive_ids)
        row = con.execute("SELECT version FROM tiles WHERE tx=? AND ty=?", key).fetchone()
        version = (row[0] if row else 0) + 1
        con.execute(
            "INSERT OR REPLACE INTO tiles(tx, ty, version, drive_count, drive_ids, segments, model_sig) "
            "VALUES (?, ?, ?, ?, ?, ?, ?)",
            (key[0], key[1], version, len(ids), json.dumps(ids), blob, model_sig),
        )
        return TileEstimate(key, version, ids, blob, model_sig)

    # --- the fleet-wide offset model and the observations it is estimated from ----------------------

    @staticmethod
    def _put_obs(con, key: TileKey, observations: Sequence[StepObservations], drive_ids: Sequence[str]) -> None:
        ids = list(drive_ids)
        con.execute(
            "INSERT OR REPLACE INTO tile_obs(tx, ty, drive_count, drive_ids, blob) VALUES (?, ?, ?, ?, ?)",
            (key[0], key[1], len(ids), json.dumps(ids), observations_to_blob(observations)),
        )

    def put_observations(
        self, key: TileKey, observations: Sequence[StepObservations], drive_ids: Sequence[str]
    ) -> None:
        """Replace a tile's observations (made from ``drive_ids``) in one transaction."""
        with self._tx() as con:
            self._put_obs(con, key, observations, drive_ids)

    def stale_observations(self) -> list[TileKey]:
        """Tiles whose observations were made from fewer drives than now cover them (or never made)."""
        rows = self._query(
            "SELECT c.tx, c.ty FROM (SELECT tx, ty, COUNT(*) AS n FROM drive_tiles GROUP BY tx, ty) c "
            "LEFT JOIN tile_obs o ON o.tx = c.tx AND o.ty = c.ty "
            "WHERE o.drive_count IS NULL OR o.drive_count < c.n ORDER BY c.tx, c.ty"
        )
        return [(r[0], r[1]) for r in rows]

    def observation_sets(self) -> list[tuple[TileKey, list[str]]]:
        """(tile, the drive ids its observations were made from), ordered by tile."""
        rows = self._query("SELECT tx, ty, drive_ids FROM tile_obs ORDER BY tx, ty")
        return [((r[0], r[1]), json.loads(r[2])) for r in rows]

    def observations(self) -> list[StepObservations]:
        """The observations of every tile, ordered by tile (then as stored)."""
        out: list[StepObservations] = []
        for (blob,) in self._query("SELECT blob FROM tile_obs ORDER BY tx, ty"):
            out.extend(blob_to_observations(blob))
        return out

    def put_model(self, model: dict, sig: str) -> None:
        """Store the fleet offset model (``OffsetModel.to_dict()``) made from the observations ``sig`` names."""
        with self._tx() as con:
            con.executemany(
                "INSERT OR REPLACE INTO meta(key, value) VALUES (?, ?)",
                [("offset_model", json.dumps(model)), ("offset_model_sig", sig)],
            )

    def model(self) -> tuple[dict | None, str]:
        """(the stored fleet offset model dict or None, its signature or '')."""
        text = self.get_meta("offset_model")
        return (json.loads(text) if text else None), self.get_meta("offset_model_sig", "") or ""

    def tiles_off_model(self, sig: str) -> list[TileKey]:
        """Tiles made from all their drives but not with the model ``sig`` names."""
        rows = self._query(
            "SELECT t.tx, t.ty FROM tiles t JOIN (SELECT tx, ty, COUNT(*) AS n FROM drive_tiles GROUP BY tx, ty) c "
            "ON t.tx = c.tx AND t.ty = c.ty WHERE t.drive_count >= c.n AND t.model_sig != ? ORDER BY t.tx, t.ty",
            (sig,),
        )
        return [(r[0], r[1]) for r in rows]


class MapStore(_Store):
    """map_stitcher's state: the latest segments per tile and the current map."""

    _SCHEMA = """
    CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
    CREATE TABLE IF NOT EXISTS tiles (
        tx INTEGER NOT NULL, ty INTEGER NOT NULL,
        version INTEGER NOT NULL,
        drive_ids TEXT NOT NULL,
        segments BLOB NOT NULL,
        PRIMARY KEY (tx, ty)
    );
    CREATE TABLE IF NOT EXISTS map (
        one INTEGER PRIMARY KEY CHECK (one = 1),
        version INTEGER NOT NULL,
        tiles_sig TEXT NOT NULL,
        blob BLOB NOT NULL
    );
    CREATE TABLE IF NOT EXISTS changes (
        id INTEGER PRIMARY KEY,
        time_ns INTEGER NOT NULL,
        doc TEXT NOT NULL
    )
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        cols = {r[1] for r in self._query("PRAGMA table_info(tiles)")}
        with self._tx() as con:  # a store of before the per-drive tile counts
            if "drive_tile_counts" not in cols:
                con.execute("ALTER TABLE tiles ADD COLUMN drive_tile_counts TEXT NOT NULL DEFAULT '[]'")
            if "final" not in cols:
                con.execute("ALTER TABLE tiles ADD COLUMN final INTEGER NOT NULL DEFAULT 1")

    def put_tile(
        self,
        key: TileKey,
        version: int,
        segments_blob: bytes,
        drive_ids: Sequence[str],
        drive_tile_counts: Sequence[int] = (),
        final: bool = True,
    ) -> bool:
        """Store a tile's segments unless a same or newer version is stored; True when stored.
        ``drive_tile_counts``: per drive id, the tiles that drive covers (empty: unknown); ``final``:
        made as the settled map makes it."""
        return self.put_tiles([(key, version, segments_blob, drive_ids, drive_tile_counts, final)])[0]

    def put_tiles(self, tiles: Sequence[tuple[TileKey, int, bytes, Sequence[str], Sequence[int], bool]]) -> list[bool]:
        """:meth:`put_tile` of each (key, version, segments blob, drive ids, drive tile counts,
        final), in one transaction (one commit for a batch of estimates); per tile, True when stored."""
        out = []
        with self._tx() as con:
            for key, version, blob, drive_ids, counts, final in tiles:
                row = con.execute("SELECT version FROM tiles WHERE tx=? AND ty=?", key).fetchone()
                if row and row[0] >= version:
                    out.append(False)
                    continue
                con.execute(
                    "INSERT OR REPLACE INTO tiles(tx, ty, version, drive_ids, segments, drive_tile_counts, final) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?)",
                    (
                        key[0],
                        key[1],
                        int(version),
                        json.dumps(list(drive_ids)),
                        blob,
                        json.dumps([int(n) for n in counts]),
                        int(bool(final)),
                    ),
                )
                out.append(True)
        return out

    def tile_progress(self) -> dict[TileKey, tuple[list[int], bool]]:
        """Per tile, the tile counts of its estimate's drives and whether it is final (as
        :meth:`put_tile` got them)."""
        rows = self._query("SELECT tx, ty, drive_tile_counts, final FROM tiles ORDER BY tx, ty")
        return {(r[0], r[1]): (json.loads(r[2]), bool(r[3])) for r in rows}

    def tiles(self) -> list[tuple[TileKey, int, list[str], bytes]]:
        """(key, version, drive_ids, segments blob) of every tile, ordered by key."""
        rows = self._query("SELECT tx, ty, version, drive_ids, segments FROM tiles ORDER BY tx, ty")
        return [((r[0], r[1]), r[2], json.loads(r[3]), r[4]) for r in rows]

    def tiles_signature(self) -> str:
        """A string naming every (tile, version): equal signatures mean equal inputs to the map."""
        rows = self._query("SELECT tx, ty, version FROM tiles ORDER BY tx, ty")
        return ";".join(f"{x},{y}:{v}" for x, y, v in rows)

    def put_map(self, hdmap: HDMap, tiles_sig: str) -> None:
        with self._tx() as con:
            con.execute(
                "INSERT OR REPLACE INTO map(one, version, tiles_sig, blob) VALUES (1, ?, ?, ?)",
                (int(hdmap.version), tiles_sig, map_to_blob(hdmap)),
            )

    def map(self) -> tuple[HDMap | None, str]:
        """The stored map and the tiles signature it was made from ((None, "") when none)."""
        rows = self._query("SELECT blob, tiles_sig FROM map WHERE one=1")
        return (blob_to_map(rows[0][0]), rows[0][1]) if rows else (None, "")

    def put_followed(self, hdmap: HDMap, tiles_sig: str, changes: Sequence[tuple[int, int, str]]) -> None:
        """The map with the road changes followed and the new changes of the history
        ``(id, time_ns, JSON document)``, in one transaction (``tiles_sig``: the tiles it was made
        from, also stored as the followed signature in meta)."""
        with self._tx() as con:
            con.execute(
                "INSERT OR REPLACE INTO map(one, version, tiles_sig, blob) VALUES (1, ?, ?, ?)",
                (int(hdmap.version), tiles_sig, map_to_blob(hdmap)),
            )
            con.executemany(
                "INSERT OR IGNORE INTO changes(id, time_ns, doc) VALUES (?, ?, ?)",
                [(int(i), int(t), doc) for i, t, doc in changes],
            )
            con.execute("INSERT OR REPLACE INTO meta(key, value) VALUES ('followed_sig', ?)", (tiles_sig,))

    def changes(self) -> list[str]:
        """The history of road changes (JSON documents), in time order."""
        return [r[0] for r in self._query("SELECT doc FROM changes ORDER BY time_ns, id")]


def read_drives(path: str | Path) -> list[Drive]:
    """Every drive of a ``DriveStore`` (the mapper's), read-only (another process may write it;
    WAL readers never block it); [] when there is no such store."""
    if str(path) == ":memory:" or not Path(path).exists():
        return []
    con = sqlite3.connect(f"file:{Path(path).resolve()}?mode=ro", uri=True, check_same_thread=False)
    try:
        rows = con.execute("SELECT blob FROM drives ORDER BY drive_id").fetchall()
    except sqlite3.OperationalError:
        return []
    finally:
        con.close()
    return [blob_to_drive(r[0]) for r in rows]
