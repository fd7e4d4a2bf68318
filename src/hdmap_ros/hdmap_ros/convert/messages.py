"""Pure message <-> data-model conversions (no rclpy, no I/O).

The same functions serve two kinds of message classes through a small namespace of classes
(:class:`MsgTypes`):

* rosbags typestore classes (the default, :func:`rosbags_types`), used for bags;
* rclpy's generated classes (:func:`rclpy_types`, imported only when asked for), used by nodes.

Reading accepts primitive arrays as numpy arrays (rosbags), ``array.array`` (rclpy) or lists.
Writing hands numpy arrays to rosbags classes and ``array.array`` to rclpy classes, which is what
each expects.

Conventions:

* Coordinates are the 2-D map frame; ``z`` is written as 0 and ignored on reading.
* Heading is ENU yaw; a pose's orientation is the rotation by yaw about z.
* ``Drive.header.stamp`` is the drive start; each ``PoseStamped.header.stamp`` is that pose's time.
* ``MapFeature.drive_count`` saturates at 65535 (uint16); ``lateral_std`` and ``width`` are
  float32 in the message, so they come back rounded to float32.
"""

from __future__ import annotations

import array
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hdmap_core.errors import InvalidDriveError, InvalidMessageError
from hdmap_core.live.progress import LiveStatus
from hdmap_core.model import (
    MAP_FRAME,
    Detection,
    Drive,
    FeatureType,
    GeoOrigin,
    HDMap,
    MapFeature,
    TopologyNode,
    validate_drive,
)
from hdmap_core.plausibility import check_quaternions

__all__ = [
    "status_to_msg",
    "rclpy_status_class",
    "msg_to_status",
    "MsgTypes",
    "rosbags_types",
    "rclpy_types",
    "drive_to_msg",
    "msg_to_drive",
    "map_to_msg",
    "feature_arrays",
    "msg_to_map",
    "origin_to_msg",
    "msg_to_origin",
    "stamp_to_ns",
    "ns_to_sec_nanosec",
    "yaw_to_quaternion",
    "quaternion_to_yaw",
]

_UINT16_MAX = 2**16 - 1
_UINT64_MAX = 2**64 - 1
_NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class MsgTypes:
    """The message classes the conversions build (one namespace per message library).

    Attributes:
        numpy_arrays: True when primitive array fields take numpy arrays (rosbags); False when
            they take ``array.array`` (rclpy).
    """

    Drive: Any
    DetectionPolyline: Any
    Map: Any
    MapFeature: Any
    TopologyNode: Any
    Header: Any
    Time: Any
    Path: Any
    PoseStamped: Any
    Pose: Any
    Point: Any
    Quaternion: Any
    NavSatFix: Any
    NavSatStatus: Any
    numpy_arrays: bool = True


_TYPE_NAMES = {
    "Drive": "hdmap_msgs/msg/Drive",
    "DetectionPolyline": "hdmap_msgs/msg/DetectionPolyline",
    "Map": "hdmap_msgs/msg/Map",
    "MapFeature": "hdmap_msgs/msg/MapFeature",
    "TopologyNode": "hdmap_msgs/msg/TopologyNode",
    "Header": "std_msgs/msg/Header",
    "Time": "builtin_interfaces/msg/Time",
    "Path": "nav_msgs/msg/Path",
    "PoseStamped": "geometry_msgs/msg/PoseStamped",
    "Pose": "geometry_msgs/msg/Pose",
    "Point": "geometry_msgs/msg/Point",
    "Quaternion": "geometry_msgs/msg/Quaternion",
    "NavSatFix": "sensor_msgs/msg/NavSatFix",
    "NavSatStatus": "sensor_msgs/msg/NavSatStatus",
}


def rosbags_types(typestore: Any = None) -> MsgTypes:
    """The rosbags classes of ``typestore`` (default: :func:`hdmap_ros.io.msgdefs.default_typestore`)."""
    if typestore is None:
        return _default_types()
    return MsgTypes(**{k: typestore.types[v] for k, v in _TYPE_NAMES.items()}, numpy_arrays=True)


@functools.lru_cache(maxsize=1)
def _default_types() -> MsgTypes:
    from hdmap_ros.io.msgdefs import default_typestore  # noqa: PLC0415 - avoid work at import

    return rosbags_types(default_typestore())


