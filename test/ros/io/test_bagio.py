"""Fleet and map bags: round trips, bad messages, damaged bags, storage variants (no rclpy)."""

from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Writer
from rosbags.typesys import Stores, get_typestore

from hdmap_core.errors import BagError
from hdmap_core.model import Detection, FeatureType, GeoOrigin
from hdmap_ros.convert.messages import drive_to_msg, origin_to_msg
from hdmap_ros.io import bagio
from hdmap_ros.io.bagio import (
    DRIVE_TYPE,
    DRIVES_TOPIC,
    ORIGIN_TOPIC,
    ORIGIN_TYPE,
    Rejection,
    iter_bag,
    iter_fleet_bag,
    read_bag_origin,
    read_fleet_bag,
    read_map_bag,
    write_fleet_bag,
    write_map_bag,
)
from hdmap_ros.io.msgdefs import default_typestore

from bag_samples import T0_NS, assert_drives_equal, assert_maps_equal, make_drive, make_map

ORIGIN = GeoOrigin(57.70887, 11.97456, 12.0)


def _drives(k: int, *, n: int = 40) -> list:
    return [make_drive(f"d{i:03d}", n=n, seed=i, start_ns=T0_NS + i * 10**9) for i in range(k)]


def _mcap_of(bag: Path) -> Path:
    (mcap,) = bag.glob("*.mcap")
    return mcap


def test_fleet_round_trip(tmp_path):
    drives = _drives(5)
    write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    got = read_fleet_bag(tmp_path / "fleet")
    assert got.error is None and got.rejected == []
    assert got.origin == ORIGIN
    assert [d.drive_id for d in got.drives] == [d.drive_id for d in drives]
    for a, b in zip(drives, got.drives):
        assert_drives_equal(a, b)


def test_fleet_bag_has_the_documented_topics_and_types(tmp_path):
    write_fleet_bag(tmp_path / "fleet", _drives(2), ORIGIN)
    seen = [(m.topic, m.msgtype) for m in iter_bag(tmp_path / "fleet")]
    assert seen == [(ORIGIN_TOPIC, ORIGIN_TYPE), (DRIVES_TOPIC, DRIVE_TYPE), (DRIVES_TOPIC, DRIVE_TYPE)]


def test_map_round_trip_last_map_and_origin(tmp_path):
    v1, v2 = make_map(seed=1), replace(make_map(seed=2), version=8, stamp_ns=T0_NS + 10**9)
    write_map_bag(tmp_path / "map", [v1, v2], ORIGIN)
    got = read_map_bag(tmp_path / "map")
    assert_maps_equal(v2, got)
    assert got.extra["origin"] == ORIGIN
    assert read_bag_origin(tmp_path / "map") == ORIGIN


def test_read_map_bag_without_map_is_a_clear_error(tmp_path):
    write_fleet_bag(tmp_path / "fleet", _drives(1), ORIGIN)
    with pytest.raises(BagError, match="no hdmap_msgs/msg/Map message"):
        read_map_bag(tmp_path / "fleet")


def test_bad_messages_are_skipped_counted_and_named(tmp_path):
    good = _drives(3)
    nan_xy = make_drive("nan-xy", n=10)
    nan_xy.xy[3, 0] = np.nan  # a fresh array of this test's own drive
    bad = [
        nan_xy,
        replace(make_drive("short-det", n=10), detections=(Detection(FeatureType.SOLID, np.zeros((1, 2))),)),
        replace(make_drive("empty", n=10), xy=np.zeros((0, 2)), yaw=np.zeros(0), stamps_ns=np.zeros(0, np.int64)),
        replace(make_drive("odd-type", n=10), detections=(Detection(7, np.zeros((3, 2))),)),
        replace(make_drive("other-frame", n=10), frame_id="odom"),
        replace(good[1], vehicle_id="someone else"),  # duplicate id: the first one is kept
    ]
    order = [good[0], bad[0], bad[1], good[1], bad[2], bad[3], bad[4], good[2], bad[5]]
    # Bags are read in log-time order (= drive start): give the drives increasing starts.
    order = [
        replace(d, stamps_ns=np.asarray(d.stamps_ns) - d.start_ns + T0_NS + i * 10**9) if len(d.stamps_ns) else d
        for i, d in enumerate(order)
    ]
    write_fleet_bag(tmp_path / "fleet", order, ORIGIN)
    got = read_fleet_bag(tmp_path / "fleet")
    assert got.error is None
    assert [d.drive_id for d in got.drives] == ["d000", "d001", "d002"]
    assert got.drives[1].vehicle_id == good[1].vehicle_id  # the first d001, not the duplicate
    assert [(r.drive_id, r.reason) for r in got.rejected] == [
        ("nan-xy", "non_finite_coordinates"),
        ("short-det", "too_few_points"),
        ("empty", "empty_trajectory"),
        ("odd-type", "unknown_type"),
        ("other-frame", "wrong_frame"),
        ("d001", "duplicate_drive_id"),
    ]
    assert "other-frame" in got.summary() and "wrong_frame" in got.summary()


