"""ROS2 sqlite3 bags read with the standard library's ``sqlite3``: a `BagReader` for a bare
``.db3`` or a bag folder whose ``metadata.yaml`` names sqlite3 storage.

rosbag2's schema is two tables: ``topics`` (id, name, type, serialization_format, ...) and
``messages`` (id, topic_id, timestamp, data), plus ``message_definitions`` (topic_type,
encoding, encoded_message_definition, type_description_hash) since schema 4. Reading them
directly skips rosbags' ``AnyReader`` and its storage plugins, which take longer to import and
open than a short conversion spends reading. Types are registered from the bag's own definitions
on first use, each checked against its RIHS01 hash as ``AnyReader`` does. Messages of a
connection asked for `header_only` are read through sqlite's incremental blob I/O: after the
first, only the bytes up to the header stamp leave the file. ``metadata.yaml`` compression is
honoured: ``file`` (each ``.db3.zstd`` is decompressed once, into a temporary folder, when the bag
is opened) and ``message`` (each message is decompressed as it is read).

Rows are read on a helper thread, a bounded number of bytes ahead of the consumer
(`_ReadAhead`). sqlite hands the GIL back at every row it steps to (and at every blob it reads);
on the consumer's thread, which in the converter also feeds the decoding workers and writes the
store, each of those handovers can mean waiting for a busy worker to give the GIL up again. ROS1
and MCAP readers hand it over once per chunk of many messages, so they have no such cost.
"""

from __future__ import annotations

import sqlite3
import threading
from collections import deque
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path, PurePath
from types import ModuleType
from typing import TYPE_CHECKING, Any

from rosbags.typesys import (
    Stores,
    TypesysError,
    get_types_from_idl,
    get_types_from_msg,
    get_typestore,
)

from converters.bag_readers import HEADER_STAMP_END, ROS2_METADATA, BagReadError

if TYPE_CHECKING:
    from tempfile import TemporaryDirectory

SQLITE_STORAGE = "sqlite3"
CDR = "cdr"
ZSTD = "zstd"
FILE_COMPRESSION, MESSAGE_COMPRESSION = "file", "message"
NEWEST_BAG_VERSION = 9  # metadata.yaml versions this reader knows (rosbags reads up to 9 too)
MSG_FORMAT, IDL_FORMAT = "ros2msg", "ros2idl"
# several IDL files in one definition: each after a line of 80 "=" and an "IDL: pkg/msg/Name" line
IDL_SEPARATOR = "=" * 80 + "\n"
IDL_HEADER = "IDL: "
COPY_BLOCK = 1 << 20  # bytes per read when decompressing a file-compressed bag
# how far the helper thread reads ahead: a few frames of a robot's topics, whatever their size
READ_AHEAD_BYTES = 8 << 20
READ_AHEAD_MESSAGES = 16


@dataclass(frozen=True)
class Ros2Connection:
    """A topic of the bag with one message type (the fields the converter reads)."""

    id: int
    topic: str
    msgtype: str


@dataclass(frozen=True)
class _Definition:
    encoding: str  # ros2msg or ros2idl
    text: str
    digest: str  # RIHS01 type description hash, "" if not recorded


