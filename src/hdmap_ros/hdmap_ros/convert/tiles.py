"""Pure conversions: tile estimates (segments of hdmap_core.steps) <-> hdmap_msgs/TileSegments.

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
from hdmap_core.steps import Segment, StepResult

__all__ = ["TileTypes", "rclpy_tile_types", "rosbags_tile_types", "tile_to_msg", "msg_to_tile", "TileMessage"]


@dataclass(frozen=True)
class TileTypes:
    TileSegments: Any
    Segment: Any
    SegmentStep: Any
    Point: Any
    Header: Any
    Time: Any
    numpy_arrays: bool


def rclpy_tile_types() -> TileTypes:
    from builtin_interfaces.msg import Time  # noqa: PLC0415
    from geometry_msgs.msg import Point  # noqa: PLC0415
    from std_msgs.msg import Header  # noqa: PLC0415

    from hdmap_msgs.msg import Segment as SegmentMsg  # noqa: PLC0415
    from hdmap_msgs.msg import SegmentStep, TileSegments  # noqa: PLC0415

    return TileTypes(TileSegments, SegmentMsg, SegmentStep, Point, Header, Time, numpy_arrays=False)


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
    )


_ARRAY_CODES = {np.float64: "d", np.uint8: "B", np.uint32: "I"}


def _prim(types: TileTypes, values: Any, dtype) -> Any:
    arr = np.ascontiguousarray(np.asarray(values, dtype=dtype).reshape(-1))
    if types.numpy_arrays:
        return arr
    return array.array(_ARRAY_CODES[dtype], arr.tobytes())


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
