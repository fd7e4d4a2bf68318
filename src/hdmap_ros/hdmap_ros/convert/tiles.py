"""Pure conversions: tile estimates (segments of hdmap_core.steps) <-> hdmap_msgs/TileSegments,
and many of them <-> one hdmap_msgs/TileSegmentsBatch (their segments in columns,
``hdmap_core.segment_columns``).

Works with rosbags typestore classes (tests, bags) and rclpy classes (nodes) alike: the classes come
from a :class:`TileTypes` namespace; primitive arrays are written as numpy (rosbags) or
``array.array`` (rclpy) and read from either.
"""

from __future__ import annotations

import array
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdmap_core.live.tiles import TileKey
from hdmap_core.segment_columns import SegmentColumns, columns_to_segments, segment_columns, take_segments
from hdmap_core.steps import Segment, StepResult

__all__ = [
    "TileTypes",
    "rclpy_tile_types",
    "rosbags_tile_types",
    "tile_to_msg",
    "msg_to_tile",
    "TileMessage",
    "tiles_to_batch",
    "batch_to_tiles",
    "TileBatchEntry",
]


@dataclass(frozen=True)
class TileTypes:
    TileSegments: Any
    Segment: Any
    SegmentStep: Any
    Point: Any
    Header: Any
    Time: Any
    numpy_arrays: bool
    TileSegmentsBatch: Any = None


def rclpy_tile_types() -> TileTypes:
    from builtin_interfaces.msg import Time  # noqa: PLC0415
    from geometry_msgs.msg import Point  # noqa: PLC0415
    from std_msgs.msg import Header  # noqa: PLC0415

    from hdmap_msgs.msg import Segment as SegmentMsg  # noqa: PLC0415
    from hdmap_msgs.msg import SegmentStep, TileSegments, TileSegmentsBatch  # noqa: PLC0415

    return TileTypes(
        TileSegments,
        SegmentMsg,
        SegmentStep,
        Point,
        Header,
        Time,
        numpy_arrays=False,
        TileSegmentsBatch=TileSegmentsBatch,
    )


def rosbags_tile_types(typestore: Any = None) -> TileTypes:
    if typestore is None:
        from hdmap_ros.io.msgdefs import default_typestore  # noqa: PLC0415

        typestore = default_typestore()
    t = typestore.types
    return TileTypes(
        t["hdmap_msgs/msg/TileSegments"],
        t["hdmap_msgs/msg/Segment"],
        t["hdmap_msgs/msg/SegmentStep"],
        t["geometry_msgs/msg/Point"],
        t["std_msgs/msg/Header"],
        t["builtin_interfaces/msg/Time"],
        numpy_arrays=True,
        TileSegmentsBatch=t["hdmap_msgs/msg/TileSegmentsBatch"],
    )


_ARRAY_CODES = {np.float64: "d", np.uint8: "B", np.uint32: "I", np.int64: "q", np.uint64: "Q"}


def _prim(types: TileTypes, values: Any, dtype) -> Any:
    arr = np.ascontiguousarray(np.asarray(values, dtype=dtype).reshape(-1))
    if types.numpy_arrays:
        return arr
    return array.array(_ARRAY_CODES[dtype], arr.tobytes())


def _bools(types: TileTypes, values: Any) -> Any:
    arr = np.asarray(values, dtype=bool).reshape(-1)
    return arr if types.numpy_arrays else arr.tolist()


def _step_to_msg(t: TileTypes, st: StepResult) -> Any:
    mid = np.asarray(st.midpoint, dtype=float)
    kw = dict(
        index=int(st.index),
        s_m=float(st.s_m),
        midpoint=t.Point(x=float(mid[0]), y=float(mid[1]), z=0.0),
        heading=float(st.heading),
        width_m=float(st.width_m),
        valid=bool(st.valid),
        processed_before=bool(st.processed_before),
        lateral_m=_prim(t, st.lateral_m, np.float64),
        types=_prim(t, st.types, np.uint8),
        counts=_prim(t, st.counts, np.uint32),
        std_m=_prim(t, st.std_m, np.float64),
        drive_ids=[str(d) for d in st.drive_ids],
    )
    empty = np.zeros((0, 2)) if st.empty_m is None else np.asarray(st.empty_m, dtype=float).reshape(-1, 2)
    kw.update(
        judged=st.empty_m is not None,
        empty_lo_m=_prim(t, empty[:, 0], np.float64),
        empty_hi_m=_prim(t, empty[:, 1], np.float64),
    )
    pose = np.full(2, np.nan) if st.pose is None else np.asarray(st.pose, dtype=float).reshape(-1)[:2]
    kw.update(pose=t.Point(x=float(pose[0]), y=float(pose[1]), z=0.0))
    return t.SegmentStep(**kw)


