"""Message <-> model conversions, tested on rosbags classes and on rclpy-like plain classes (no rclpy)."""

from __future__ import annotations

import array
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from hdmap_core.errors import InvalidDriveError, InvalidMessageError
from hdmap_core.model import Detection, FeatureType, GeoOrigin
from hdmap_ros.convert.messages import (
    MsgTypes,
    drive_to_msg,
    map_to_msg,
    msg_to_drive,
    msg_to_map,
    msg_to_origin,
    origin_to_msg,
    quaternion_to_yaw,
    yaw_to_quaternion,
)
from hdmap_ros.io.msgdefs import default_typestore, hdmap_msg_texts

from bag_samples import assert_drives_equal, assert_maps_equal, make_drive, make_map


def _plain_types() -> MsgTypes:
    """Stand-ins for rclpy classes: keyword constructors, array.array for primitive arrays."""

    def cls(name: str, **consts):
        return type(name, (SimpleNamespace,), consts)

    names = [
        "Drive",
        "DetectionPolyline",
        "Map",
        "MapFeature",
        "TopologyNode",
        "Header",
        "Time",
        "Path",
        "PoseStamped",
        "Pose",
        "Point",
        "Quaternion",
    ]
    classes = {n: cls(n) for n in names}
    classes["NavSatFix"] = cls("NavSatFix", COVARIANCE_TYPE_UNKNOWN=0)
    classes["NavSatStatus"] = cls("NavSatStatus", STATUS_FIX=0, SERVICE_GPS=1)
    return MsgTypes(**classes, numpy_arrays=False)


def test_msg_texts_are_the_hdmap_msgs_files():
    texts = hdmap_msg_texts()
    for name in ("Drive", "DetectionPolyline", "Map", "MapFeature", "TopologyNode"):
        assert f"hdmap_msgs/msg/{name}" in texts
    assert "nav_msgs/Path trajectory" in texts["hdmap_msgs/msg/Drive"]


@pytest.mark.parametrize("yaw", [0.0, 0.3, -2.0, math.pi - 1e-9, -math.pi + 1e-9, 1.5707963])
def test_yaw_quaternion_round_trip(yaw):
    q = yaw_to_quaternion(np.array([yaw]))
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(quaternion_to_yaw(q), [yaw], atol=1e-12)


def test_drive_round_trip_through_cdr():
    store = default_typestore()
    drive = make_drive("drive/7", n=40, seed=3)
    raw = store.serialize_cdr(drive_to_msg(drive), "hdmap_msgs/msg/Drive")
    back = msg_to_drive(store.deserialize_cdr(raw, "hdmap_msgs/msg/Drive"))
    assert_drives_equal(drive, back)


def test_drive_message_fields():
    drive = make_drive(n=5)
    msg = drive_to_msg(drive)
    assert msg.header.frame_id == "map"
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == drive.stamps_ns[0]
    p = msg.trajectory.poses[3]
    assert p.header.stamp.sec * 10**9 + p.header.stamp.nanosec == drive.stamps_ns[3]
    assert p.pose.position.z == 0.0
    assert [d.type for d in msg.detections] == [1, 2, 3]


def test_drive_round_trip_plain_classes_with_lists():
    drive = make_drive(n=12, seed=5)
    back = msg_to_drive(drive_to_msg(drive, types=_plain_types()))
    assert_drives_equal(drive, back)


def _bad(drive_msg_edit):
    msg = drive_to_msg(make_drive("bad-1", n=10))
    drive_msg_edit(msg)
    return msg


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        (lambda m: setattr(m.trajectory.poses[4].pose.position, "x", float("nan")), "non_finite_coordinates"),
        (lambda m: setattr(m.detections[1].points[0], "y", float("inf")), "non_finite_coordinates"),
        (lambda m: setattr(m.detections[0], "points", m.detections[0].points[:1]), "too_few_points"),
        (lambda m: setattr(m.trajectory, "poses", []), "empty_trajectory"),
        (lambda m: setattr(m.trajectory, "poses", m.trajectory.poses[:1]), "too_few_points"),
        (lambda m: setattr(m.detections[2], "type", 9), "unknown_type"),
        (lambda m: setattr(m.header, "frame_id", "odom"), "wrong_frame"),
        (lambda m: setattr(m.trajectory.poses[2].header, "frame_id", "base_link"), "wrong_frame"),
        (lambda m: setattr(m.trajectory.poses[2].pose.orientation, "w", float("nan")), "bad_quaternion"),
        (lambda m: setattr(m.trajectory.poses[2].pose.orientation, "w", 0.0), "bad_quaternion"),
    ],
)
def test_malformed_drive_message_names_drive_and_reason(edit, reason):
    with pytest.raises(InvalidDriveError) as info:
        msg_to_drive(_bad(edit))
    assert info.value.drive_id == "bad-1"
    assert info.value.reason == reason
    assert "bad-1" in str(info.value) and reason in str(info.value)


