"""Read what survives of a truncated MCAP file (a recorder that died before writing its summary).

rosbags needs the MCAP summary and refuses such files ("File end magic is invalid"); the ``mcap``
package's stream reader still walks the records from the start, so every message of the intact
chunks can be recovered. `SalvagedMcap` is a `converters.bag_readers.BagReader`, with types
registered from the file's own ``ros2msg`` schemas.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, McapRecord, Message, Schema
from mcap.stream_reader import StreamReader
from rosbags.typesys import Stores, TypesysError, get_typestore
from rosbags.typesys.msg import get_types_from_msg

ROS2_SCHEMA_ENCODING = "ros2msg"
CDR_ENCODING = "cdr"


@dataclass(frozen=True)
class SalvagedConnection:
    """A channel of the salvaged file (the fields the converter reads from a connection)."""

    id: int
    topic: str
    msgtype: str


class SalvagedMcap:
    """The intact messages of a truncated ROS2 MCAP file, in file order."""

    is2 = True
    storage = "ROS2 mcap (truncated: messages of the intact chunks salvaged with the mcap package)"

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.typestore = get_typestore(Stores.EMPTY)
        self.connections: list[SalvagedConnection] = []
        self._by_id: dict[int, SalvagedConnection] = {}
        schemas: dict[int, Schema] = {}
        for record in self._records():
            if isinstance(record, Schema) and record.encoding == ROS2_SCHEMA_ENCODING:
                try:
                    types = get_types_from_msg(record.data.decode(), record.name)
                    self.typestore.register(types)
                except (TypesysError, UnicodeDecodeError):  # a damaged schema: skip its channels
                    continue
                schemas[record.id] = record
            elif (
                isinstance(record, Channel)
                and record.message_encoding == CDR_ENCODING
                and record.schema_id in schemas
                and record.id not in self._by_id
            ):
                connection = SalvagedConnection(
                    record.id, record.topic, _msgtype(schemas[record.schema_id].name)
                )
                self._by_id[record.id] = connection
                self.connections.append(connection)

    def _records(self) -> Iterator[McapRecord]:
        """Every readable record; stops quietly where the file was cut."""
        with open(self.path, "rb") as fh:
            # no record can be larger than the file: a length cut in half is not trusted
            records = StreamReader(fh, record_size_limit=self.path.stat().st_size).records
            try:
                yield from records
            except (McapError, EOFError, ValueError):
                return

    def messages(
        self, connections: Collection[SalvagedConnection] = (), *, header_only: Collection[Any] = ()
    ) -> Iterator[tuple[SalvagedConnection, int, bytes]]:
        """(connection, log time ns, CDR bytes) of the wanted channels' surviving messages, all
        whole (`header_only` is ignored)."""
        wanted = {c.id for c in connections} or set(self._by_id)
        for record in self._records():
            if isinstance(record, Message) and record.channel_id in wanted:
                yield self._by_id[record.channel_id], record.log_time, record.data

    def deserialize(self, raw: bytes | memoryview, msgtype: str) -> Any:
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        """Nothing stays open between passes."""


def _msgtype(schema_name: str) -> str:
    """``pkg/msg/Name`` for a schema named ``pkg/msg/Name`` or ``pkg/Name``."""
    package, _, name = schema_name.rpartition("/")
    return schema_name if package.endswith("/msg") else f"{package}/msg/{name}"
