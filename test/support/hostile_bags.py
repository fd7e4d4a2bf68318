"""Hostile bags the bag and node tests share (not a test module): CRC-checked MCAP files with small
chunks, one whose Drive definition differs from hdmap_msgs', and one holding both definitions."""

from __future__ import annotations

from pathlib import Path

from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from hdmap_core.model import GeoOrigin
from hdmap_ros.convert.messages import drive_to_msg, origin_to_msg
from hdmap_ros.io.bagio import DRIVE_TYPE, DRIVES_TOPIC, ORIGIN_TOPIC, ORIGIN_TYPE
from hdmap_ros.io.cdr import encode_drive
from hdmap_ros.io.msgdefs import default_typestore

from bag_samples import T0_NS, make_drive

ORIGIN = GeoOrigin(48.0, 11.0, 500.0)
_NO_TIME = (QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False)


def small_drives(k: int, n: int = 60) -> list:
    return [make_drive(f"d{i:03d}", n=n, seed=i, start_ns=T0_NS + i * 10**9) for i in range(k)]


def crc_mcap(path: Path, drives: list, *, chunk_size: int = 12_000, drive_def: str | None = None, encode=None) -> Path:
    """A bare .mcap with CRCs and small uncompressed chunks (as the mcap library writes by default)."""
    store = default_typestore()
    msgdef = drive_def or store.generate_msgdef(DRIVE_TYPE, ros_version=2)[0]
    odef, _ = store.generate_msgdef(ORIGIN_TYPE, ros_version=2)
    with path.open("wb") as stream:
        w = McapWriter(stream, chunk_size=chunk_size, compression=CompressionType.NONE, enable_crcs=True)
        w.start(profile="ros2", library="test")
        oid = w.register_channel(ORIGIN_TOPIC, "cdr", w.register_schema(ORIGIN_TYPE, "ros2msg", odef.encode()))
        w.add_message(oid, T0_NS, bytes(store.serialize_cdr(origin_to_msg(ORIGIN, stamp_ns=T0_NS), ORIGIN_TYPE)), T0_NS)
        cid = w.register_channel(DRIVES_TOPIC, "cdr", w.register_schema(DRIVE_TYPE, "ros2msg", msgdef.encode()))
        for d in drives:
            w.add_message(cid, d.start_ns, (encode or encode_drive)(d), d.start_ns)
        w.finish()
    return path


def _without_vehicle_id():
    """A Drive definition lacking ``vehicle_id`` (as embedded in a bag), its typestore, and an encoder
    of drives with it."""
    store = default_typestore()
    full, _ = store.generate_msgdef(DRIVE_TYPE, ros_version=2)
    own, _, rest = full.partition("\n" + "=" * 80 + "\n")
    changed = "\n".join(line for line in own.splitlines() if "vehicle_id" not in line)
    other = get_typestore(Stores.EMPTY)
    other.register({k: v for k, v in store.fielddefs.items() if k != DRIVE_TYPE})
    other.register(get_types_from_msg(changed, DRIVE_TYPE))
    cls = other.types[DRIVE_TYPE]

    def encode(d):
        m = drive_to_msg(d)
        return bytes(
            other.serialize_cdr(
                cls(header=m.header, drive_id=m.drive_id, trajectory=m.trajectory, detections=m.detections), DRIVE_TYPE
            )
        )

    return changed + "\n" + "=" * 80 + "\n" + rest, other, encode


def bag_without_vehicle_id(tmp_path: Path, drives: list) -> Path:
    """A bare .mcap whose Drive definition (and bytes) lack ``vehicle_id``."""
    msgdef, _, encode = _without_vehicle_id()
    return crc_mcap(tmp_path / "nodef.mcap", drives, drive_def=msgdef, encode=encode)


def two_definition_bag(path: Path, good: list, bad: list, *, rosbag2: bool) -> Path:
    """A bag with two ``/fleet/drives`` connections of hdmap_msgs/msg/Drive: ``good`` recorded with the
    contract's definition, ``bad`` with one lacking ``vehicle_id`` (as two recordings merged would
    give); messages in start-time order. ``rosbag2``: a rosbag2 MCAP directory, else a bare .mcap."""
    store = default_typestore()
    bad_def, bad_store, bad_encode = _without_vehicle_id()
    items = sorted([(d, False) for d in good] + [(d, True) for d in bad], key=lambda x: x[0].start_ns)
    origin_cdr = bytes(store.serialize_cdr(origin_to_msg(ORIGIN, stamp_ns=T0_NS), ORIGIN_TYPE))
    if rosbag2:
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            oc = w.add_connection(ORIGIN_TOPIC, ORIGIN_TYPE, typestore=store)
            w.write(oc, T0_NS, origin_cdr)
            # a rosbag2 writer keeps one connection per topic, type and QoS: the second recording's differs
            gc = w.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=store)
            qos = Qos(QosHistory.KEEP_ALL, 0, QosReliability.RELIABLE, QosDurability.VOLATILE, *_NO_TIME)
            bc = w.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=bad_store, offered_qos_profiles=[qos])
            for d, is_bad in items:
                w.write(bc if is_bad else gc, d.start_ns, bad_encode(d) if is_bad else encode_drive(d))
        return path
    good_def, _ = store.generate_msgdef(DRIVE_TYPE, ros_version=2)
    odef, _ = store.generate_msgdef(ORIGIN_TYPE, ros_version=2)
    with path.open("wb") as stream:
        w = McapWriter(stream, chunk_size=12_000, compression=CompressionType.NONE, enable_crcs=True)
        w.start(profile="ros2", library="test")
        oid = w.register_channel(ORIGIN_TOPIC, "cdr", w.register_schema(ORIGIN_TYPE, "ros2msg", odef.encode()))
        w.add_message(oid, T0_NS, origin_cdr, T0_NS)
        gid = w.register_channel(DRIVES_TOPIC, "cdr", w.register_schema(DRIVE_TYPE, "ros2msg", good_def.encode()))
        bid = w.register_channel(DRIVES_TOPIC, "cdr", w.register_schema(DRIVE_TYPE, "ros2msg", bad_def.encode()))
        for d, is_bad in items:
            w.add_message(bid if is_bad else gid, d.start_ns, bad_encode(d) if is_bad else encode_drive(d), d.start_ns)
        w.finish()
    return path


def rechunk(path: Path, *, chunk_size: int = 12_000) -> Path:
    """Rewrite an MCAP file in place with small uncompressed chunks and CRCs (as `ros2 bag record`
    writes), keeping its schemas, channels (with their metadata) and messages."""
    from mcap.reader import make_reader  # noqa: PLC0415

    data = path.read_bytes()
    import io  # noqa: PLC0415

    with path.open("wb") as out:
        w = McapWriter(out, chunk_size=chunk_size, compression=CompressionType.NONE, enable_crcs=True)
        w.start(profile="ros2", library="test")
        sids: dict[int, int] = {}
        cids: dict[int, int] = {}
        for schema, channel, msg in make_reader(io.BytesIO(data)).iter_messages():
            if schema.id not in sids:
                sids[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in cids:
                cids[channel.id] = w.register_channel(
                    channel.topic, channel.message_encoding, sids[schema.id], channel.metadata
                )
            w.add_message(cids[channel.id], msg.log_time, msg.data, msg.publish_time, msg.sequence)
        w.finish()
    return path