@dataclass(frozen=True)
class TileMessage:
    """A decoded TileSegments message."""

    key: TileKey
    tile_size_m: float
    version: int
    drive_ids: tuple[str, ...]
    segments: list[Segment]
    stamp_ns: int = 0
    drive_tile_counts: tuple[int, ...] = ()  # per drive id: the tiles that drive covers (empty: unknown)
    final: bool = True  # made as the settled map makes it: its drives count as mapped here


def tile_to_msg(
    key: TileKey,
    segments: list[Segment],
    *,
    version: int,
    drive_ids: list[str] | tuple[str, ...],
    tile_size_m: float,
    stamp_ns: int,
    frame_id: str = "map",
    types: TileTypes,
    drive_tile_counts: list[int] | tuple[int, ...] = (),
    final: bool = True,
) -> Any:
    """One tile estimate -> hdmap_msgs/msg/TileSegments (``drive_tile_counts``: per drive id, the
    tiles that drive covers, and ``final``: made as the settled map makes it, so the stitcher can
    tell when a drive is mapped everywhere)."""
    t = types
    header = t.Header(stamp=t.Time(sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9)), frame_id=frame_id)
    segs = [t.Segment(pivot_id=s.pivot_id, steps=[_step_to_msg(t, st) for st in s.steps]) for s in segments]
    return t.TileSegments(
        header=header,
        tile_x=int(key[0]),
        tile_y=int(key[1]),
        tile_size_m=float(tile_size_m),
        version=int(version),
        drive_ids=[str(d) for d in drive_ids],
        drive_tile_counts=_prim(t, [int(n) for n in drive_tile_counts], np.uint32),
        final=bool(final),
        segments=segs,
    )


def _np(values: Any, dtype) -> np.ndarray:
    if isinstance(values, np.ndarray):
        return values.astype(dtype, copy=True)
    return np.array(values, dtype=dtype)


def _empty_from_msg(s: Any) -> np.ndarray | None:
    """A SegmentStep's empty intervals as (M, 2), None when not judged; unequal lo/hi lengths are
    cut to the shorter (a malformed message loses that evidence, not the step)."""
    if not bool(getattr(s, "judged", False)):
        return None
    lo, hi = _np(s.empty_lo_m, np.float64), _np(s.empty_hi_m, np.float64)
    n = min(len(lo), len(hi))
    return np.stack([lo[:n], hi[:n]], axis=1)


def _pose_from_msg(s: Any) -> np.ndarray | None:
    """A SegmentStep's pivot position, None when not known (NaN, or a message without it)."""
    p = getattr(s, "pose", None)
    if p is None:
        return None
    xy = np.array([p.x, p.y], dtype=float)
    return xy if np.isfinite(xy).all() else None


def msg_to_tile(msg: Any) -> TileMessage:
    """hdmap_msgs/msg/TileSegments (rosbags or rclpy) -> :class:`TileMessage`."""
    segments = []
    for sm in msg.segments:
        pivot = str(sm.pivot_id)
        steps = tuple(
            StepResult(
                pivot_id=pivot,
                index=int(s.index),
                s_m=float(s.s_m),
                midpoint=np.array([s.midpoint.x, s.midpoint.y], dtype=float),
                heading=float(s.heading),
                width_m=float(s.width_m),
                valid=bool(s.valid),
                processed_before=bool(s.processed_before),
                lateral_m=_np(s.lateral_m, np.float64),
                types=_np(s.types, np.int64),
                counts=_np(s.counts, np.int64),
                std_m=_np(s.std_m, np.float64),
                drive_ids=tuple(str(d) for d in s.drive_ids),
                empty_m=_empty_from_msg(s),
                pose=_pose_from_msg(s),
            )
            for s in sm.steps
        )
        segments.append(Segment(pivot_id=pivot, steps=steps))
    stamp = msg.header.stamp
    return TileMessage(
        key=(int(msg.tile_x), int(msg.tile_y)),
        tile_size_m=float(msg.tile_size_m),
        version=int(msg.version),
        drive_ids=tuple(str(d) for d in msg.drive_ids),
        segments=segments,
        stamp_ns=int(stamp.sec) * 10**9 + int(stamp.nanosec),
        drive_tile_counts=_tile_counts(msg),
        final=bool(getattr(msg, "final", True)),
    )


