"""The data model every pipeline stage hands to the next: drives in, hierarchical map out.

All coordinates are metric, 2-D, in the local east-north-up map frame (x east, y north).
Arrays are numpy; shapes are given in the docstrings. Data classes are frozen: stages never
mutate their inputs, they return new objects.

Type codes equal the constants of hdmap_msgs (DetectionPolyline / MapFeature TYPE_*), so that the
message conversion is a plain cast.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from hdmap_core.errors import InvalidDriveError

__all__ = [
    "FeatureType",
    "Detection",
    "Drive",
    "GeoOrigin",
    "MapFeature",
    "TopologyNode",
    "HDMap",
    "validate_drive",
    "MAP_FRAME",
]

MAP_FRAME = "map"


class FeatureType(IntEnum):
    """Road feature type; values equal hdmap_msgs TYPE_* constants."""

    UNKNOWN = 0
    SOLID = 1
    DASHED = 2
    ROAD_BORDER = 3

    @property
    def label(self) -> str:
        """The ground-truth JSON / GeoJSON name of this type."""
        return _LABELS[self]

    @classmethod
    def from_label(cls, label: str) -> FeatureType:
        """Parse a ground-truth JSON type name ("solid", "dashed", "road_border")."""
        try:
            return _FROM_LABEL[label]
        except KeyError:
            raise ValueError(f"unknown feature type label {label!r}") from None


_LABELS = {
    FeatureType.UNKNOWN: "unknown",
    FeatureType.SOLID: "solid",
    FeatureType.DASHED: "dashed",
    FeatureType.ROAD_BORDER: "road_border",
}
_FROM_LABEL = {v: k for k, v in _LABELS.items()}


@dataclass(frozen=True)
class Detection:
    """One connected detection polyline of one drive.

    Attributes:
        type: the detected feature type (may be wrong: misclassification happens).
        points: (N, 2) float64, ordered in driving direction, map frame [m].
    """

    type: FeatureType
    points: np.ndarray


@dataclass(frozen=True)
class Drive:
    """One drive snippet of one fleet vehicle.

    Attributes:
        drive_id: unique per snippet; the stable key of everything derived from this drive.
        xy: (N, 2) float64 trajectory positions, map frame [m], time ordered.
        yaw: (N,) float64 heading, ENU yaw [rad].
        stamps_ns: (N,) int64 pose time stamps [ns since epoch].
        detections: the drive's detection polylines.
        vehicle_id: may be empty.
        frame_id: the frame of all coordinates; must be ``MAP_FRAME`` for use.
    """

    drive_id: str
    xy: np.ndarray
    yaw: np.ndarray
    stamps_ns: np.ndarray
    detections: tuple[Detection, ...] = ()
    vehicle_id: str = ""
    frame_id: str = MAP_FRAME

    @property
    def start_ns(self) -> int:
        return int(self.stamps_ns[0]) if len(self.stamps_ns) else 0

    @property
    def length_m(self) -> float:
        """Travelled distance along the trajectory [m]."""
        if len(self.xy) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.xy, axis=0), axis=1).sum())


@dataclass(frozen=True)
class GeoOrigin:
    """WGS84 origin of the local ENU map frame (/fleet/origin)."""

    latitude_deg: float
    longitude_deg: float
    altitude_m: float = 0.0


@dataclass(frozen=True)
class MapFeature:
    """One polyline of the road-feature graph: a fused lane marking or road border.

    Attributes:
        id: stable across map versions while the feature exists.
        type: feature type.
        points: (N, 2) float64, ordered in driving direction, map frame [m].
        drive_count: (N,) int, drives supporting each point.
        lateral_std: (N,) float, estimated 1-sigma lateral uncertainty per point [m].
        predecessors: ids of features whose last point connects to this first point.
        successors: ids of features whose first point connects to this last point.
    """

    id: int
    type: FeatureType
    points: np.ndarray
    drive_count: np.ndarray
    lateral_std: np.ndarray
    predecessors: tuple[int, ...] = ()
    successors: tuple[int, ...] = ()


@dataclass(frozen=True)
class TopologyNode:
    """One sampling step of the topology graph (SD-map-like).

    Attributes:
        id: stable id.
        position: (2,) road midpoint at this step [m].
        heading: driving direction, ENU yaw [rad].
        width: estimated ego-road width [m].
        successors: ids of the next topology nodes (several at a split).
        features: ids of the MapFeatures crossing this step.
    """

    id: int
    position: np.ndarray
    heading: float
    width: float
    successors: tuple[int, ...] = ()
    features: tuple[int, ...] = ()


@dataclass(frozen=True)
class HDMap:
    """The hierarchical map: topology graph plus road-feature graph."""

    features: tuple[MapFeature, ...] = ()
    topology: tuple[TopologyNode, ...] = ()
    drive_ids: tuple[str, ...] = ()
    version: int = 0
    frame_id: str = MAP_FRAME
    stamp_ns: int = 0
    extra: dict = field(default_factory=dict, compare=False)

    def features_of_type(self, ftype: FeatureType) -> list[MapFeature]:
        return [f for f in self.features if f.type == ftype]


def _check_points(drive_id: str, what: str, pts: np.ndarray) -> None:
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise InvalidDriveError(drive_id, "bad_shape", f"{what} has shape {pts.shape}, want (N, 2)")
    if len(pts) < 2:
        raise InvalidDriveError(drive_id, "too_few_points", f"{what} has {len(pts)} point(s), need >= 2")
    if not np.all(np.isfinite(pts)):
        raise InvalidDriveError(drive_id, "non_finite_coordinates", f"{what} has NaN/inf coordinates")


def validate_drive(drive: Drive, *, expected_frame: str = MAP_FRAME) -> Drive:
    """Check a drive for the bad-input classes and return it unchanged.

    Raises:
        InvalidDriveError: empty id, wrong frame, empty/short/non-finite trajectory,
            yaw or stamps of the wrong length, a detection of unknown type, fewer than 2 points
            or non-finite coordinates. ``reason`` names the class. TYPE_UNKNOWN (0) is a valid
            message value and passes; the pipeline ignores such detections.
    """
    did = drive.drive_id
    if not did:
        raise InvalidDriveError(did, "empty_drive_id")
    if expected_frame and drive.frame_id != expected_frame:
        raise InvalidDriveError(did, "wrong_frame", f"frame_id {drive.frame_id!r}, want {expected_frame!r}")
    xy = np.asarray(drive.xy)
    if xy.size == 0:
        raise InvalidDriveError(did, "empty_trajectory")
    _check_points(did, "trajectory", xy)
    if np.shape(drive.yaw) != (len(xy),) or not np.all(np.isfinite(drive.yaw)):
        raise InvalidDriveError(did, "bad_heading", "yaw missing, of wrong length or non-finite")
    if np.shape(drive.stamps_ns) != (len(xy),):
        raise InvalidDriveError(did, "bad_stamps", "one stamp per pose is required")
    for i, det in enumerate(drive.detections):
        try:
            FeatureType(int(det.type))  # raises ValueError on an unknown code
        except ValueError:
            raise InvalidDriveError(did, "unknown_type", f"detection {i} has type {det.type!r}") from None
        _check_points(did, f"detection {i}", np.asarray(det.points))
    return drive


def unique_drives(drives: Iterable[Drive]) -> list[Drive]:
    """Keep the first drive of each drive_id, order preserved."""
    seen: set[str] = set()
    out: list[Drive] = []
    for d in drives:
        if d.drive_id not in seen:
            seen.add(d.drive_id)
            out.append(d)
    return out
