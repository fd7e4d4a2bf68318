"""The conversions on rclpy's generated classes, and CDR compatibility with rclpy (no DDS started)."""

from __future__ import annotations

import array

import pytest

pytest.importorskip("rclpy")
hdmap_msgs = pytest.importorskip("hdmap_msgs.msg")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from hdmap_core.model import GeoOrigin  # noqa: E402
from hdmap_ros.convert.messages import (  # noqa: E402
    drive_to_msg,
    map_to_msg,
    msg_to_drive,
    msg_to_map,
    msg_to_origin,
    origin_to_msg,
    rclpy_types,
)
from hdmap_ros.io.cdr import decode_drive, encode_drive  # noqa: E402
from hdmap_ros.io.msgdefs import default_typestore  # noqa: E402

from bag_samples import assert_drives_equal, assert_maps_equal, make_drive, make_map  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def types():
    return rclpy_types()


def test_drive_round_trip_on_rclpy_classes(types):
    drive = make_drive("r1", n=30, seed=2)
    msg = drive_to_msg(drive, types=types)
    assert isinstance(msg, hdmap_msgs.Drive)
    assert_drives_equal(drive, msg_to_drive(msg))


def test_map_round_trip_on_rclpy_classes(types):
    hdmap = make_map(seed=3)
    msg = map_to_msg(hdmap, types=types)
    assert isinstance(msg, hdmap_msgs.Map)
    assert isinstance(msg.features[0].drive_count, array.array)
    assert_maps_equal(hdmap, msg_to_map(msg))


def test_origin_on_rclpy_classes(types):
    origin = GeoOrigin(48.1, 11.5, 520.0)
    assert msg_to_origin(origin_to_msg(origin, types=types)) == origin


def test_drive_cdr_agrees_between_rclpy_rosbags_and_fastcdr(types):
    drive = make_drive("cdr", n=25, seed=4)
    rclpy_raw = bytes(serialize_message(drive_to_msg(drive, types=types)))
    rosbags_raw = bytes(default_typestore().serialize_cdr(drive_to_msg(drive), "hdmap_msgs/msg/Drive"))
    assert rosbags_raw == encode_drive(drive)
    # rclpy leaves alignment padding uninitialised, so only the layout (length) is compared
    assert len(rclpy_raw) == len(rosbags_raw)
    assert_drives_equal(drive, decode_drive(rclpy_raw))
    assert_drives_equal(drive, msg_to_drive(deserialize_message(encode_drive(drive), hdmap_msgs.Drive)))


def test_rosbags_map_bytes_deserialize_in_rclpy():
    hdmap = make_map(seed=5)
    raw = bytes(default_typestore().serialize_cdr(map_to_msg(hdmap), "hdmap_msgs/msg/Map"))
    assert_maps_equal(hdmap, msg_to_map(deserialize_message(raw, hdmap_msgs.Map)))


def test_map_status_round_trip_through_cdr():
    from hdmap_core.live.progress import LiveStatus
    from hdmap_ros.convert.messages import msg_to_status, rclpy_status_class, status_to_msg

    st = LiveStatus(
        map_version=7,
        drives_received=30,
        drives_integrated=12,
        drives_rejected=2,
        tiles_pending=5,
        tile_versions=99,
        settled=False,
        stamp_ns=1_700_000_000_123_456_789,
    )
    cls = rclpy_status_class()
    msg = deserialize_message(serialize_message(status_to_msg(st, cls=cls, types=rclpy_types())), cls)
    assert msg_to_status(msg) == st and msg.header.frame_id == "map"


def test_drive_from_wire_reads_cdr_bytes_and_messages_alike_and_names_bad_input():
    from hdmap_core.errors import InvalidDriveError, InvalidMessageError
    from hdmap_ros.nodes._common import drive_from_wire, drive_to_wire

    d = make_drive()
    t = rclpy_types()
    raw = drive_to_wire(d)
    assert_drives_equal(msg_to_drive(deserialize_message(raw, t.Drive)), d)  # rclpy reads what we send
    assert_drives_equal(drive_from_wire(raw, t.Drive, expected_frame="map"), d)
    assert_drives_equal(drive_from_wire(drive_to_msg(d, types=t), t.Drive, expected_frame="map"), d)
    with pytest.raises(InvalidDriveError) as err:
        drive_from_wire(raw, t.Drive, expected_frame="odom")
    assert err.value.reason == "wrong_frame"
    with pytest.raises(InvalidMessageError):
        drive_from_wire(b"\x00\x01\x00\x00garbage", t.Drive, expected_frame=None)
