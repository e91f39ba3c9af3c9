"""Message readers of ROS1 and ROS2 bags, one interface (`BagReader`) for both and for the
salvaged part of a truncated MCAP (`converters.mcap_salvage`).

A ROS1 ``.bag`` is read with rosbags' ROS1 reader alone (imported, like every storage reader,
only for its own kind of bag): its index tells where every message
sits, a chunk is read and decompressed when the time-ordered index reaches it, and messages come
out as views into the decompressed chunk, so nothing is copied until the caller keeps one.
Message types are registered from the bag's own definitions only when a message is first
deserialised: the converter's second pass reuses the first pass's deserialiser and never needs
them. ROS2 sqlite3 bags are read with the standard library (`converters.bag_sqlite`); ROS2
MCAP bags go through rosbags' ``AnyReader``, imported only for them, since its storage plugins
(sqlite3, MCAP, zstd, YAML) take a noticeable part of a short conversion to import. Storage
errors of all of them come out as `BagReadError`.
"""

from __future__ import annotations

import struct
from collections.abc import Collection, Iterator
from functools import cached_property
from operator import itemgetter
from pathlib import Path
from typing import Any, Protocol

from rosbags.interfaces import Connection
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

# ROS1 bag format 2.0: a record is (uint32 header length, header of uint32-length-prefixed
# "name=value" fields, uint32 data length, data); "op" names the record type.
UINT32 = struct.Struct("<I")
OP_FIELD = b"op="
OP_MSG_DATA = 0x02
OP_CONNECTION = 0x07  # chunks repeat a connection record before its first message
PAST_END = "a record runs past the end of its chunk"
MCAP_SUFFIX = ".mcap"
ROS2_METADATA = "metadata.yaml"  # beside the storage files of a ROS2 bag folder
# Every stamped message starts with std_msgs/Header: ROS1 ``uint32 seq`` then the stamp; CDR a
# 4-byte encapsulation header (byte 1: 1 = little-endian) then the stamp. Both at offset 4.
STAMP_OFFSET = 4
HEADER_STAMP_END = STAMP_OFFSET + 8  # int32 sec, uint32 nanosec


class BagReadError(Exception):
    """A bag's storage cannot be read (damaged, truncated or inconsistent)."""


class BagReader(Protocol):
    """What the converter uses of an open bag. `deserialize` keeps working after `close`, so
    worker threads can deserialise messages read by a pass that has finished."""

    is2: bool  # CDR (ROS2) rather than ROS1 serialisation
    storage: str  # e.g. "ROS1 bag", "ROS2 mcap", for the store's provenance
    connections: list[Any]  # each with .id, .topic and .msgtype (``pkg/msg/Name``)

    def messages(
        self, connections: Collection[Any] = (), *, header_only: Collection[Any] = ()
    ) -> Iterator[tuple[Any, int, bytes | memoryview]]:
        """(connection, time ns, serialised message) of the given connections (all if none).

        Messages of the `header_only` connections, except the first of each, may come cut short
        after `HEADER_STAMP_END` bytes: readers that can read part of a message do so.
        """
        ...

    def deserialize(self, raw: bytes | memoryview, msgtype: str) -> Any: ...

    def close(self) -> None: ...


