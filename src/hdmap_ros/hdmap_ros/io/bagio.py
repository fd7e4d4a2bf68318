"""Bag I/O: fleet bags (drives + origin) and map bags, read from and written to rosbag2.

Read: rosbag2 directories (MCAP or sqlite3 storage, through rosbags' rosbag2 ``Reader``) and bare
``.mcap`` files (through a record scanner built on the ``mcap`` library). Messages are decoded with
the schemas embedded in the bag, each message with its own connection's (so a bag holding one type
name under two definitions decodes each connection right), and no type has to be registered to
read; a connection without an embedded definition falls back to the hdmap_msgs definitions
(:mod:`hdmap_ros.io.msgdefs`).

Write: rosbag2 MCAP (``rosbags.rosbag2.Writer``, bag version 9) with the hdmap_msgs definitions.

Topics (see docs/bags.md): ``/fleet/drives`` (hdmap_msgs/msg/Drive, one message per drive snippet,
log time = drive start), ``/fleet/origin`` (sensor_msgs/msg/NavSatFix), ``/hdmap/map``
(hdmap_msgs/msg/Map, log time = map stamp).

Bad input never stops a read: a malformed drive is skipped and reported as a :class:`Rejection`
(also a drive whose embedded definition differs from the contract so that it does not convert:
``definition_mismatch``); an MCAP chunk whose content is damaged (CRC, compression) is skipped with
a warning (``damaged_chunk``) and the chunks after it are read; damage to the bag's framing
(truncation) ends the read with :class:`BagError` -- or, in :func:`read_fleet_bag`, with
``FleetBag.error`` set -- after every intact message before the damage was delivered. Whatever a
reader raises on hostile bytes becomes one of these, never a traceback.
"""

from __future__ import annotations

import functools
import shutil
import sqlite3
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