def test_expected_frame_can_be_switched_off():
    drive = replace(make_drive(n=6), frame_id="odom")
    assert msg_to_drive(drive_to_msg(drive), expected_frame=None).frame_id == "odom"
    assert msg_to_drive(drive_to_msg(drive), expected_frame="odom").frame_id == "odom"


def test_map_round_trip_through_cdr():
    store = default_typestore()
    hdmap = make_map(seed=2)
    raw = store.serialize_cdr(map_to_msg(hdmap), "hdmap_msgs/msg/Map")
    assert_maps_equal(hdmap, msg_to_map(store.deserialize_cdr(raw, "hdmap_msgs/msg/Map")))


def test_map_round_trip_plain_classes_with_array_array():
    hdmap = make_map(seed=4)
    msg = map_to_msg(hdmap, types=_plain_types())
    assert isinstance(msg.features[0].drive_count, array.array) and msg.features[0].drive_count.typecode == "H"
    assert isinstance(msg.features[0].lateral_std, array.array) and msg.features[0].lateral_std.typecode == "f"
    assert msg.features[1].predecessors.typecode == "Q"
    assert_maps_equal(hdmap, msg_to_map(msg))


def test_drive_count_saturates_at_uint16():
    hdmap = make_map(n_features=1, n_points=3)
    f = replace(hdmap.features[0], drive_count=np.array([1, 70_000, 65_535]))
    back = msg_to_map(map_to_msg(replace(hdmap, features=(f,))))
    np.testing.assert_array_equal(back.features[0].drive_count, [1, 65_535, 65_535])


def test_map_id_outside_uint64_is_refused():
    hdmap = make_map(n_features=1)
    with pytest.raises(InvalidMessageError, match="uint64"):
        map_to_msg(replace(hdmap, features=(replace(hdmap.features[0], id=-1),)))


def test_map_per_point_length_mismatch_is_refused_both_ways():
    hdmap = make_map(n_features=1, n_points=5)
    bad = replace(hdmap.features[0], lateral_std=np.ones(4))
    with pytest.raises(InvalidMessageError, match="5 points"):
        map_to_msg(replace(hdmap, features=(bad,)))
    msg = map_to_msg(hdmap)
    msg.features[0].drive_count = msg.features[0].drive_count[:2]
    with pytest.raises(InvalidMessageError, match="drive counts"):
        msg_to_map(msg)


def test_map_unknown_feature_type_and_wrong_frame():
    msg = map_to_msg(make_map(n_features=2))
    with pytest.raises(InvalidMessageError, match="frame"):
        msg_to_map(msg, expected_frame="odom")
    msg.features[1].type = 42
    with pytest.raises(InvalidMessageError, match="unknown type 42"):
        msg_to_map(msg)


def test_origin_round_trip_and_checks():
    origin = GeoOrigin(48.137154, 11.576124, 519.5)
    msg = origin_to_msg(origin, stamp_ns=5)
    assert msg_to_origin(msg) == origin
    msg.altitude = float("nan")
    assert msg_to_origin(msg).altitude_m == 0.0
    msg.latitude = 91.0
    with pytest.raises(InvalidMessageError, match="WGS84"):
        msg_to_origin(msg)


def test_detection_points_keep_order_and_z_is_dropped():
    pts = np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.7]])
    drive = replace(make_drive(n=5), detections=(Detection(FeatureType.SOLID, pts),))
    msg = drive_to_msg(drive)
    for p in msg.detections[0].points:
        p.z = 3.0  # a 3-D detection: z is ignored
    np.testing.assert_array_equal(msg_to_drive(msg).detections[0].points, pts)
