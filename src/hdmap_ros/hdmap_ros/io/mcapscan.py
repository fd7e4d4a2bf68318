"""Read an MCAP file record by record from its start, without needing its index or footer.

Used for bare ``.mcap`` files and for rosbag2 MCAP files whose summary is damaged (e.g. a
truncated recording): every complete record before the damage is delivered -- also the complete
records of a cut-off uncompressed chunk -- and then :class:`~hdmap_core.errors.BagError` says where
and what the damage is. A chunk whose frame is intact but whose content is not (CRC mismatch,
bad compression, a damaged record inside) is skipped with a warning (``on_warning``) and the
records after it are read. Records are framed here and parsed with the ``mcap`` library; messages are
decoded with rosbags from the schemas embedded in the file, each with its own channel's schema (two
schemas of one type name, e.g. two recordings with different definitions, do not mix).
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Callable, Iterator
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

__all__ = ["BagMessage", "scan_mcap", "typestore_of_schema", "WarningFn"]

WarningFn = Callable[[str], None]
# What the mcap library and the decompressors raise on damaged bytes.
_RECORD_ERRORS = (
    McapError,
    struct.error,
    UnicodeDecodeError,
    ValueError,
    KeyError,
    OverflowError,
    MemoryError,
    IndexError,
    TypeError,
)

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEADER = struct.Struct("<BQ")  # opcode, body length


@dataclass(frozen=True)
class BagMessage:
    """One raw message of a bag.

    Attributes:
        topic, msgtype: where it was recorded and its ROS type name.
        log_time_ns: the bag's log (receive) time [ns].
        data: the serialized CDR bytes (what a raw publisher sends).
        typestore: a rosbags typestore that knows ``msgtype`` (from the message's own schema in the
            bag: two connections of one type with different definitions get different stores).
        unknown_definition: empty, or why the bag does not hold this message's own definition (a
            rosbag2 connection whose type hash differs from the definition the bag gives its type).
    """

    topic: str
    msgtype: str
    log_time_ns: int
    data: bytes
    typestore: Typestore = field(repr=False, compare=False)
    unknown_definition: str = field(default="", compare=False)

    def decode(self) -> Any:
        """Deserialize into a rosbags message object."""
        return self.typestore.deserialize_cdr(self.data, self.msgtype)


class _McapScanner:
    """Read an MCAP file record by record, from the start, without its index.

    Complete records before any damage are delivered (also the complete records of a truncated
    uncompressed chunk); the damage then raises :class:`BagError` saying where and what.
    """

    def __init__(
        self, path: Path, wanted: set[str] | None, *, note: str = "", on_warning: WarningFn | None = None
    ) -> None:
        self.path = path
        self.wanted = wanted
        self.note = note
        self.on_warning = on_warning
        self.schemas: dict[int, McapSchema] = {}
        self.channels: dict[int, McapChannel] = {}
        self.typestores: dict[int, Typestore] = {}  # per schema id
        self.count = 0
        self.data: bytes = b""
        self._summary_read = False

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
        self.data = data
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
                self.typestores.pop(schema.id, None)  # rebuilt with the new schema when needed
            elif opcode == Opcode.CHANNEL:
                channel = McapChannel.read(stream)
                self.channels[channel.id] = channel
            elif opcode == Opcode.MESSAGE:
                msg = McapMessage.read(stream, len(body))
                out = self._message(msg, pos)
                if out is not None:
                    self.count += 1
                    yield out
        except _RECORD_ERRORS as err:
            raise self._fail(f"corrupted {_opname(opcode)} record at byte {pos}: {type(err).__name__}: {err}") from err

    def _message(self, msg: McapMessage, pos: int) -> BagMessage | None:
        channel = self.channels.get(msg.channel_id)
        if channel is None and self._from_summary():
            channel = self.channels.get(msg.channel_id)
        if channel is None:
            raise self._fail(f"corrupted: message at byte {pos} on unknown channel {msg.channel_id}")
        if self.wanted is not None and channel.topic not in self.wanted:
            return None
        if channel.message_encoding != "cdr":
            raise self._fail(f"channel {channel.topic!r} has encoding {channel.message_encoding!r}, want cdr")
        schema = self.schemas.get(channel.schema_id)
        if schema is None or not schema.name:
            raise self._fail(f"channel {channel.topic!r} has no schema, its message type is unknown")
        return BagMessage(channel.topic, schema.name, int(msg.log_time), bytes(msg.data), self._typestore(schema))

    def _from_summary(self) -> bool:
        """Take the schemas and channels the file's summary section repeats (once): a skipped
        chunk may have held their only other copy. True when any was new."""
        if self._summary_read:
            return False
        self._summary_read = True
        from mcap.reader import SeekingReader  # noqa: PLC0415 - only for damaged files

        try:
            summary = SeekingReader(BytesIO(self.data), validate_crcs=False).get_summary()
        except (*_RECORD_ERRORS, RuntimeError, EOFError):
            return False
        if summary is None:
            return False
        new = False
        for sid, schema in summary.schemas.items():
            if sid not in self.schemas:
                self.schemas[sid] = schema
                self.typestores.pop(sid, None)
                new = True
        for cid, channel in summary.channels.items():
            if cid not in self.channels:
                self.channels[cid], new = channel, True
        return new

    def _typestore(self, schema: McapSchema) -> Typestore:
        store = self.typestores.get(schema.id)
        if store is None:
            store = self.typestores[schema.id] = typestore_of_schema(schema.name, schema.encoding, bytes(schema.data))
        return store

    def _warn(self, text: str) -> None:
        if self.on_warning is not None:
            self.on_warning(f"{self.path}: {text}")

    def _chunk(self, body: memoryview, pos: int) -> Iterator[BagMessage]:
        # RULE: the chunk's frame (its length in the record header) is intact, so a chunk whose
        # content is damaged is skipped and the records after it are still read.
        try:
            chunk = McapChunk.read(ReadDataStream(BytesIO(body)))
            stream, size = get_chunk_data_stream(chunk, validate_crc=True)
            inner = stream.read(size) if size else b""
        except (*_RECORD_ERRORS, CRCValidationError, RuntimeError, EOFError) as err:
            self._warn(f"chunk at byte {pos} skipped: {type(err).__name__}: {err}")
            return
        try:
            yield from self._inner_records(memoryview(inner), pos, partial=False)
        except BagError as err:
            self._warn(f"chunk at byte {pos}: the rest of it skipped: {err}")

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


_IDL_SEPARATOR = "=" * 80 + "\n"


@functools.lru_cache(maxsize=32)
def typestore_of_schema(name: str, encoding: str, data: bytes) -> Typestore:
    """A typestore for the messages of one schema (``encoding`` ``ros2msg`` or ``ros2idl``, as MCAP
    and rosbag2 name them): the schema's embedded definitions (the type and the types it uses), on top
    of the known (hdmap_msgs / Jazzy) ones for types it lacks; the known store itself when every
    definition is the known one (the usual case, and no types to register: that took ~1 s per file).
    No (or a damaged) embedded definition: the known store; a message that then does not decode is
    rejected on its own."""
    store = default_typestore()
    types: dict = {}
    try:
        text = data.decode("utf-8")
        if encoding == "ros2msg" and text:
            types.update(get_types_from_msg(text, name))
        elif encoding == "ros2idl" and text.startswith(_IDL_SEPARATOR + "IDL: "):
            for part in text.split(_IDL_SEPARATOR)[1:]:  # rosbag2's concatenation of IDL files
                types.update(get_types_from_idl(part.split("\n", 1)[1]))
        elif encoding == "ros2idl" and text:
            types.update(get_types_from_idl(text))
    except (TypesysError, UnicodeDecodeError, ValueError, KeyError, IndexError, TypeError, RecursionError):
        return store
    if all(store.fielddefs.get(k) == v for k, v in types.items()):
        return store
    # A fresh store of the file's own definitions plus the known types they refer to.
    needed = _closure(store.fielddefs, types)
    fresh = get_typestore(Stores.EMPTY)
    try:
        fresh.register({k: store.fielddefs[k] for k in needed if k not in types})
        fresh.register(types)
    except (TypesysError, ValueError, KeyError, TypeError):  # definitions that contradict each other
        return store
    return fresh


def _closure(known: dict, types: dict) -> set[str]:
    """The names of the known types ``types`` refer to, directly or through each other."""
    out: set[str] = set()
    todo = [types[k] for k in types]

    def walk(obj: object) -> None:
        if isinstance(obj, str):
            if obj in known and obj not in out and obj not in types:
                out.add(obj)
                todo.append(known[obj])
        elif isinstance(obj, (tuple, list)):
            for item in obj:
                walk(item)

    while todo:
        walk(todo.pop())
    return out


def _opname(opcode: int) -> str:
    try:
        return Opcode(opcode).name
    except ValueError:
        return f"opcode 0x{opcode:02x}"


def scan_mcap(
    path: Path, topics: set[str] | None = None, *, note: str = "", on_warning: WarningFn | None = None
) -> Iterator[BagMessage]:
    """Yield the messages of an MCAP file in file order (``topics``: only these).

    Args:
        on_warning: called with a line naming each damaged chunk that was skipped.

    Raises:
        BagError: not an MCAP file, or damaged beyond a chunk (after every intact message before
            the damage); ``note`` is appended to the error text (e.g. why the index was not used).
    """
    yield from _McapScanner(Path(path), topics, note=note, on_warning=on_warning).messages()
