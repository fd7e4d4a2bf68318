"""Read an MCAP file record by record from its start, without needing its index or footer.

Used for bare ``.mcap`` files and for rosbag2 MCAP files whose summary is damaged (e.g. a
truncated recording): every complete record before the damage is delivered -- also the complete
records of a cut-off uncompressed chunk -- and then :class:`~hdmap_core.errors.BagError` says where
and what the damage is. Records are framed here and parsed with the ``mcap`` library; messages are
decoded with rosbags from the schemas embedded in the file.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from io import BytesIO
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel as McapChannel
from mcap.records import Chunk as McapChunk
from mcap.records import Message as McapMessage
from mcap.records import Schema as McapSchema
from mcap.stream_reader import CRCValidationError, get_chunk_data_stream
from rosbags.typesys import Stores, TypesysError, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from hdmap_core.errors import BagError
from hdmap_ros.io.msgdefs import default_typestore

__all__ = ["BagMessage", "scan_mcap"]

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")  # opcode, body length


@dataclass(frozen=True)
class BagMessage:
    """One raw message of a bag.

    Attributes:
        topic, msgtype: where it was recorded and its ROS type name.
        log_time_ns: the bag's log (receive) time [ns].
        data: the serialized CDR bytes (what a raw publisher sends).
        typestore: a rosbags typestore that knows ``msgtype`` (from the bag's own schemas).
    """

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes
    typestore: Typestore = field(repr=False, compare=False)

    def decode(self) -> Any:
        """Deserialize into a rosbags message object."""
        return self.typestore.deserialize_cdr(self.data, self.msgtype)


class _McapScanner:
    """Read an MCAP file record by record, from the start, without its index.

    Complete records before any damage are delivered (also the complete records of a truncated
    uncompressed chunk); the damage then raises :class:`BagError` saying where and what.
    """

    def __init__(self, path: Path, wanted: set[str] | None, *, note: str = "") -> None:
        self.path = path
        self.wanted = wanted
        self.note = note
        self.schemas: dict[int, McapSchema] = {}
        self.channels: dict[int, McapChannel] = {}
        self.typestore: Typestore | None = None
        self.count = 0

    def _fail(self, what: str) -> BagError:
        text = f"{self.path}: {what}; the {self.count} message(s) before the damage were read"
        if self.note:
            text += f" [{self.note}]"
        return BagError(text)

    def messages(self) -> Iterator[BagMessage]:
        try:
            data = self.path.read_bytes()
        except OSError as err:
            raise BagError(f"{self.path}: cannot read: {err}") from err
        if not data.startswith(_MCAP_MAGIC):
            raise BagError(f"{self.path}: not an MCAP file (bad magic)")
        view = memoryview(data)
        pos, end = len(_MCAP_MAGIC), len(data)
        while True:
            if pos == end:
                raise self._fail(f"truncated: file ends at byte {end} without an MCAP footer")
            if pos + _RECORD_HEADER.size > end:
                raise self._fail(f"truncated: a record header at byte {pos} is cut off (file is {end} B)")
            opcode, length = _RECORD_HEADER.unpack_from(view, pos)
            body = view[pos + _RECORD_HEADER.size : pos + _RECORD_HEADER.size + length]
            if len(body) < length:
                if opcode == Opcode.CHUNK:
                    yield from self._salvage_chunk(body)
                raise self._fail(
                    f"truncated (or corrupted): {_opname(opcode)} record at byte {pos} needs {length} B, "
                    f"only {len(body)} B present (file is {end} B)"
                )
            if opcode == Opcode.FOOTER:
                if bytes(view[pos + _RECORD_HEADER.size + length :]) != _MCAP_MAGIC:
                    raise self._fail("corrupted: bad magic after the footer")
                return
            if opcode == Opcode.CHUNK:
                yield from self._chunk(body, pos)
            else:
                yield from self._record(opcode, body, pos)
            pos += _RECORD_HEADER.size + length

    def _record(self, opcode: int, body: memoryview, pos: int) -> Iterator[BagMessage]:
        stream = ReadDataStream(BytesIO(body))
        try:
            if opcode == Opcode.SCHEMA:
                schema = McapSchema.read(stream)
                self.schemas[schema.id] = schema
                self.typestore = None  # rebuilt with the new schema when needed
            elif opcode == Opcode.CHANNEL:
                channel = McapChannel.read(stream)
                self.channels[channel.id] = channel
            elif opcode == Opcode.MESSAGE:
                msg = McapMessage.read(stream, len(body))
                out = self._message(msg, pos)
                if out is not None:
                    self.count += 1
                    yield out
        except (McapError, struct.error, UnicodeDecodeError) as err:
            raise self._fail(f"corrupted {_opname(opcode)} record at byte {pos}: {err}") from err

    def _message(self, msg: McapMessage, pos: int) -> BagMessage | None:
        channel = self.channels.get(msg.channel_id)
        if channel is None:
            raise self._fail(f"corrupted: message at byte {pos} on unknown channel {msg.channel_id}")
        if self.wanted is not None and channel.topic not in self.wanted:
            return None
        if channel.message_encoding != "cdr":
            raise self._fail(f"channel {channel.topic!r} has encoding {channel.message_encoding!r}, want cdr")
        schema = self.schemas.get(channel.schema_id)
        msgtype = schema.name if schema is not None else ""
        if not msgtype:
            raise self._fail(f"channel {channel.topic!r} has no schema, its message type is unknown")
        return BagMessage(channel.topic, msgtype, int(msg.log_time), bytes(msg.data), self._typestore())

    def _typestore(self) -> Typestore:
        if self.typestore is None:
            store = default_typestore()
            types: dict = {}
            for schema in self.schemas.values():
                # No (or a damaged) embedded definition: rely on the hdmap_msgs / Jazzy types; a
                # message that then does not decode is rejected on its own.
                try:
                    text = bytes(schema.data).decode("utf-8")
                    if schema.encoding == "ros2msg" and text:
                        types.update(get_types_from_msg(text, schema.name))
                    elif schema.encoding == "ros2idl" and text:
                        types.update(get_types_from_idl(text))
                except (TypesysError, UnicodeDecodeError, ValueError):
                    continue
            # A fresh store of the bag's own definitions, on top of the known ones for missing ones.
            fresh = get_typestore(Stores.EMPTY)
            fresh.register({k: v for k, v in store.fielddefs.items() if k not in types})
            fresh.register(types)
            self.typestore = fresh
        return self.typestore

    def _chunk(self, body: memoryview, pos: int) -> Iterator[BagMessage]:
        try:
            chunk = McapChunk.read(ReadDataStream(BytesIO(body)))
            stream, size = get_chunk_data_stream(chunk, validate_crc=True)
            inner = stream.read(size) if size else b""
        except (McapError, CRCValidationError, struct.error, ValueError, RuntimeError) as err:
            raise self._fail(f"corrupted chunk at byte {pos}: {type(err).__name__}: {err}") from err
        yield from self._inner_records(memoryview(inner), pos, partial=False)

    def _salvage_chunk(self, body: memoryview) -> Iterator[BagMessage]:
        """The complete records of a truncated, uncompressed chunk."""
        head = struct.Struct("<QQQII")
        if len(body) < head.size:
            return
        *_, comp_len = head.unpack_from(body, 0)
        start = head.size + comp_len + 8  # compression string, then the u64 records length
        if comp_len != 0 or len(body) < start:
            return  # compressed: nothing can be recovered from a partial stream
        yield from self._inner_records(body[start:], -1, partial=True)

    def _inner_records(self, data: memoryview, chunk_pos: int, *, partial: bool) -> Iterator[BagMessage]:
        pos, end = 0, len(data)
        while pos < end:
            if pos + _RECORD_HEADER.size > end:
                if partial:
                    return
                raise self._fail(f"corrupted chunk at byte {chunk_pos}: record header cut off")
            opcode, length = _RECORD_HEADER.unpack_from(data, pos)
            body = data[pos + _RECORD_HEADER.size : pos + _RECORD_HEADER.size + length]
            if len(body) < length:
                if partial:
                    return
                raise self._fail(f"corrupted chunk at byte {chunk_pos}: a record overruns the chunk")
            yield from self._record(opcode, body, chunk_pos)
            pos += _RECORD_HEADER.size + length


def _opname(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"opcode 0x{opcode:02x}"


def scan_mcap(path: Path, topics: set[str] | None = None, *, note: str = "") -> Iterator[BagMessage]:
    """Yield the messages of an MCAP file in file order (``topics``: only these).

    Raises:
        BagError: not an MCAP file, or damaged (after every intact message before the damage);
            ``note`` is appended to the error text (e.g. why the index was not used).
    """
    yield from _McapScanner(Path(path), topics, note=note).messages()