def rclpy_types() -> MsgTypes:
    """The rclpy-generated classes (needs the built hdmap_msgs and the ROS message packages)."""
    import importlib  # noqa: PLC0415

    classes = {}
    for key, name in _TYPE_NAMES.items():
        pkg, _, cls = name.split("/")
        classes[key] = getattr(importlib.import_module(f"{pkg}.msg"), cls)
    return MsgTypes(**classes, numpy_arrays=False)


# ---------------------------------------------------------------- small helpers


def ns_to_sec_nanosec(stamp_ns: int) -> tuple[int, int]:
    """Split nanoseconds since the epoch into (sec, nanosec) as in builtin_interfaces/Time."""
    sec, nsec = divmod(int(stamp_ns), _NS_PER_S)
    return sec, nsec


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> nanoseconds."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def yaw_to_quaternion(yaw: np.ndarray) -> np.ndarray:
    """(N,) ENU yaw [rad] -> (N, 4) quaternions (x, y, z, w) of the rotation about z."""
    half = 0.5 * np.asarray(yaw, dtype=np.float64)
    zeros = np.zeros_like(half)
    return np.stack([zeros, zeros, np.sin(half), np.cos(half)], axis=-1)


def quaternion_to_yaw(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) -> (N,) yaw [rad] in (-pi, pi] (rotation about z)."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _header(types: MsgTypes, stamp_ns: int, frame_id: str) -> Any:
    sec, nsec = ns_to_sec_nanosec(stamp_ns)
    return types.Header(stamp=types.Time(sec=sec, nanosec=nsec), frame_id=frame_id)


def _points_to_msgs(types: MsgTypes, xy: np.ndarray) -> list:
    point = types.Point
    # tolist() gives Python floats: fastest to iterate, and what rclpy's setters accept.
    return [point(x=x, y=y, z=0.0) for x, y in np.asarray(xy, dtype=np.float64).tolist()]


def _msgs_to_xy(points: Sequence[Any]) -> np.ndarray:
    """geometry_msgs/Point[] -> (N, 2) float64."""
    n = len(points)
    flat = np.fromiter((c for p in points for c in (p.x, p.y)), dtype=np.float64, count=2 * n)
    return flat.reshape(n, 2)


def _prim_array(types: MsgTypes, values: Any, dtype: str) -> Any:
    """A primitive array field: numpy for rosbags, array.array for rclpy."""
    arr = np.ascontiguousarray(values, dtype=dtype)
    if types.numpy_arrays:
        return arr
    code = {"<u2": "H", "<f4": "f", "<u8": "Q"}[dtype]
    return array.array(code, arr.tobytes())


def _ids(values: Any) -> tuple[int, ...]:
    return tuple(int(v) for v in np.asarray(values, dtype=np.uint64).tolist())


# ---------------------------------------------------------------- drives


def drive_to_msg(drive: Drive, *, types: MsgTypes | None = None) -> Any:
    """Drive -> hdmap_msgs/msg/Drive (of the class namespace ``types``, default rosbags).

    Writes what it is given (no validation): writing malformed drives on purpose is allowed, e.g.
    for bad-input test bags.
    """
    t = types or _default_types()
    frame = drive.frame_id
    xy = np.asarray(drive.xy, dtype=np.float64).reshape(-1, 2)
    quats = yaw_to_quaternion(np.asarray(drive.yaw, dtype=np.float64)).tolist()
    stamps = np.asarray(drive.stamps_ns, dtype=np.int64).tolist()
    poses = [
        t.PoseStamped(
            header=_header(t, ns, frame),
            pose=t.Pose(
                position=t.Point(x=x, y=y, z=0.0),
                orientation=t.Quaternion(x=qx, y=qy, z=qz, w=qw),
            ),
        )
        for (x, y), (qx, qy, qz, qw), ns in zip(xy.tolist(), quats, stamps, strict=False)
    ]
    start_ns = stamps[0] if stamps else 0
    detections = [
        t.DetectionPolyline(type=int(d.type), points=_points_to_msgs(t, np.reshape(d.points, (-1, 2))))
        for d in drive.detections
    ]
    return t.Drive(
        header=_header(t, start_ns, frame),
        drive_id=drive.drive_id,
        vehicle_id=drive.vehicle_id,
        trajectory=t.Path(header=_header(t, start_ns, frame), poses=poses),
        detections=detections,
    )