def test_expected_frame_option(tmp_path):
    write_fleet_bag(tmp_path / "fleet", [replace(make_drive("o", n=5), frame_id="odom")], None)
    assert [d.drive_id for d in read_fleet_bag(tmp_path / "fleet", expected_frame="odom").drives] == ["o"]
    assert read_fleet_bag(tmp_path / "fleet").drives == []


def _big_bag(tmp_path: Path, k: int = 24) -> tuple[Path, list]:
    # ~90 kB per drive: rosbags closes a chunk every 1 MB, so the bag has several chunks.
    drives = _drives(k, n=800)
    bag = write_fleet_bag(tmp_path / "big", drives, ORIGIN)
    return bag, drives


def test_truncated_bag_gives_clear_error_and_intact_drives(tmp_path):
    bag, drives = _big_bag(tmp_path)
    mcap = _mcap_of(bag)
    data = mcap.read_bytes()
    assert len(data) > 1.5 * 2**20  # at least two chunks
    mcap.write_bytes(data[: int(len(data) * 0.6)])
    got = read_fleet_bag(bag)
    assert got.error is not None and "truncated" in got.error and str(mcap) in got.error
    assert 5 < len(got.drives) < len(drives)
    for a, b in zip(drives, got.drives):
        assert_drives_equal(a, b)
    assert got.origin == ORIGIN


def test_bag_missing_only_its_footer_still_yields_every_drive(tmp_path):
    bag, drives = _big_bag(tmp_path, k=3)
    mcap = _mcap_of(bag)
    mcap.write_bytes(mcap.read_bytes()[:-20])
    got = read_fleet_bag(bag)
    assert got.error is not None and "truncated" in got.error
    assert [d.drive_id for d in got.drives] == [d.drive_id for d in drives]


def test_corrupted_bytes_do_not_crash_the_read(tmp_path):
    bag, drives = _big_bag(tmp_path, k=6)
    mcap = _mcap_of(bag)
    data = bytearray(mcap.read_bytes())
    rng = np.random.default_rng(0)
    middle = len(data) // 2
    data[middle : middle + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
    mcap.write_bytes(bytes(data))
    got = read_fleet_bag(bag)
    by_id = {d.drive_id: d for d in drives}
    # Whatever was read is exactly what was written; the damage is reported, not raised.
    for d in got.drives:
        assert_drives_equal(by_id[d.drive_id], d)
    assert len(got.drives) < len(drives)
    assert got.error is not None or got.rejected


def test_bare_mcap_file(tmp_path):
    drives = _drives(4)
    bag = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    bare = tmp_path / "bare.mcap"
    shutil.copy(_mcap_of(bag), bare)
    got = read_fleet_bag(bare)
    assert got.error is None and got.origin == ORIGIN
    for a, b in zip(drives, got.drives, strict=True):
        assert_drives_equal(a, b)


def test_directory_without_metadata_is_read_from_its_mcap(tmp_path):
    drives = _drives(2)
    bag = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    (bag / "metadata.yaml").unlink()
    got = read_fleet_bag(bag)
    assert [d.drive_id for d in got.drives] == ["d000", "d001"]
    assert got.error is None


def test_sqlite3_rosbag2(tmp_path):
    drives = _drives(3)
    store = default_typestore()
    with Writer(tmp_path / "sq", version=9) as writer:  # default storage: sqlite3
        oc = writer.add_connection(ORIGIN_TOPIC, ORIGIN_TYPE, typestore=store)
        writer.write(oc, T0_NS, store.serialize_cdr(origin_to_msg(ORIGIN), ORIGIN_TYPE))
        dc = writer.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=store)
        for d in drives:
            writer.write(dc, d.start_ns, store.serialize_cdr(drive_to_msg(d), DRIVE_TYPE))
    assert list((tmp_path / "sq").glob("*.db3"))
    got = read_fleet_bag(tmp_path / "sq")
    assert got.error is None and got.origin == ORIGIN
    for a, b in zip(drives, got.drives, strict=True):
        assert_drives_equal(a, b)