def _tile_counts(msg: Any) -> tuple[int, ...]:
    """The per-drive tile counts, () when absent or not one per drive id (unknown)."""
    counts = tuple(int(n) for n in getattr(msg, "drive_tile_counts", ()))
    return counts if len(counts) == len(msg.drive_ids) else ()


@dataclass(frozen=True)
class TileBatchEntry:
    """One tile of a decoded TileSegmentsBatch: the tile (its segments not yet made) and its
    segments in columns (``columns_to_segments`` makes them; a store takes the columns as they are)."""

    tile: TileMessage
    columns: SegmentColumns

    def segments(self) -> list[Segment]:
        return columns_to_segments(self.columns)


def tiles_to_batch(
    tiles: list[tuple[TileKey, list[Segment], int, list[str] | tuple[str, ...], list[int] | tuple[int, ...], bool]],
    *,
    tile_size_m: float,
    stamp_ns: int,
    frame_id: str = "map",
    types: TileTypes,
    columns: SegmentColumns | None = None,
) -> Any:
    """Many tile estimates -> one hdmap_msgs/msg/TileSegmentsBatch.

    Args:
        tiles: per tile (key, segments, version, drive ids, per drive id the tiles it covers (one
            per drive id, or empty for every tile: unknown), final), as :func:`tile_to_msg` takes them.
        columns: the tiles' segments in columns, in order (``segment_columns``), when at hand.
    """
    t = types
    c = segment_columns([seg for _, segs, *_ in tiles for seg in segs]) if columns is None else columns
    if len(c.pivots) != sum(len(segs) for _, segs, *_ in tiles):
        raise ValueError("tiles_to_batch: the columns are not of the tiles' segments")
    counts = [int(n) for *_, tc, _ in tiles for n in tc]
    n_ids = sum(len(ids) for *_, ids, _, _ in tiles)
    return t.TileSegmentsBatch(
        header=t.Header(stamp=t.Time(sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9)), frame_id=frame_id),
        tile_size_m=float(tile_size_m),
        tile_x=_prim(t, [int(k[0]) for k, *_ in tiles], np.int64),
        tile_y=_prim(t, [int(k[1]) for k, *_ in tiles], np.int64),
        version=_prim(t, [int(v) for _, _, v, *_ in tiles], np.uint64),
        final=_bools(t, [bool(f) for *_, f in tiles]),
        tile_drives=_prim(t, [len(ids) for *_, ids, _, _ in tiles], np.uint32),
        tile_segments=_prim(t, [len(segs) for _, segs, *_ in tiles], np.uint32),
        drive_ids=[str(d) for *_, ids, _, _ in tiles for d in ids],
        drive_tile_counts=_prim(t, counts if len(counts) == n_ids else [], np.uint32),
        pivot_id=list(c.pivots),
        segment_steps=_prim(t, c.nsteps, np.uint32),
        index=_prim(t, c.index, np.uint32),
        s_m=_prim(t, c.s_m, np.float64),
        midpoint_x=_prim(t, c.midpoint[:, 0], np.float64),
        midpoint_y=_prim(t, c.midpoint[:, 1], np.float64),
        heading=_prim(t, c.heading, np.float64),
        width_m=_prim(t, c.width_m, np.float64),
        valid=_bools(t, c.valid),
        processed_before=_bools(t, c.processed_before),
        judged=_bools(t, c.judged),
        pose_x=_prim(t, c.pose[:, 0], np.float64),
        pose_y=_prim(t, c.pose[:, 1], np.float64),
        step_maxima=_prim(t, c.k, np.uint32),
        step_empty=_prim(t, c.n_empty, np.uint32),
        step_drives=_prim(t, c.n_drives, np.uint32),
        lateral_m=_prim(t, c.lateral_m, np.float64),
        types=_prim(t, c.types, np.uint8),
        counts=_prim(t, c.counts, np.uint32),
        std_m=_prim(t, c.std_m, np.float64),
        empty_lo_m=_prim(t, c.empty_m[:, 0], np.float64),
        empty_hi_m=_prim(t, c.empty_m[:, 1], np.float64),
        step_drive_names=list(c.drive_names),
        step_drive_index=_prim(t, c.drive_index, np.uint32),
    )