def msg_to_drive(msg: Any, *, expected_frame: str | None = MAP_FRAME) -> Drive:
    """hdmap_msgs/msg/Drive (rosbags or rclpy) -> a validated Drive.

    Args:
        msg: the message.
        expected_frame: the frame every coordinate must be in; None or "" skips that check.

    Raises:
        InvalidDriveError: malformed content (``reason`` names the class, e.g.
            ``non_finite_coordinates``, ``too_few_points``, ``empty_trajectory``,
            ``unknown_type``, ``wrong_frame``); see :func:`hdmap_core.model.validate_drive`;
            ``bad_quaternion`` for a pose orientation whose norm is not 1
            (:func:`hdmap_core.plausibility.check_quaternions`).
    """
    did = str(msg.drive_id)
    frame = str(msg.header.frame_id)
    poses = msg.trajectory.poses
    n = len(poses)
    # A path or pose in a frame other than the drive's own is as wrong as a wrong drive frame.
    inner = {str(msg.trajectory.header.frame_id)} | {str(p.header.frame_id) for p in poses}
    inner.discard("")
    if inner - {frame}:
        raise InvalidDriveError(did, "wrong_frame", f"drive frame {frame!r} but trajectory poses in {sorted(inner)}")
    xy = np.fromiter(
        (c for p in poses for c in (p.pose.position.x, p.pose.position.y)), dtype=np.float64, count=2 * n
    ).reshape(n, 2)
    quat = np.fromiter(
        (
            c
            for p in poses
            for c in (p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w)
        ),
        dtype=np.float64,
        count=4 * n,
    ).reshape(n, 4)
    stamps = np.fromiter((stamp_to_ns(p.header.stamp) for p in poses), dtype=np.int64, count=n)
    detections = []
    for i, det in enumerate(msg.detections):
        try:
            ftype = FeatureType(int(det.type))
        except ValueError:
            raise InvalidDriveError(did, "unknown_type", f"detection {i} has type {int(det.type)}") from None
        detections.append(Detection(type=ftype, points=_msgs_to_xy(det.points)))
    check_quaternions(did, quat)
    yaw = quaternion_to_yaw(quat)
    drive = Drive(
        drive_id=did,
        xy=xy,
        yaw=yaw,
        stamps_ns=stamps,
        detections=tuple(detections),
        vehicle_id=str(msg.vehicle_id),
        frame_id=frame,
    )
    return validate_drive(drive, expected_frame=expected_frame or "")


# ---------------------------------------------------------------- maps


def map_to_msg(hdmap: HDMap, *, types: MsgTypes | None = None) -> Any:
    """HDMap -> hdmap_msgs/msg/Map (of the class namespace ``types``, default rosbags).

    Raises:
        InvalidMessageError: an id outside uint64, or per-point arrays of the wrong length.
    """
    t = types or _default_types()
    features = [_feature_to_msg(t, f) for f in hdmap.features]
    topology = [_node_to_msg(t, n) for n in hdmap.topology]
    return t.Map(
        header=_header(t, hdmap.stamp_ns, hdmap.frame_id),
        version=int(hdmap.version),
        drive_ids=[str(d) for d in hdmap.drive_ids],
        features=features,
        topology=topology,
    )


def _check_id(what: str, value: int) -> int:
    value = int(value)
    if not 0 <= value <= _UINT64_MAX:
        raise InvalidMessageError(f"{what} id {value} does not fit uint64")
    return value