@pytest.mark.parametrize("bare", [False, True])
def test_reading_uses_the_schemas_embedded_in_the_bag(tmp_path, monkeypatch, bare):
    drives = _drives(2)
    bag = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    path = _mcap_of(bag) if bare else bag
    # No hdmap_msgs types known to the reader: only the bag's own schemas can decode the drives.
    monkeypatch.setattr(bagio, "default_typestore", lambda: get_typestore(Stores.ROS2_JAZZY))
    got = read_fleet_bag(path)
    assert got.error is None
    for a, b in zip(drives, got.drives, strict=True):
        assert_drives_equal(a, b)


@pytest.mark.parametrize("name", ["missing", "plain.txt", "emptydir"])
def test_not_a_bag_is_an_error_not_a_crash(tmp_path, name):
    (tmp_path / "plain.txt").write_text("hello")
    (tmp_path / "emptydir").mkdir()
    got = read_fleet_bag(tmp_path / name)
    assert got.drives == [] and got.error and name in got.error


def test_not_an_mcap_file(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"definitely not mcap")
    with pytest.raises(BagError, match="bad magic"):
        list(iter_bag(tmp_path / "x.mcap"))


def test_write_refuses_to_overwrite_unless_asked(tmp_path):
    write_fleet_bag(tmp_path / "fleet", _drives(1), ORIGIN)
    with pytest.raises(BagError, match="exists"):
        write_fleet_bag(tmp_path / "fleet", _drives(2), ORIGIN)
    write_fleet_bag(tmp_path / "fleet", _drives(2), ORIGIN, overwrite=True)
    assert len(read_fleet_bag(tmp_path / "fleet").drives) == 2
    (tmp_path / "file").write_text("x")
    with pytest.raises(BagError, match="not a rosbag2 directory"):
        write_fleet_bag(tmp_path / "file", _drives(1), ORIGIN, overwrite=True)


def test_iter_fleet_bag_streams_in_bag_order_and_flags_conflicting_origin(tmp_path):
    store = default_typestore()
    with Writer(tmp_path / "two", version=9) as writer:
        oc = writer.add_connection(ORIGIN_TOPIC, ORIGIN_TYPE, typestore=store)
        dc = writer.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=store)
        writer.write(oc, 1, store.serialize_cdr(origin_to_msg(ORIGIN), ORIGIN_TYPE))
        writer.write(dc, 2, store.serialize_cdr(drive_to_msg(make_drive("a", n=5)), DRIVE_TYPE))
        writer.write(oc, 3, store.serialize_cdr(origin_to_msg(replace(ORIGIN, latitude_deg=1.0)), ORIGIN_TYPE))
    items = list(iter_fleet_bag(tmp_path / "two"))
    assert items[0] == ORIGIN
    assert items[1].drive_id == "a"
    assert isinstance(items[2], Rejection) and items[2].reason == "conflicting_origin"


@pytest.mark.slow
def test_baginfo_describes_drives_rejections_and_damage(tmp_path, capsys):
    from hdmap_ros.io.baginfo import main

    bad = replace(make_drive("zz-bad", n=5, start_ns=T0_NS + 10**10), frame_id="odom")
    bag = write_fleet_bag(tmp_path / "fleet", _drives(2) + [bad], ORIGIN)
    assert main([str(bag), "--drives"]) == 0
    out = capsys.readouterr().out
    assert "/fleet/drives" in out and "hdmap_msgs/msg/Drive" in out and "3 msgs" in out
    assert "d000" in out and "d001" in out and "rejected drive 'zz-bad': wrong_frame" in out
    mcap = _mcap_of(bag)
    mcap.write_bytes(mcap.read_bytes()[:-100])
    assert main([str(bag)]) == 1
    assert "DAMAGED:" in capsys.readouterr().out
    assert main([str(tmp_path / "missing")]) == 1


