"""The vectorised Drive decoder agrees with rosbags' generic deserializer, or declines."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hdmap_core.model import Detection, FeatureType
from hdmap_ros.convert.messages import drive_to_msg, msg_to_drive
from hdmap_ros.io.cdr import decode_drive
from hdmap_ros.io.msgdefs import default_typestore

from bag_samples import assert_drives_equal, make_drive

DRIVE = "hdmap_msgs/msg/Drive"


def _raw(drive_or_msg) -> bytes:
    msg = drive_or_msg if hasattr(drive_or_msg, "trajectory") else drive_to_msg(drive_or_msg)
    return bytes(default_typestore().serialize_cdr(msg, DRIVE))


@pytest.mark.parametrize("drive_id", ["a", "ab", "abc", "abcd", "abcde", "drive-0123456", "ü-umlaut"])
@pytest.mark.parametrize("frame", ["map", "m", "mapframe", ""])
@pytest.mark.parametrize("n", [2, 3, 7])
def test_agrees_with_generic_path_for_every_alignment(drive_id, frame, n):
    drive = replace(make_drive(drive_id, n=max(n, 2), seed=n), frame_id=frame, vehicle_id=drive_id[:n])
    drive = replace(drive, xy=drive.xy[:n], yaw=drive.yaw[:n], stamps_ns=drive.stamps_ns[:n])
    raw = _raw(drive)
    generic = msg_to_drive(default_typestore().deserialize_cdr(raw, DRIVE), expected_frame=None)
    fast = decode_drive(raw)
    assert fast is not None
    assert_drives_equal(generic, fast)


def test_empty_and_odd_detections():
    dets = (
        Detection(FeatureType.SOLID, np.zeros((0, 2))),
        Detection(FeatureType.DASHED, np.ones((1, 2))),
        Detection(9, np.arange(6.0).reshape(3, 2)),
    )
    drive = replace(make_drive("x", n=3), detections=dets)
    fast = decode_drive(_raw(drive))
    assert [int(d.type) for d in fast.detections] == [1, 2, 9]
    np.testing.assert_array_equal(fast.detections[2].points, dets[2].points)
    empty = replace(drive, xy=np.zeros((0, 2)), yaw=np.zeros(0), stamps_ns=np.zeros(0, np.int64), detections=())
    assert len(decode_drive(_raw(empty)).xy) == 0
    one = replace(drive, xy=drive.xy[:1], yaw=drive.yaw[:1], stamps_ns=drive.stamps_ns[:1])
    got = decode_drive(_raw(one))
    np.testing.assert_array_equal(got.xy, one.xy)
    np.testing.assert_array_equal(got.stamps_ns, one.stamps_ns)


def test_declines_mixed_frames_and_damage():
    msg = drive_to_msg(make_drive("x", n=6))
    msg.trajectory.poses[3].header.frame_id = "odom"
    assert decode_drive(_raw(msg)) is None
    raw = _raw(make_drive("y", n=6))
    assert decode_drive(raw[:-30]) is None
    assert decode_drive(raw + b"\x00" * 16) is None
    assert decode_drive(b"\x00\x00" + raw[2:]) is None  # big endian: generic path


@pytest.mark.parametrize("drive_id", ["a", "abcd", "drive-0123456", "ü"])
@pytest.mark.parametrize("frame", ["map", "mapframe", ""])
@pytest.mark.parametrize("n", [0, 1, 2, 5])
def test_encoder_is_byte_identical_to_rosbags(drive_id, frame, n):
    from hdmap_ros.io.cdr import encode_drive

    drive = replace(make_drive(drive_id, n=6, seed=n), frame_id=frame)
    drive = replace(drive, xy=drive.xy[:n], yaw=drive.yaw[:n], stamps_ns=drive.stamps_ns[:n])
    drive = replace(drive, detections=drive.detections + (Detection(FeatureType.SOLID, np.zeros((0, 2))),))
    assert encode_drive(drive) == _raw(drive)


@pytest.mark.parametrize("frame", ["map", "m", "mapframe", ""])
@pytest.mark.parametrize("n_points", [1, 2, 3, 30])
@pytest.mark.parametrize("drive_ids", [(), ("a",), ("a", "bc", "def")])
def test_map_encoder_is_byte_identical_to_rosbags(frame, n_points, drive_ids):
    """Every alignment case: odd point counts (the uint16 and float32 arrays end off 8),
    features and nodes without predecessors, successors or features, empty drive ids."""
    from hdmap_ros.convert.messages import map_to_msg
    from hdmap_ros.io.cdr import encode_map

    from bag_samples import make_map

    m = replace(make_map(n_features=5, n_points=n_points, seed=n_points), frame_id=frame, drive_ids=drive_ids)
    m = replace(m, features=(*m.features, replace(m.features[0], id=3, predecessors=(), successors=())))
    m = replace(m, topology=(*m.topology, replace(m.topology[0], id=99, successors=(), features=())))
    assert encode_map(m) == bytes(default_typestore().serialize_cdr(map_to_msg(m), "hdmap_msgs/msg/Map"))
    assert encode_map(replace(m, features=(), topology=())) == bytes(
        default_typestore().serialize_cdr(map_to_msg(replace(m, features=(), topology=())), "hdmap_msgs/msg/Map")
    )


def test_map_encoder_refuses_what_map_to_msg_refuses():
    from hdmap_core.errors import InvalidMessageError
    from hdmap_ros.io.cdr import encode_map

    from bag_samples import make_map

    m = make_map()
    with pytest.raises(InvalidMessageError):
        encode_map(replace(m, features=(replace(m.features[0], id=2**64),)))
    with pytest.raises(InvalidMessageError):
        encode_map(replace(m, features=(replace(m.features[0], drive_count=m.features[0].drive_count[1:]),)))