def feature_arrays(f: MapFeature) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A map feature's per-point arrays as a message carries them: points (N, 2), drive counts
    (N,), lateral stds (N,). Raises InvalidMessageError when their lengths differ."""
    pts = np.asarray(f.points, dtype=np.float64).reshape(-1, 2)
    counts = np.asarray(f.drive_count).reshape(-1)
    std = np.asarray(f.lateral_std, dtype=np.float64).reshape(-1)
    if len(counts) != len(pts) or len(std) != len(pts):
        raise InvalidMessageError(
            f"map feature {f.id}: {len(pts)} points but {len(counts)} drive counts and {len(std)} lateral stds"
        )
    return pts, counts, std


def _feature_to_msg(t: MsgTypes, f: MapFeature) -> Any:
    fid = _check_id("map feature", f.id)
    pts, counts, std = feature_arrays(f)
    return t.MapFeature(
        id=fid,
        type=int(f.type),
        points=_points_to_msgs(t, pts),
        drive_count=_prim_array(t, np.clip(counts, 0, _UINT16_MAX), "<u2"),
        lateral_std=_prim_array(t, std, "<f4"),
        predecessors=_prim_array(t, [_check_id("predecessor", i) for i in f.predecessors], "<u8"),
        successors=_prim_array(t, [_check_id("successor", i) for i in f.successors], "<u8"),
    )


def _node_to_msg(t: MsgTypes, n: TopologyNode) -> Any:
    x, y = np.asarray(n.position, dtype=np.float64).reshape(2).tolist()
    return t.TopologyNode(
        id=_check_id("topology node", n.id),
        position=t.Point(x=x, y=y, z=0.0),
        heading=float(n.heading),
        width=float(n.width),
        successors=_prim_array(t, [_check_id("successor", i) for i in n.successors], "<u8"),
        features=_prim_array(t, [_check_id("feature", i) for i in n.features], "<u8"),
    )


def msg_to_map(msg: Any, *, expected_frame: str | None = None) -> HDMap:
    """hdmap_msgs/msg/Map (rosbags or rclpy) -> HDMap.

    Raises:
        InvalidMessageError: wrong frame (when ``expected_frame`` is given), a feature of unknown
            type, per-point arrays of the wrong length, or non-finite coordinates.
    """
    frame = str(msg.header.frame_id)
    if expected_frame and frame != expected_frame:
        raise InvalidMessageError(f"map frame {frame!r}, want {expected_frame!r}")
    features = tuple(_msg_to_feature(f) for f in msg.features)
    topology = tuple(_msg_to_node(n) for n in msg.topology)
    return HDMap(
        features=features,
        topology=topology,
        drive_ids=tuple(str(d) for d in msg.drive_ids),
        version=int(msg.version),
        frame_id=frame,
        stamp_ns=stamp_to_ns(msg.header.stamp),
    )


def _msg_to_feature(m: Any) -> MapFeature:
    fid = int(m.id)
    try:
        ftype = FeatureType(int(m.type))
    except ValueError:
        raise InvalidMessageError(f"map feature {fid}: unknown type {int(m.type)}") from None
    pts = _msgs_to_xy(m.points)
    counts = np.asarray(m.drive_count, dtype=np.int64).reshape(-1)
    std = np.asarray(m.lateral_std, dtype=np.float64).reshape(-1)
    if len(counts) != len(pts) or len(std) != len(pts):
        raise InvalidMessageError(
            f"map feature {fid}: {len(pts)} points but {len(counts)} drive counts and {len(std)} lateral stds"
        )
    if not np.all(np.isfinite(pts)):
        raise InvalidMessageError(f"map feature {fid}: NaN/inf coordinates")
    return MapFeature(
        id=fid,
        type=ftype,
        points=pts,
        drive_count=counts,
        lateral_std=std,
        predecessors=_ids(m.predecessors),
        successors=_ids(m.successors),
    )


def _msg_to_node(m: Any) -> TopologyNode:
    pos = np.array([m.position.x, m.position.y], dtype=np.float64)
    if not np.all(np.isfinite(pos)):
        raise InvalidMessageError(f"topology node {int(m.id)}: NaN/inf position")
    return TopologyNode(
        id=int(m.id),
        position=pos,
        heading=float(m.heading),
        width=float(m.width),
        successors=_ids(m.successors),
        features=_ids(m.features),
    )


# ---------------------------------------------------------------- origin


def origin_to_msg(
    origin: GeoOrigin, *, stamp_ns: int = 0, frame_id: str = MAP_FRAME, types: MsgTypes | None = None
) -> Any:
    """GeoOrigin -> sensor_msgs/msg/NavSatFix (a fix, covariance unknown)."""
    t = types or _default_types()
    return t.NavSatFix(
        header=_header(t, stamp_ns, frame_id),
        status=t.NavSatStatus(status=t.NavSatStatus.STATUS_FIX, service=t.NavSatStatus.SERVICE_GPS),
        latitude=float(origin.latitude_deg),
        longitude=float(origin.longitude_deg),
        altitude=float(origin.altitude_m),
        position_covariance=np.zeros(9, dtype=np.float64),
        position_covariance_type=t.NavSatFix.COVARIANCE_TYPE_UNKNOWN,
    )


def msg_to_origin(msg: Any) -> GeoOrigin:
    """sensor_msgs/msg/NavSatFix -> GeoOrigin (a NaN altitude, "no altitude" in ROS, becomes 0).

    Raises:
        InvalidMessageError: latitude/longitude not finite or out of range, or the status says
            there is no fix.
    """
    lat, lon, alt = float(msg.latitude), float(msg.longitude), float(msg.altitude)
    if not (math.isfinite(lat) and math.isfinite(lon)) or abs(lat) > 90.0 or abs(lon) > 180.0:
        raise InvalidMessageError(f"origin latitude/longitude ({lat}, {lon}) is not a valid WGS84 position")
    if int(msg.status.status) < 0:
        raise InvalidMessageError(f"origin NavSatFix has no fix (status {int(msg.status.status)})")
    return GeoOrigin(latitude_deg=lat, longitude_deg=lon, altitude_m=alt if math.isfinite(alt) else 0.0)


# ---------------------------------------------------------------- the live map's status


def rclpy_status_class() -> Any:
    """The rclpy class of hdmap_msgs/msg/MapStatus."""
    from hdmap_msgs.msg import MapStatus  # noqa: PLC0415

    return MapStatus


def status_to_msg(status: LiveStatus, *, cls: Any, types: MsgTypes) -> Any:
    """:class:`~hdmap_core.live.progress.LiveStatus` -> hdmap_msgs/msg/MapStatus (class ``cls``)."""
    return cls(
        header=_header(types, status.stamp_ns, MAP_FRAME),
        map_version=int(status.map_version),
        drives_received=int(status.drives_received),
        drives_integrated=int(status.drives_integrated),
        drives_rejected=int(status.drives_rejected),
        tiles_pending=int(status.tiles_pending),
        tile_versions=int(status.tile_versions),
        settled=bool(status.settled),
    )


def msg_to_status(msg: Any) -> LiveStatus:
    """hdmap_msgs/msg/MapStatus -> :class:`~hdmap_core.live.progress.LiveStatus`."""
    return LiveStatus(
        map_version=int(msg.map_version),
        drives_received=int(msg.drives_received),
        drives_integrated=int(msg.drives_integrated),
        drives_rejected=int(msg.drives_rejected),
        tiles_pending=int(msg.tiles_pending),
        tile_versions=int(msg.tile_versions),
        settled=bool(msg.settled),
        stamp_ns=stamp_to_ns(msg.header.stamp),
    )


# ---------------------------------------------------------------- road changes


def rclpy_change_class() -> Any:
    """The rclpy class of hdmap_msgs/msg/MapChange."""
    from hdmap_msgs.msg import MapChange  # noqa: PLC0415

    return MapChange


def change_to_msg(change: Any, *, cls: Any, types: MsgTypes) -> Any:
    """:class:`~hdmap_core.live.changes.LiveChange` -> hdmap_msgs/msg/MapChange (class ``cls``)."""
    from geometry_msgs.msg import Point32, Polygon  # noqa: PLC0415

    poly = np.asarray(change.polygon, dtype=float).reshape(-1, 2)
    valid_from = min((r.valid_from_ns for r in change.retired), default=int(change.time_ns))
    return cls(
        header=_header(types, change.confirmed_ns, MAP_FRAME),
        id=int(change.id),
        time_ns=int(change.time_ns),
        kinds=[str(k) for k in change.kinds],
        confidence=float(change.confidence),
        polygon=Polygon(points=[Point32(x=float(x), y=float(y), z=0.0) for x, y in poly]),
        tile_x=[int(t[0]) for t in change.tiles],
        tile_y=[int(t[1]) for t in change.tiles],
        place_x=[int(p[0]) for p in change.places],
        place_y=[int(p[1]) for p in change.places],
        place_side=[int(p[2]) for p in change.places],
        place_cell_m=float(change.cell_m),
        retired_feature_ids=[int(i) for i in change.retired_feature_ids],
        retired=[
            _feature_to_msg(
                types,
                MapFeature(
                    id=int(r.feature_id),
                    type=FeatureType(int(r.type)),
                    points=np.asarray(r.points, dtype=float).reshape(-1, 2),
                    drive_count=np.zeros(len(r.points), dtype=np.uint16),
                    lateral_std=np.zeros(len(r.points)),
                ),
            )
            for r in change.retired
        ],
        drive_ids=[str(d) for d in change.drive_ids],
        valid_from_ns=int(change.time_ns),
        retired_valid_from_ns=int(valid_from),
        retired_valid_to_ns=int(change.time_ns),
        map_version=int(change.map_version),
    )