@pytest.mark.parametrize("name", ["e6mini_20", "ramps_20"])
def test_sample_fleet_bags_read_cleanly(name, sample_bags):
    got = read_fleet_bag(sample_bags / name)
    assert got.error is None and got.rejected == [] and got.origin is not None
    assert len(got.drives) == 20 and len({d.drive_id for d in got.drives}) == 20
    assert 10.0 < sum(d.length_m for d in got.drives) / 1000.0 < 13.0  # bags/README.md: 11.6 km


def test_sample_bad_inputs_bag_is_as_documented(sample_bags):
    got = read_fleet_bag(sample_bags / "bad_inputs")
    assert got.error is None and len(got.drives) == 4
    assert [(r.drive_id, r.reason) for r in got.rejected] == [
        ("bad-nan-trajectory", "non_finite_coordinates"),
        ("bad-inf-detection", "non_finite_coordinates"),
        ("bad-short-detection", "too_few_points"),
        ("bad-empty-trajectory", "empty_trajectory"),
        ("bad-one-pose", "too_few_points"),
        ("bad-unknown-type", "unknown_type"),
        ("bad-wrong-frame", "wrong_frame"),
        ("bad-nan-heading", "bad_quaternion"),
        ("", "empty_drive_id"),
        ("motorway_s7_0001", "duplicate_drive_id"),
        ("", "undecodable"),
    ]
    cut = read_fleet_bag(sample_bags / "bad_inputs_truncated.mcap")
    assert "truncated" in cut.error
    assert [d.drive_id for d in cut.drives] == [d.drive_id for d in got.drives[:2]]
    assert len(cut.rejected) == 8 and cut.origin == got.origin


def test_broken_metadata_yaml_reads_every_drive_and_says_so(tmp_path):
    drives = _drives(3)
    bag = write_fleet_bag(tmp_path / "fleet", drives, ORIGIN)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [")
    got = read_fleet_bag(bag)
    assert got.error is not None and "rosbag2 reader failed" in got.error and "metadata.yaml" in got.error
    for a, b in zip(drives, got.drives, strict=True):
        assert_drives_equal(a, b)


def test_zstd_compressed_mcap_reads_as_directory_and_bare_file(tmp_path):
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin

    drives = _drives(3)
    store = default_typestore()
    writer = Writer(tmp_path / "z", version=9, storage_plugin=StoragePlugin.MCAP)
    writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    with writer:
        dc = writer.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=store)
        for d in drives:
            writer.write(dc, d.start_ns, store.serialize_cdr(drive_to_msg(d), DRIVE_TYPE))
    mcap = _mcap_of(tmp_path / "z")
    assert b"zstd" in mcap.read_bytes()[:400]
    for path in (tmp_path / "z", mcap):
        got = read_fleet_bag(path)
        assert got.error is None
        for a, b in zip(drives, got.drives, strict=True):
            assert_drives_equal(a, b)


@pytest.mark.parametrize("compression", ["NONE", "LZ4", "ZSTD"])
def test_mcap_from_another_writer_with_small_chunks_and_crcs(tmp_path, compression):
    """A bare .mcap as other tools write it (mcap library: CRCs, small compressed chunks), then cut."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    from hdmap_ros.io.cdr import encode_drive

    drives = _drives(12, n=200)
    msgdef, _ = default_typestore().generate_msgdef(DRIVE_TYPE, ros_version=2)
    path = tmp_path / "other.mcap"
    with path.open("wb") as stream:
        w = McapWriter(stream, chunk_size=20_000, compression=CompressionType[compression])
        w.start(profile="ros2", library="test")
        sid = w.register_schema(DRIVE_TYPE, "ros2msg", msgdef.encode())
        cid = w.register_channel(DRIVES_TOPIC, "cdr", sid)
        for d in drives:
            w.add_message(cid, d.start_ns, encode_drive(d), d.start_ns)
        w.finish()
    got = read_fleet_bag(path)
    assert got.error is None
    for a, b in zip(drives, got.drives, strict=True):
        assert_drives_equal(a, b)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    cut = read_fleet_bag(path)
    assert "truncated" in cut.error and 2 <= len(cut.drives) < len(drives)
    for a, b in zip(drives, cut.drives):
        assert_drives_equal(a, b)