def _arr(values: Any, dtype) -> np.ndarray:
    """A message's primitive array (numpy, ``array.array`` or a list) as a numpy array of ``dtype``."""
    if isinstance(values, array.array):
        return np.frombuffer(values, dtype=np.dtype(values.typecode)).astype(dtype)
    return np.asarray(values).astype(dtype).reshape(-1)


def batch_to_tiles(msg: Any) -> list[TileBatchEntry]:
    """hdmap_msgs/msg/TileSegmentsBatch (rosbags or rclpy) -> its tiles, in order.

    Raises:
        ValueError: the columns do not add up (a malformed message).
    """
    n_seg = _arr(msg.tile_segments, np.int64)
    n_ids = _arr(msg.tile_drives, np.int64)
    nsteps = _arr(msg.segment_steps, np.int64)
    k, n_empty, n_drives = (_arr(getattr(msg, f), np.int64) for f in ("step_maxima", "step_empty", "step_drives"))
    c = SegmentColumns(
        pivots=tuple(str(p) for p in msg.pivot_id),
        nsteps=nsteps,
        index=_arr(msg.index, np.int64),
        s_m=_arr(msg.s_m, np.float64),
        midpoint=np.stack([_arr(msg.midpoint_x, np.float64), _arr(msg.midpoint_y, np.float64)], axis=1),
        pose=np.stack([_arr(msg.pose_x, np.float64), _arr(msg.pose_y, np.float64)], axis=1),
        heading=_arr(msg.heading, np.float64),
        width_m=_arr(msg.width_m, np.float64),
        valid=_arr(msg.valid, bool),
        processed_before=_arr(msg.processed_before, bool),
        judged=_arr(msg.judged, bool),
        k=k,
        lateral_m=_arr(msg.lateral_m, np.float64),
        types=_arr(msg.types, np.int64),
        counts=_arr(msg.counts, np.int64),
        std_m=_arr(msg.std_m, np.float64),
        n_empty=n_empty,
        empty_m=np.stack([_arr(msg.empty_lo_m, np.float64), _arr(msg.empty_hi_m, np.float64)], axis=1),
        drive_names=tuple(str(d) for d in msg.step_drive_names),
        n_drives=n_drives,
        drive_index=_arr(msg.step_drive_index, np.int64),
    )
    n_steps = len(c.index)
    n_tiles = len(msg.tile_x)
    per_step = ("s_m", "heading", "width_m", "valid", "processed_before", "judged", "k", "n_empty", "n_drives")
    if (
        any(len(a) != n_tiles for a in (msg.tile_y, msg.version, msg.final, n_seg, n_ids))
        or int(n_seg.sum()) != len(c.pivots)
        or len(nsteps) != len(c.pivots)
        or int(nsteps.sum()) != n_steps
        or any(len(getattr(c, f)) != n_steps for f in per_step)
        or len(c.midpoint) != n_steps
        or len(c.pose) != n_steps
        or any(len(a) != int(k.sum()) for a in (c.lateral_m, c.types, c.counts, c.std_m))
        or len(c.empty_m) != int(n_empty.sum())
        or len(c.drive_index) != int(n_drives.sum())
        or (len(c.drive_index) and int(c.drive_index.max()) >= len(c.drive_names))
        or int(n_ids.sum()) != len(msg.drive_ids)
    ):
        raise ValueError("TileSegmentsBatch: its columns do not add up")
    ids = [str(d) for d in msg.drive_ids]
    counts = [int(n) for n in msg.drive_tile_counts]
    if len(counts) != len(ids):
        counts = []  # unknown
    stamp = msg.header.stamp
    stamp_ns = int(stamp.sec) * 10**9 + int(stamp.nanosec)
    seg_at = np.concatenate([[0], np.cumsum(n_seg)])
    id_at = np.concatenate([[0], np.cumsum(n_ids)])
    out = []
    for i in range(n_tiles):
        a, b = int(id_at[i]), int(id_at[i + 1])
        tile = TileMessage(
            key=(int(msg.tile_x[i]), int(msg.tile_y[i])),
            tile_size_m=float(msg.tile_size_m),
            version=int(msg.version[i]),
            drive_ids=tuple(ids[a:b]),
            segments=[],
            stamp_ns=stamp_ns,
            drive_tile_counts=tuple(counts[a:b]) if counts else (),
            final=bool(msg.final[i]),
        )
        out.append(TileBatchEntry(tile, take_segments(c, int(seg_at[i]), int(seg_at[i + 1]))))
    return out