def read_metadata(folder: Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` mapping of a bag folder's ``metadata.yaml``."""
    from ruamel.yaml import YAML  # rosbags' YAML library; only folders need it
    from ruamel.yaml.error import YAMLError

    path = folder / ROS2_METADATA
    try:
        info = YAML(typ="safe").load(path.read_text())["rosbag2_bagfile_information"]
    except (OSError, UnicodeDecodeError, YAMLError) as err:
        raise BagReadError(f"cannot read {path} ({err})") from err
    except (KeyError, TypeError) as err:
        raise BagReadError(f"{path} has no rosbag2_bagfile_information mapping") from err
    if not isinstance(info, dict):
        raise BagReadError(f"{path}: rosbag2_bagfile_information is not a mapping")
    return info


def _zstd() -> ModuleType:
    """The zstd module rosbags itself uses (the standard library's from Python 3.14)."""
    try:
        from compression import zstd  # type: ignore[import-not-found]
    except ImportError:
        from backports import zstd
    return zstd


class Ros2Sqlite:
    """An open ROS2 sqlite3 bag: a bare ``.db3`` or a folder (then `metadata` is its parsed
    ``metadata.yaml``). Messages come file by file, each file in timestamp order."""

    is2 = True
    storage = "ROS2 sqlite3"

    def __init__(self, path: Path, metadata: dict[str, Any] | None = None) -> None:
        self._temp: TemporaryDirectory[str] | None = None
        self._compressed_messages = False
        self._databases: list[tuple[sqlite3.Connection, dict[int, Ros2Connection]]] = []
        self.connections: list[Ros2Connection] = []
        self._definitions: dict[str, _Definition] = {}
        self._typestore = get_typestore(Stores.EMPTY)
        self._registered: set[str] = set()
        self._lock = threading.Lock()
        self._read_aheads: set[_ReadAhead] = set()  # running passes, stopped before closing
        try:
            files = [path] if metadata is None else self._storage_files(path, metadata)
            by_key: dict[tuple[str, str], Ros2Connection] = {}
            for file in files:
                self._open_database(file, by_key)
        except BaseException:
            self.close()
            raise
        if self.connections and not self._definitions:
            self.close()
            raise BagReadError(
                f"{path} holds no message definitions (rosbag2 stores them from sqlite "
                "schema 4 on), so its messages cannot be decoded"
            )

    def _storage_files(self, folder: Path, metadata: dict[str, Any]) -> list[Path]:
        """The database files of a bag folder, decompressed first if the bag is file-compressed."""
        yaml = folder / ROS2_METADATA
        try:
            version = int(metadata["version"])
            storage = metadata["storage_identifier"]
            names = [PurePath(name).name for name in metadata["relative_file_paths"]]
        except (KeyError, TypeError, ValueError) as err:
            raise BagReadError(f"{yaml}: an entry is missing or invalid ({err})") from err
        if version > NEWEST_BAG_VERSION:
            raise BagReadError(f"{yaml}: rosbag2 bag version {version} is not supported")
        if storage != SQLITE_STORAGE:
            raise BagReadError(f"{yaml}: storage {storage!r} is not {SQLITE_STORAGE}")
        mode = str(metadata.get("compression_mode") or "").lower()
        mode = "" if mode == "none" else mode
        if mode and metadata.get("compression_format") != ZSTD:
            raise BagReadError(
                f"{yaml}: compression format {metadata.get('compression_format')!r} is not "
                f"supported (only {ZSTD})"
            )
        if mode not in ("", FILE_COMPRESSION, MESSAGE_COMPRESSION):
            raise BagReadError(f"{yaml}: compression mode {mode!r} is not supported")
        files = [folder / name for name in names]
        if missing := [f.name for f in files if not f.is_file()]:
            raise BagReadError(f"{yaml} lists database files that are missing: {missing}")
        self._compressed_messages = mode == MESSAGE_COMPRESSION
        return [self._decompressed(f) for f in files] if mode == FILE_COMPRESSION else files

    def _decompressed(self, file: Path) -> Path:
        """A zstd-compressed database file, decompressed into the bag's temporary folder."""
        from tempfile import TemporaryDirectory  # file-compressed bags only

        zstd = _zstd()
        if self._temp is None:
            self._temp = TemporaryDirectory(prefix="bgs-db3-")
        target = Path(self._temp.name, file.stem)
        try:
            with zstd.open(file, "rb") as src, target.open("wb") as dst:
                while block := src.read(COPY_BLOCK):
                    dst.write(block)
        except (zstd.ZstdError, EOFError) as err:
            raise BagReadError(f"{file} cannot be decompressed ({err})") from err
        return target

    def _open_database(self, file: Path, by_key: dict[tuple[str, str], Ros2Connection]) -> None:
        """Open one database file read-only and learn its topics and message definitions."""
        uri = f"{file.resolve().as_uri()}?mode=ro&immutable=1"
        try:  # any thread may run a pass, one at a time: a plan made here can be used elsewhere
            db = sqlite3.connect(uri, uri=True, check_same_thread=False)
        except sqlite3.Error as err:
            raise BagReadError(f"{file} cannot be opened ({err})") from err
        try:
            tables = {
                name for (name,) in db.execute("SELECT name FROM sqlite_master WHERE type='table'")
            }
            if not {"messages", "topics"} <= tables:
                raise BagReadError(f"{file} is not a rosbag2 database (no messages/topics table)")
            ids = {}
            for topic_id, topic, msgtype, fmt in db.execute(
                "SELECT id, name, type, serialization_format FROM topics ORDER BY id"
            ):
                if fmt != CDR:
                    raise BagReadError(f"{file}: {topic} is serialised as {fmt!r}, not {CDR}")
                key = (topic, msgtype)
                if key not in by_key:
                    by_key[key] = Ros2Connection(len(by_key) + 1, topic, msgtype)
                    self.connections.append(by_key[key])
                ids[topic_id] = by_key[key]
            if "message_definitions" in tables:
                for msgtype, encoding, text, digest in db.execute(
                    "SELECT topic_type, encoding, encoded_message_definition, "
                    "type_description_hash FROM message_definitions ORDER BY id"
                ):
                    if text and msgtype not in self._definitions:
                        self._definitions[msgtype] = _Definition(encoding, text, digest or "")
        except sqlite3.Error as err:
            db.close()
            raise BagReadError(f"{file} is not a readable sqlite3 database ({err})") from err
        except BaseException:
            db.close()
            raise
        self._databases.append((db, ids))

    def messages(
        self, connections: Collection[Ros2Connection] = (), *, header_only: Collection[Any] = ()
    ) -> Iterator[tuple[Ros2Connection, int, bytes]]:
        """(connection, log time ns, CDR bytes) of the wanted connections. Messages of the
        `header_only` connections after the first of each are cut after the header stamp.
        Read on a helper thread, at most `READ_AHEAD_BYTES` ahead."""
        wanted = {c.id for c in connections or self.connections}
        short = set() if self._compressed_messages else {c.id for c in header_only}
        rows = (
            message
            for db, ids in self._databases
            for message in self._file_messages(db, ids, wanted, short)
        )
        read_ahead = _ReadAhead(rows)
        self._read_aheads.add(read_ahead)
        try:
            yield from read_ahead
        except sqlite3.Error as err:
            raise BagReadError(f"the database cannot be read ({err})") from err
        finally:
            read_ahead.close()
            self._read_aheads.discard(read_ahead)

    def _file_messages(
        self,
        db: sqlite3.Connection,
        ids: dict[int, Ros2Connection],
        wanted: set[int],
        short: set[int],
    ) -> Iterator[tuple[Ros2Connection, int, bytes]]:
        full_ids = [i for i, c in ids.items() if c.id in wanted and c.id not in short]
        short_ids = [i for i, c in ids.items() if c.id in short and c.id in wanted]
        if not full_ids and not short_ids:
            return
        # sqlite loads a row's data only when the CASE needs it; the index gives the order
        query = (
            f"SELECT id, topic_id, timestamp, CASE WHEN topic_id IN ({_marks(full_ids)}) "
            f"THEN data END FROM messages WHERE topic_id IN ({_marks(full_ids + short_ids)}) "
            "ORDER BY timestamp, id"
        )
        seen: set[int] = set()
        zstd = _zstd() if self._compressed_messages else None
        for row_id, topic_id, timestamp, data in db.execute(query, full_ids * 2 + short_ids):
            if data is None:  # a header-only connection
                data = _head(db, row_id) if topic_id in seen else _data(db, row_id)
                seen.add(topic_id)
            elif zstd is not None:
                try:
                    data = zstd.decompress(data)
                except zstd.ZstdError as err:
                    raise BagReadError(f"a message cannot be decompressed ({err})") from err
            yield ids[topic_id], timestamp, data

    def deserialize(self, raw: bytes | memoryview, msgtype: str) -> Any:
        if msgtype not in self._registered:
            self._register(msgtype)
        return self._typestore.deserialize_cdr(raw, msgtype)

    def _register(self, msgtype: str) -> None:
        """Register a type (and those it uses) from the bag's definition, checking its hash."""
        with self._lock:
            if msgtype in self._registered:
                return
            definition = self._definitions.get(msgtype)
            if definition is None:
                raise BagReadError(f"the bag holds no message definition of {msgtype}")
            try:
                self._typestore.register(_parse(msgtype, definition))
                digest = self._typestore.hash_rihs01(msgtype)
            except TypesysError as err:
                raise BagReadError(f"bad message definition of {msgtype} ({err})") from err
            if definition.digest and digest != definition.digest:
                raise BagReadError(
                    f"message type {msgtype} does not match its hash ({digest} != "
                    f"{definition.digest})"
                )
            self._registered.add(msgtype)

    def close(self) -> None:
        """Close the databases and delete decompressed copies; idempotent. Deserialising keeps
        working (the types stay registered)."""
        read_aheads, self._read_aheads = self._read_aheads, set()
        for read_ahead in read_aheads:  # passes left unfinished: they use the databases
            read_ahead.close()
        databases, self._databases = self._databases, []
        for db, _ in databases:
            db.close()
        if self._temp is not None:
            self._temp.cleanup()
            self._temp = None


class _ReadAhead:
    """Iterates `messages` (connection, time, bytes) on a helper thread, holding at most
    `READ_AHEAD_BYTES` (or `READ_AHEAD_MESSAGES`) not yet taken, but always at least one.

    An error of the helper is raised to the consumer where the message would have come; `close`
    stops the helper and waits for it, whether or not it has finished.
    """

    def __init__(self, messages: Iterator[tuple[Any, int, bytes]]) -> None:
        self._ready: deque[tuple[Any, int, bytes]] = deque()
        self._bytes = 0
        self._done = False
        self._stop = False
        self._error: BaseException | None = None
        self._changed = threading.Condition()
        self._thread = threading.Thread(
            target=self._read, args=(messages,), name="db3-read-ahead", daemon=True
        )
        self._thread.start()

    def _read(self, messages: Iterator[tuple[Any, int, bytes]]) -> None:
        try:
            for message in messages:
                size = len(message[2])
                with self._changed:
                    while not self._stop and self._full(size):
                        self._changed.wait()
                    if self._stop:
                        return
                    self._ready.append(message)
                    self._bytes += size
                    self._changed.notify_all()
        except BaseException as err:  # handed to the consumer, raised there
            self._error = err
        finally:
            close = getattr(messages, "close", None)
            if close is not None:  # ends the statement on this thread, which runs it
                close()
            with self._changed:
                self._done = True
                self._changed.notify_all()

    def _full(self, size: int) -> bool:
        """Whether a message of `size` bytes must wait for the consumer to take some."""
        return bool(self._ready) and (
            self._bytes + size > READ_AHEAD_BYTES or len(self._ready) >= READ_AHEAD_MESSAGES
        )

    def __iter__(self) -> Iterator[tuple[Any, int, bytes]]:
        while True:
            with self._changed:
                while not self._ready and not self._done:
                    self._changed.wait()
                if not self._ready:
                    if self._error is not None:
                        raise self._error
                    return
                message = self._ready.popleft()
                self._bytes -= len(message[2])
                self._changed.notify_all()
            yield message

    def close(self) -> None:
        """Stop reading and wait for the helper; idempotent."""
        with self._changed:
            self._stop = True
            self._changed.notify_all()
        if self._thread is not threading.current_thread():
            self._thread.join()


def _marks(ids: list[int]) -> str:
    return ",".join("?" * len(ids))


def _data(db: sqlite3.Connection, row_id: int) -> bytes:
    (data,) = db.execute("SELECT data FROM messages WHERE id = ?", (row_id,)).fetchone()
    return data


def _head(db: sqlite3.Connection, row_id: int) -> bytes:
    """The first bytes of a message, up to its header stamp, without loading the rest."""
    with db.blobopen("messages", "data", row_id, readonly=True) as blob:
        return blob.read(HEADER_STAMP_END)


def _parse(msgtype: str, definition: _Definition) -> dict[str, Any]:
    """The types of one recorded definition: ``.msg`` text (with its dependencies) or IDL."""
    if definition.encoding == MSG_FORMAT:
        return get_types_from_msg(definition.text, msgtype)
    if definition.encoding != IDL_FORMAT:
        raise BagReadError(f"definition of {msgtype} has unknown encoding {definition.encoding!r}")
    types: dict[str, Any] = {}
    if definition.text.startswith(IDL_SEPARATOR + IDL_HEADER):
        for part in definition.text.split(IDL_SEPARATOR)[1:]:
            _, _, idl = part.partition("\n")  # drop the "IDL: pkg/msg/Name" line
            types.update(get_types_from_idl(idl))
    else:
        types.update(get_types_from_idl(definition.text))
    return types