from rosbags.interfaces import (
    Connection,
    MessageDefinitionFormat,
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer, WriterError
from rosbags.serde import SerdeError
from rosbags.typesys import TypesysError
from rosbags.typesys.store import Typestore

from hdmap_core.errors import BagError, InvalidDriveError, InvalidMessageError
from hdmap_core.model import MAP_FRAME, Drive, GeoOrigin, HDMap, validate_drive
from hdmap_ros.convert.messages import drive_to_msg, map_to_msg, msg_to_drive, msg_to_map, msg_to_origin, origin_to_msg
from hdmap_ros.io.cdr import decode_drive, drive_id_of, encode_drive
from hdmap_ros.io.mcapscan import BagMessage, WarningFn, scan_mcap, typestore_of_schema
from hdmap_ros.io.msgdefs import default_typestore

__all__ = [
    "DRIVES_TOPIC",
    "ORIGIN_TOPIC",
    "MAP_TOPIC",
    "DRIVE_TYPE",
    "ORIGIN_TYPE",
    "MAP_TYPE",
    "BagMessage",
    "Rejection",
    "FleetBag",
    "iter_bag",
    "iter_fleet_bag",
    "drive_of_message",
    "has_contract_definition",
    "read_fleet_bag",
    "write_fleet_bag",
    "write_map_bag",
    "read_map_bag",
    "read_bag_origin",
]

DRIVES_TOPIC = "/fleet/drives"
ORIGIN_TOPIC = "/fleet/origin"
MAP_TOPIC = "/hdmap/map"
DRIVE_TYPE = "hdmap_msgs/msg/Drive"
ORIGIN_TYPE = "sensor_msgs/msg/NavSatFix"
MAP_TYPE = "hdmap_msgs/msg/Map"

# Errors a damaged rosbag2 can raise from rosbags' readers (and the storage, YAML and
# decompressors below them); found by fuzzing (test_bag_fuzz.py): KeyError, OverflowError and
# MemoryError (a length field read as gigabytes) among them.
_READ_ERRORS = (
    ReaderError,
    sqlite3.Error,
    struct.error,
    OSError,
    EOFError,
    ValueError,
    IndexError,
    KeyError,
    OverflowError,
    MemoryError,
    TypeError,
    AttributeError,
    UnicodeDecodeError,
    RuntimeError,
    TypesysError,
    SerdeError,
)
# Errors decoding one message can raise: bad CDR, or a schema that does not parse.
_DECODE_ERRORS = (
    SerdeError,
    TypesysError,
    struct.error,
    ValueError,
    IndexError,
    KeyError,
    UnicodeDecodeError,
    OverflowError,
    MemoryError,
    TypeError,
    AttributeError,
    RecursionError,
)
# Converting a message of another definition than the contract's (e.g. a Drive without vehicle_id).
_DEFINITION_ERRORS = (AttributeError, TypeError, ValueError, KeyError, IndexError, OverflowError)


@dataclass(frozen=True)
class Rejection:
    """A message that was skipped, and why.

    Attributes:
        drive_id: the drive's id ("" when the message is not a drive or its id is unreadable).
        reason: short key, e.g. ``non_finite_coordinates``, ``duplicate_drive_id``, ``undecodable``.
        detail: human-readable detail.
        topic, log_time_ns: where the message is in the bag (set by the bag readers).
    """

    drive_id: str
    reason: str
    detail: str = ""
    topic: str = ""
    log_time_ns: int | None = None

    def __str__(self) -> str:
        if self.drive_id:
            what = f"drive {self.drive_id!r}"
        else:
            where = f" at log time {self.log_time_ns}" if self.log_time_ns is not None else ""
            what = f"{self.topic or 'a'} message{where}"
        return f"{what}: {self.reason}" + (f" ({self.detail})" if self.detail else "")


@dataclass(frozen=True)
class FleetBag:
    """What :func:`read_fleet_bag` found.

    Attributes:
        drives: the valid drives, in bag order, first of each drive_id.
        origin: the WGS84 origin of the map frame, None when the bag has none.
        rejected: every skipped message with its reason.
        error: None when the whole bag was read; else what is wrong with the bag (truncated,
            corrupted, unreadable) -- ``drives`` then holds the intact ones before the damage.
        path: the bag read.
    """

    drives: list[Drive]
    origin: GeoOrigin | None
    rejected: list[Rejection]
    error: str | None = None
    path: str = ""

    def summary(self) -> str:
        """A few lines for humans: counts, rejections with reasons, the bag error."""
        lines = [f"{self.path}: {len(self.drives)} valid drive(s), {len(self.rejected)} rejected"]
        lines += [f"  rejected {r}" for r in self.rejected]
        if self.origin is not None:
            o = self.origin
            lines.append(f"  origin lat {o.latitude_deg:.8f} lon {o.longitude_deg:.8f} alt {o.altitude_m:.2f} m")
        if self.error:
            lines.append(f"  bag error: {self.error}")
        return "\n".join(lines)


# ------------------------------------------------------------------------------------ reading


def iter_bag(
    path: str | Path, *, topics: Iterable[str] | None = None, on_warning: WarningFn | None = None
) -> Iterator[BagMessage]:
    """Yield the raw messages of a bag (rosbag2 directory or bare ``.mcap`` file) in bag order.

    rosbag2 directories come in log-time order (rosbags' rosbag2 ``Reader``); ``.mcap`` files in file
    order. A rosbag2 MCAP directory whose file is damaged (e.g. truncated, so its index is gone) and
    a directory without ``metadata.yaml`` are read with the scanner, like bare ``.mcap`` files;
    when the rosbag2 reader fails part way (e.g. a chunk failing its CRC), the scanner delivers the
    messages it had not delivered yet. ``on_warning`` is called with a line for every damaged chunk
    skipped (the rest of the bag is read).

    Raises:
        BagError: the bag does not exist or is not a bag (before anything is yielded), or it is
            damaged (after every intact message before the damage was yielded).
    """
    path = Path(path)
    wanted = None if topics is None else set(topics)
    if not path.exists():
        raise BagError(f"{path}: no such bag (file or directory)")
    if path.is_dir():
        mcaps = sorted(path.glob("*.mcap"))
        if (path / "metadata.yaml").exists():
            yield from _iter_rosbag2(path, wanted, mcaps, on_warning)
        elif mcaps:
            note = "no metadata.yaml (recording not closed?)"
            yield from _iter_mcap_files(mcaps, wanted, note=note, on_warning=on_warning)
        else:
            raise BagError(f"{path}: not a rosbag2 directory (no metadata.yaml and no .mcap file)")
    elif path.suffix == ".mcap":
        yield from _iter_mcap_files([path], wanted, on_warning=on_warning)
    elif path.suffix == ".db3":
        raise BagError(f"{path}: a sqlite3 bag is read through its rosbag2 directory; pass {path.parent}")
    else:
        raise BagError(f"{path}: not a bag (want a rosbag2 directory or a .mcap file)")


def _iter_rosbag2(
    path: Path, wanted: set[str] | None, mcaps: list[Path], on_warning: WarningFn | None
) -> Iterator[BagMessage]:
    try:
        # Not rosbags' AnyReader: its one typestore holds one definition per type name and fails to
        # open a bag holding a type under two definitions (two recordings merged).
        reader = Reader(path)
        reader.open()
    except _READ_ERRORS as err:
        if not mcaps:
            raise BagError(f"{path}: cannot open the bag: {type(err).__name__}: {err}") from err
        # MCAP storage whose index/footer/metadata is damaged: read the records that are intact.
        yield from _iter_mcap_files(mcaps, wanted, note=f"rosbag2 reader: {err}", on_warning=on_warning)
        raise BagError(
            f"{path}: damaged: the rosbag2 reader failed ({type(err).__name__}: {err}); every message was "
            "read from the MCAP records instead"
        ) from err
    count = 0
    seen: set[tuple[str, int, int]] = set()  # what was delivered, should the scanner take over
    failure: BaseException | None = None
    try:
        conns = [c for c in reader.connections if wanted is None or c.topic in wanted]
        # RULE: each connection's messages are decoded with its own embedded definition.
        stores = {id(c): _connection_typestore(c) for c in conns}
        unknown = {id(c): _unknown_definition(c, stores[id(c)]) for c in conns}
        if conns:
            for conn, timestamp, raw in reader.messages(connections=conns):
                data = bytes(raw)
                if mcaps:
                    seen.add((conn.topic, int(timestamp), zlib.crc32(data)))
                yield BagMessage(conn.topic, conn.msgtype, int(timestamp), data, stores[id(conn)], unknown[id(conn)])
                count += 1
    except _READ_ERRORS as err:
        failure = err
    finally:
        try:
            reader.close()
        except _READ_ERRORS:
            pass
    if failure is None:
        return
    if not mcaps:
        raise BagError(f"{path}: damaged after {count} message(s): {type(failure).__name__}: {failure}") from failure
    # RULE: MCAP storage: the scanner goes on past the damage (a chunk failing its CRC is skipped),
    # delivering what the rosbag2 reader had not.
    if on_warning is not None:
        on_warning(
            f"{path}: the rosbag2 reader failed after {count} message(s) ({type(failure).__name__}: "
            f"{failure}); the rest was read record by record"
        )
    for bm in _iter_mcap_files(mcaps, wanted, note=f"rosbag2 reader: {failure}", on_warning=on_warning):
        if (bm.topic, bm.log_time_ns, zlib.crc32(bm.data)) not in seen:
            yield bm


def _connection_typestore(conn: Connection) -> Typestore:
    """The typestore of a rosbag2 connection's embedded definition (the known one without)."""
    fmt = conn.msgdef.format
    if fmt == MessageDefinitionFormat.NONE:
        return default_typestore()
    encoding = "ros2idl" if fmt == MessageDefinitionFormat.IDL else "ros2msg"
    return typestore_of_schema(conn.msgtype, encoding, conn.msgdef.data.encode("utf-8"))


def _unknown_definition(conn: Connection, store: Typestore) -> str:
    """Why the bag lacks this connection's definition ("" when it has it).

    rosbag2 keeps one definition per type name (its storage writes one schema per type) but each
    connection's type hash: a connection recorded with another definition of the type (two
    recordings merged) has a hash that differs from the definition the bag gives. Its bytes are not
    of that definition, so they are not decoded with it."""
    if not conn.digest.startswith("RIHS01_"):
        return ""  # older bags record no hash
    try:
        have = store.hash_rihs01(conn.msgtype)
    except (TypesysError, KeyError, ValueError, TypeError):
        return ""
    if have == conn.digest:
        return ""
    return (
        f"the {conn.topic} connection was recorded with a {conn.msgtype} definition of hash {conn.digest}, "
        f"which the bag does not hold (its definition of the type has hash {have})"
    )


def _iter_mcap_files(
    paths: list[Path], wanted: set[str] | None, *, note: str = "", on_warning: WarningFn | None = None
) -> Iterator[BagMessage]:
    for p in paths:
        yield from scan_mcap(p, wanted, note=note, on_warning=on_warning)


def iter_fleet_bag(
    path: str | Path, *, expected_frame: str | None = MAP_FRAME
) -> Iterator[Drive | GeoOrigin | Rejection]:
    """Stream a fleet bag: valid drives, the origin, and a Rejection for each skipped message.

    Duplicate drive ids: the first is kept, later ones are rejected (``duplicate_drive_id``).
    An origin message that differs from the first one is rejected (``conflicting_origin``).

    Raises:
        BagError: the bag is missing or damaged (after everything intact was yielded).
    """
    seen: set[str] = set()
    origin: GeoOrigin | None = None
    warnings: list[str] = []
    for bm in iter_bag(path, topics=(DRIVES_TOPIC, ORIGIN_TOPIC), on_warning=warnings.append):
        while warnings:
            yield Rejection("", "damaged_chunk", warnings.pop(0))
        if bm.topic == ORIGIN_TOPIC:
            item = _decode_origin(bm)
            if isinstance(item, GeoOrigin):
                if origin is None:
                    origin = item
                elif item != origin:
                    item = Rejection("", "conflicting_origin", f"{item} differs from the first origin {origin}")
                else:
                    continue
        else:
            item = _decode_drive(bm, expected_frame)
            if isinstance(item, Drive):
                if item.drive_id in seen:
                    item = Rejection(
                        item.drive_id, "duplicate_drive_id", "an earlier drive has this id; kept the first"
                    )
                else:
                    seen.add(item.drive_id)
        if isinstance(item, Rejection):
            item = replace(item, topic=bm.topic, log_time_ns=bm.log_time_ns)
        yield item
    while warnings:
        yield Rejection("", "damaged_chunk", warnings.pop(0))


def has_contract_definition(bm: BagMessage) -> bool:
    """True when the bag's definition of the message's type is hdmap_msgs' own (so its bytes read
    the same in any hdmap_msgs subscriber)."""
    return bm.msgtype == DRIVE_TYPE and not bm.unknown_definition and _is_our_drive_definition(bm.typestore)


def drive_of_message(bm: BagMessage, *, expected_frame: str | None = MAP_FRAME) -> Drive | Rejection:
    """One ``/fleet/drives`` message -> a valid Drive, or the Rejection saying why not
    (``undecodable``, ``definition_mismatch``, ``wrong_type`` or a ``validate_drive`` reason)."""
    return _decode_drive(bm, expected_frame)


@functools.lru_cache(maxsize=8)
def _is_our_drive_definition(store: Typestore) -> bool:
    """True when the bag's Drive definition is hdmap_msgs' own (the fast decoder knows its layout)."""
    try:
        return store.hash_rihs01(DRIVE_TYPE) == default_typestore().hash_rihs01(DRIVE_TYPE)
    except (TypesysError, KeyError):
        return False


def _decode_drive(bm: BagMessage, expected_frame: str | None) -> Drive | Rejection:
    if bm.msgtype != DRIVE_TYPE:
        return Rejection("", "wrong_type", f"{bm.topic} carries {bm.msgtype}, want {DRIVE_TYPE}")
    if bm.unknown_definition:
        return Rejection(drive_id_of(bm.data), "definition_mismatch", bm.unknown_definition)
    try:
        fast = decode_drive(bm.data) if _is_our_drive_definition(bm.typestore) else None
        if fast is not None:
            return validate_drive(fast, expected_frame=expected_frame or "")
    except InvalidDriveError as err:
        return Rejection(err.drive_id, err.reason, err.detail)
    try:
        msg = bm.decode()
    except _DECODE_ERRORS as err:
        return Rejection("", "undecodable", f"{type(err).__name__}: {err}")
    try:
        return msg_to_drive(msg, expected_frame=expected_frame)
    except InvalidDriveError as err:
        return Rejection(err.drive_id, err.reason, err.detail)
    except _DEFINITION_ERRORS as err:
        did = getattr(msg, "drive_id", "")
        return Rejection(
            did if isinstance(did, str) else "",
            "definition_mismatch",
            f"the bag's {DRIVE_TYPE} definition differs from hdmap_msgs': {type(err).__name__}: {err}",
        )


def _decode_origin(bm: BagMessage) -> GeoOrigin | Rejection:
    if bm.msgtype != ORIGIN_TYPE:
        return Rejection("", "wrong_type", f"{bm.topic} carries {bm.msgtype}, want {ORIGIN_TYPE}")
    try:
        return msg_to_origin(bm.decode())
    except _DECODE_ERRORS as err:
        return Rejection("", "undecodable", f"origin message: {type(err).__name__}: {err}")
    except InvalidMessageError as err:
        return Rejection("", "invalid_origin", str(err))


def read_fleet_bag(path: str | Path, *, expected_frame: str | None = MAP_FRAME) -> FleetBag:
    """Read every drive and the origin of a fleet bag; never raises for bad content.

    Returns:
        FleetBag with the valid drives, the origin (None if absent), the rejections, and ``error``
        set when the bag is missing, not a bag, truncated or corrupted (then ``drives`` holds the
        intact drives before the damage).
    """
    drives: list[Drive] = []
    rejected: list[Rejection] = []
    origin: GeoOrigin | None = None
    error: str | None = None
    try:
        for item in iter_fleet_bag(path, expected_frame=expected_frame):
            if isinstance(item, Drive):
                drives.append(item)
            elif isinstance(item, Rejection):
                rejected.append(item)
            else:
                origin = item
    except BagError as err:
        error = str(err)
    return FleetBag(drives=drives, origin=origin, rejected=rejected, error=error, path=str(path))


def read_map_bag(path: str | Path) -> HDMap:
    """The last map on ``/hdmap/map`` of a bag; its origin (if the bag has one) in ``extra["origin"]``.

    Raises:
        BagError: the bag is missing/damaged before any map, or holds no map message.
        InvalidMessageError: the last map message is malformed.
    """
    last: BagMessage | None = None
    origin: GeoOrigin | None = None
    damage: BagError | None = None
    try:
        for bm in iter_bag(path, topics=(MAP_TOPIC, ORIGIN_TOPIC)):
            if bm.topic == MAP_TOPIC and bm.msgtype == MAP_TYPE:
                last = bm
            elif bm.topic == ORIGIN_TOPIC and origin is None:
                got = _decode_origin(bm)
                origin = got if isinstance(got, GeoOrigin) else None
    except BagError as err:
        damage = err
    if last is None:
        if damage is not None:
            raise damage
        raise BagError(f"{path}: no {MAP_TYPE} message on {MAP_TOPIC}")
    try:
        hdmap = msg_to_map(last.decode())
    except _DECODE_ERRORS as err:
        raise BagError(f"{path}: the last map message does not decode: {err}") from err
    if origin is not None:
        hdmap.extra["origin"] = origin
    if damage is not None:
        hdmap.extra["bag_error"] = str(damage)
    return hdmap


def read_bag_origin(path: str | Path) -> GeoOrigin | None:
    """The first valid ``/fleet/origin`` of a bag, None if it has none (or it is unreadable)."""
    try:
        for bm in iter_bag(path, topics=(ORIGIN_TOPIC,)):
            got = _decode_origin(bm)
            if isinstance(got, GeoOrigin):
                return got
    except BagError:
        return None
    return None


# ------------------------------------------------------------------------------------ writing

_INFINITE = QosTime(sec=0x7FFFFFFF, nsec=0xFFFFFFFF)  # rosbag2's "infinite" duration


def _qos(*, latched: bool) -> list[Qos]:
    """The offered QoS recorded with a connection (rosbag2 ``offered_qos_profiles``), as the nodes
    publish (``hdmap_ros.nodes.qos``): ``ros2 bag play`` then offers the same (the origin and the
    map latched, TRANSIENT_LOCAL), instead of VOLATILE defaults a latched subscriber cannot match."""
    return [
        Qos(
            history=QosHistory.KEEP_LAST if latched else QosHistory.KEEP_ALL,
            depth=1 if latched else 0,
            reliability=QosReliability.RELIABLE,
            durability=QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
            deadline=_INFINITE,
            lifespan=_INFINITE,
            liveliness=QosLiveliness.AUTOMATIC,
            liveliness_lease_duration=_INFINITE,
            avoid_ros_namespace_conventions=False,
        )
    ]


_LATCHED, _STREAM = _qos(latched=True), _qos(latched=False)


def _open_writer(path: Path, *, overwrite: bool) -> Writer:
    if path.exists():
        if not overwrite:
            raise BagError(f"{path}: exists already; not overwriting (choose another path)")
        if not (path.is_dir() and (path / "metadata.yaml").exists()):
            raise BagError(f"{path}: exists and is not a rosbag2 directory; refusing to replace it")
        shutil.rmtree(path)
    try:
        writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
    except (WriterError, OSError) as err:
        raise BagError(f"{path}: cannot create the bag: {err}") from err
    return writer


def write_fleet_bag(
    path: str | Path,
    drives: Iterable[Drive],
    origin: GeoOrigin | None,
    *,
    overwrite: bool = False,
    start_ns: int | None = None,
) -> Path:
    """Write a rosbag2 MCAP fleet bag: the origin, then one ``/fleet/drives`` message per drive.

    Drives are written as given (no validation), in the given order, with log time = drive start
    (a drive with no poses gets the previous log time). ``overwrite`` replaces an existing
    rosbag2 directory. ``start_ns``: the log time of the origin (default: the earliest drive
    start); given, the drives are streamed, one at a time, never all held.

    Returns:
        the bag directory.

    Raises:
        BagError: the path exists (and not ``overwrite``) or cannot be written.
    """
    path = Path(path)
    if start_ns is None:
        drives = list(drives)
    store = default_typestore()
    writer = _open_writer(path, overwrite=overwrite)
    try:
        first_ns = (
            start_ns if start_ns is not None else min((d.start_ns for d in drives if len(d.stamps_ns)), default=0)
        )
        if origin is not None:
            conn = writer.add_connection(ORIGIN_TOPIC, ORIGIN_TYPE, typestore=store, offered_qos_profiles=_LATCHED)
            msg = origin_to_msg(origin, stamp_ns=first_ns)
            writer.write(conn, first_ns, store.serialize_cdr(msg, ORIGIN_TYPE))
        conn = writer.add_connection(DRIVES_TOPIC, DRIVE_TYPE, typestore=store, offered_qos_profiles=_STREAM)
        t_ns = first_ns
        for drive in drives:
            t_ns = drive.start_ns if len(drive.stamps_ns) else t_ns
            writer.write(conn, t_ns, _drive_cdr(drive, store))
    finally:
        writer.close()
    return path


def _drive_cdr(drive: Drive, store: Typestore) -> bytes:
    try:
        return encode_drive(drive)  # byte-identical to the generic path, ~50x faster
    except ValueError:
        return bytes(store.serialize_cdr(drive_to_msg(drive), DRIVE_TYPE))


def write_map_bag(
    path: str | Path,
    hdmap: HDMap | Iterable[HDMap],
    origin: GeoOrigin | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Write a rosbag2 MCAP map bag: the origin (if given) and the map(s) on ``/hdmap/map``.

    ``hdmap`` may be one map or a sequence of map versions; log time = each map's ``stamp_ns``.

    Raises:
        BagError: the path exists (and not ``overwrite``) or cannot be written.
        InvalidMessageError: a map does not fit the message (e.g. an id outside uint64).
    """
    path = Path(path)
    maps = [hdmap] if isinstance(hdmap, HDMap) else list(hdmap)
    msgs = [map_to_msg(m) for m in maps]  # convert first: a bad map leaves no half-written bag
    store = default_typestore()
    writer = _open_writer(path, overwrite=overwrite)
    try:
        first_ns = min((m.stamp_ns for m in maps), default=0)
        if origin is not None:
            conn = writer.add_connection(ORIGIN_TOPIC, ORIGIN_TYPE, typestore=store, offered_qos_profiles=_LATCHED)
            writer.write(conn, first_ns, store.serialize_cdr(origin_to_msg(origin, stamp_ns=first_ns), ORIGIN_TYPE))
        conn = writer.add_connection(MAP_TOPIC, MAP_TYPE, typestore=store, offered_qos_profiles=_LATCHED)
        for m, msg in zip(maps, msgs, strict=True):
            writer.write(conn, int(m.stamp_ns), store.serialize_cdr(msg, MAP_TYPE))
    finally:
        writer.close()
    return path