class Ros1Bag:
    """An open ROS1 ``.bag``: messages in rosbags' order (receive time, then connection order)
    as views into their decompressed chunk; only the current chunk is held."""

    is2 = False
    storage = "ROS1 bag"

    def __init__(self, path: Path) -> None:
        from rosbags.rosbag1 import Reader, ReaderError  # here: see the module doc

        self._reader = Reader(path)
        try:
            self._reader.open()
        except ReaderError as err:
            raise BagReadError(*err.args) from err
        self.connections: list[Connection] = list(self._reader.connections)  # close clears it

    @cached_property
    def typestore(self) -> Typestore:
        """The bag's message types, from the definitions its connections carry, checked against
        their md5sums as rosbags' ``AnyReader`` does."""
        types: dict[str, Any] = {}
        digests = {}
        try:
            for conn in self.connections:
                types.update(get_types_from_msg(conn.msgdef.data, conn.msgtype))
                if conn.digest:
                    digests[conn.msgtype] = conn.digest
            typestore = get_typestore(Stores.EMPTY)
            typestore.register(types)
        except TypesysError as err:
            raise BagReadError(f"bad message definition ({err})") from err
        for msgtype, digest in digests.items():
            if (have := typestore.generate_msgdef(msgtype)[1]) != digest:
                raise BagReadError(
                    f"message type {msgtype} does not match its md5sum ({have} != {digest})"
                )
        return typestore

    def messages(
        self, connections: Collection[Connection] = (), *, header_only: Collection[Any] = ()
    ) -> Iterator[tuple[Connection, int, memoryview]]:
        """(connection, receive time ns, serialised message) of the wanted connections, all
        whole (`header_only` is ignored: views into the chunk cost nothing)."""
        indexes = self._reader.indexes
        # stable sort by time: ties keep connection order, as rosbags' merge of the indexes
        entries = [
            (entry.time, entry.chunk_pos, entry.offset, conn)
            for conn in connections or self.connections
            for entry in indexes[conn.id]
        ]
        entries.sort(key=itemgetter(0))
        chunk_pos, chunk = None, memoryview(b"")
        for time, pos, offset, conn in entries:
            if pos != chunk_pos:
                chunk_pos, chunk = pos, memoryview(self._chunk(pos))
            yield conn, time, _message_data(chunk, offset)

    def _chunk(self, pos: int) -> bytes:
        """The decompressed records of the chunk at file position `pos`."""
        bio, chunk = self._reader.bio, self._reader.chunks[pos]
        if bio is None:
            raise BagReadError("the bag is closed")
        bio.seek(chunk.datapos)
        data = bio.read(chunk.datasize)
        if len(data) != chunk.datasize:
            raise BagReadError(f"chunk at byte {pos} is cut short")
        try:
            return chunk.decompressor(data)
        except (RuntimeError, OSError, ValueError) as err:  # lz4, bz2: corrupt data
            raise BagReadError(f"chunk at byte {pos} cannot be decompressed ({err})") from err

    def deserialize(self, raw: bytes | memoryview, msgtype: str) -> Any:
        return self.typestore.deserialize_ros1(raw, msgtype)

    def close(self) -> None:
        """Idempotent: the converter's second pass and its safety net may both close."""
        if self._reader.bio is not None:
            self._reader.close()


def _message_data(chunk: memoryview, offset: int) -> memoryview:
    """The data of the message record at `offset` of a chunk, skipping connection records."""
    while True:
        try:
            (header_size,) = UINT32.unpack_from(chunk, offset)
            op = _record_op(chunk, offset + UINT32.size, header_size)
            offset += UINT32.size + header_size
            (data_size,) = UINT32.unpack_from(chunk, offset)
        except struct.error as err:
            raise BagReadError(PAST_END) from err
        offset += UINT32.size
        if offset + data_size > len(chunk):
            raise BagReadError(PAST_END)
        if op == OP_MSG_DATA:
            return chunk[offset : offset + data_size]
        if op != OP_CONNECTION:
            raise BagReadError(f"expected message data, found a record of type {op}")
        offset += data_size


def _record_op(chunk: memoryview, start: int, size: int) -> int | None:
    """The "op" field of the record header at ``chunk[start:start + size]``."""
    end = start + size
    while start < end:
        (field_size,) = UINT32.unpack_from(chunk, start)
        start += UINT32.size
        field = chunk[start : start + field_size]
        if field[: len(OP_FIELD)] == OP_FIELD and len(field) > len(OP_FIELD):
            return field[len(OP_FIELD)]
        start += field_size
    return None


class Ros2Bag:
    """An open ROS2 MCAP bag (folder or ``.mcap``) read with rosbags' ``AnyReader``, whose
    errors come out as `BagReadError`."""

    is2 = True

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError  # here: see the module doc
        from rosbags.rosbag2 import ReaderError

        self._errors = (AnyReaderError, ReaderError)
        try:
            self._reader = AnyReader([path])
            self._reader.open()
        except self._errors as err:
            raise BagReadError(*err.args) from err
        self.storage = "ROS2 mcap"
        # AnyReader clears its connections and drops its typestore on close
        self.connections: list[Connection] = list(self._reader.connections)
        self._typestore: Typestore = self._reader.typestore
        self._open = True

    def messages(
        self, connections: Collection[Connection] = (), *, header_only: Collection[Any] = ()
    ) -> Iterator[tuple[Connection, int, bytes]]:
        """(connection, log time ns, CDR bytes) of the wanted connections, in time order, all
        whole (``AnyReader`` cannot read part of a message)."""
        try:
            yield from self._reader.messages(connections=connections)
        except self._errors as err:
            raise BagReadError(*err.args) from err

    def deserialize(self, raw: bytes | memoryview, msgtype: str) -> Any:
        return self._typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Idempotent, as `Ros1Bag.close`."""
        if self._open:
            self._open = False
            self._reader.close()
