"""rosbag2 bags (MCAP storage, metadata version 9) without ROS: write, read, repair.

Built on ``rosbags`` (writer/reader, ROS 2 Jazzy message definitions) and the ``mcap``
library (sequential record reading to salvage the files of a killed writer).
Times are integer nanoseconds since the epoch; sizes are bytes.
"""
from __future__ import annotations

import heapq
import os
import re
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass
from io import StringIO
from pathlib import Path
from typing import Iterator

from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import (Connection, ConnectionExtRosbag2, MessageDefinition,
                                MessageDefinitionFormat, Qos, QosDurability, QosHistory,
                                QosLiveliness, QosReliability, QosTime)
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionMode
from rosbags.rosbag2.metadata import dump_qos_v9, parse_qos
from rosbags.rosbag2.storage_mcap import McapWriter
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
MAGIC = b"\x89MCAP0\r\n"
_INFINITE = QosTime(9223372036, 854775807)  # rmw's "infinite" duration
_RELIABILITY = {"reliable": QosReliability.RELIABLE, "best_effort": QosReliability.BEST_EFFORT}


class BagError(Exception):
    """A bag cannot be written, read or repaired; the message names the path."""


def _hint(bag) -> str:
    return f"run `hdrqn bag repair {bag}`"


def _unknown(where, topic: str, type_name: str) -> BagError:
    return BagError(f"{where}: topic {topic} has unknown message type {type_name!r} "
                    "(not in the ROS 2 Jazzy type store)")


class _FileTarget:
    """Path shim: McapWriter writes ``dir / f'{dir.name}.mcap'``, which this maps to ``file``."""

    def __init__(self, file: Path):
        self.file, self.name = file, file.stem

    def __truediv__(self, _other) -> Path:
        return self.file


class _McapFile(McapWriter):
    """rosbags MCAP storage for one named file; flushes every finished chunk (kill -9 safe).
    ``compress``: zstd-compressed chunks (like ``ros2 bag record --storage-preset-profile zstd_fast``)."""

    def __init__(self, file: Path, compress: bool = False):
        super().__init__(_FileTarget(file), CompressionMode.STORAGE if compress else CompressionMode.NONE)
        self.qos_texts: dict[int, str] = {}  # channel id -> offered_qos_profiles YAML

    def add_connection(self, connection: Connection, offered_qos_profiles: str) -> None:
        self.qos_texts[connection.id] = offered_qos_profiles
        super().add_connection(connection, offered_qos_profiles)

    def close_chunk(self) -> None:
        super().close_chunk()
        self.bio.flush()


def _file_info(name: str, start: int, end: int, count: int) -> dict:
    start, end = (start, end) if count else (0, 0)
    return {"path": name, "starting_time": {"nanoseconds_since_epoch": start},
            "duration": {"nanoseconds": end - start}, "message_count": count}


def _topic_entry(name: str, type_name: str, fmt: str, qos: list[Qos], count: int) -> dict:
    digest = TYPESTORE.hash_rihs01(type_name) if type_name in TYPESTORE.fielddefs else ""
    return {"topic_metadata": {"name": name, "type": type_name, "serialization_format": fmt,
                               "offered_qos_profiles": dump_qos_v9(qos),
                               "type_description_hash": digest}, "message_count": count}


def _metadata(files: list[dict], topics: list[dict], custom_data: dict[str, str] | None = None) -> dict:
    """``rosbag2_bagfile_information`` (version 9, storage mcap) for these files/topics."""
    full = [(f["starting_time"]["nanoseconds_since_epoch"], f["duration"]["nanoseconds"])
            for f in files if f["message_count"]]
    start, end = min((s for s, _ in full), default=0), max((s + d for s, d in full), default=0)
    return {"version": 9, "storage_identifier": "mcap",
            "relative_file_paths": [f["path"] for f in files],
            "duration": {"nanoseconds": end - start},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": sum(f["message_count"] for f in files),
            "topics_with_message_count": topics, "compression_format": "",
            "compression_mode": "", "files": files, "custom_data": dict(custom_data or {}),
            "ros_distro": "jazzy"}


def _yaml(obj) -> str:
    yaml, out = YAML(typ="safe"), StringIO()
    yaml.default_flow_style, yaml.width = False, 2**16
    yaml.dump(obj, out)
    return out.getvalue()


def _write_metadata(bag: Path, info: dict) -> None:
    """Atomically (re)write ``bag/metadata.yaml``."""
    tmp = bag / "metadata.yaml.tmp"
    tmp.write_text(_yaml({"rosbag2_bagfile_information": info}), "utf8")
    os.replace(tmp, bag / "metadata.yaml")


class BagWriter:
    """Write a rosbag2 MCAP bag directory as ``<name>_0.mcap``, ``<name>_1.mcap``, ...

    A file is finished (a standalone MCAP with all schemas/channels) and metadata.yaml
    rewritten once the file holds ``split_bytes`` bytes, or before a message would make it
    span more than ``split_seconds`` s of message time (0: no time split). ``compress``:
    zstd chunks. ``custom_data``: string pairs kept in metadata.yaml's ``custom_data``.
    """

    def __init__(self, path, *, split_bytes: int = 256 * 2**20, split_seconds: float = 0.0,
                 compress: bool = False, custom_data: dict[str, str] | None = None):
        self.path = Path(path)
        if split_bytes <= 0 or split_seconds < 0:
            raise ValueError("split_bytes must be > 0 and split_seconds >= 0")
        if os.path.lexists(self.path):
            raise BagError(f"{self.path} already exists; refusing to overwrite it")
        self._split_bytes, self._split_ns = split_bytes, round(split_seconds * 1e9)
        self._compress, self.custom_data = compress, {str(k): str(v) for k, v in (custom_data or {}).items()}
        self._w = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._files: list[dict] = []  # metadata entries of finished files
        self._counts: dict[int, int] = {}  # connection id -> messages in finished files
        self._topics: dict[str, Connection] = {}
        self._closed = False
        with self._guard("create"):
            self.path.mkdir(mode=0o755, parents=True)
            self._w.storage = _McapFile(self.path / f"{self.path.name}_0.mcap", compress)
            _write_metadata(self.path, _metadata([], [], self.custom_data))

    @contextmanager
    def _guard(self, what: str):
        """OSError (disk full, permissions) -> BagError; the unfinished file is abandoned."""
        try:
            yield
        except OSError as err:
            self._closed, storage, self._w.storage = True, self._w.storage, None
            if storage is not None:
                with suppress(Exception):
                    storage.abort()
            raise BagError(f"cannot {what} bag {self.path}: {err.strerror or err}; finished "
                           f"files stay readable ({_hint(self.path)})") from None

    def _storage(self) -> _McapFile:
        if self._closed:
            raise BagError(f"bag {self.path} is closed")
        return self._w.storage

    def add_topic(self, topic: str, type_name: str, qos: str = "reliable",
                  transient_local: bool = False, depth: int = 10) -> int:
        """Register ``topic`` of ROS 2 type ``type_name``; returns its connection id."""
        self._storage()
        if type_name not in TYPESTORE.fielddefs:
            raise _unknown(f"bag {self.path}", topic, type_name)
        if topic in self._topics:
            raise BagError(f"bag {self.path}: topic {topic} was already added")
        if qos not in _RELIABILITY:
            raise ValueError(f"qos must be 'reliable' or 'best_effort', not {qos!r}")
        durability = QosDurability.TRANSIENT_LOCAL if transient_local else QosDurability.VOLATILE
        profile = Qos(QosHistory.KEEP_LAST, depth, _RELIABILITY[qos], durability, _INFINITE,
                      _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE, False)
        with self._guard("add a topic to"):
            conn = self._w.add_connection(topic, type_name, typestore=TYPESTORE,
                                          offered_qos_profiles=[profile])
        self._topics[topic], self._counts[conn.id] = conn, 0
        return conn.id

    def write(self, topic_or_id: str | int, timestamp_ns: int, cdr: bytes) -> None:
        """Append one CDR-serialized message (with its 4-byte encapsulation header)."""
        file, conns = self._storage(), self._w.connections
        if isinstance(topic_or_id, int):
            conn = conns[topic_or_id - 1] if 0 < topic_or_id <= len(conns) else None
        else:
            conn = self._topics.get(topic_or_id)
        if conn is None:
            raise BagError(f"bag {self.path}: unknown topic {topic_or_id!r}; call add_topic first")
        span = max(timestamp_ns, file.message_end_time) - min(timestamp_ns,
                                                              file.message_start_time)
        if sum(file.channel_stats.values()) and (  # bytes so far incl. the pending chunk
                file.bio.tell() + file.chunk.bio.tell() >= self._split_bytes
                or 0 < self._split_ns < span):
            self._split(file)
        with self._guard("write to"):
            self._w.write(conn, timestamp_ns, cdr)

    def sync(self) -> None:
        """End the pending chunk and flush it to the OS: the messages written so far then
        survive a kill of this process (``repair_bag`` recovers complete chunks)."""
        file = self._storage()
        if file.chunk.msgs:
            with self._guard("write to"):
                file.close_chunk()

    def _finish(self, file: _McapFile) -> None:
        """Finish ``file`` and rewrite metadata.yaml listing all finished files."""
        info = _file_info(file.path.name, file.message_start_time, file.message_end_time,
                          sum(file.channel_stats.values()))
        file.close(9, _yaml(_metadata([info], self._topic_entries(file.channel_stats), self.custom_data)).strip())
        self._w.storage = None
        self._files.append(info)
        for cid, count in file.channel_stats.items():
            self._counts[cid] += count
        _write_metadata(self.path, _metadata(self._files, self._topic_entries(self._counts), self.custom_data))

    def _topic_entries(self, counts: dict[int, int]) -> list[dict]:
        return [_topic_entry(c.topic, c.msgtype, c.ext.serialization_format,
                             c.ext.offered_qos_profiles, counts.get(c.id, 0))
                for c in self._w.connections]

    def _split(self, old: _McapFile) -> None:
        with self._guard("split"):
            self._finish(old)
            name = f"{self.path.name}_{len(self._files)}.mcap"
            new = self._w.storage = _McapFile(self.path / name, self._compress)
            for conn in self._w.connections:
                if all(s.name != conn.msgtype for s in new.schemas):
                    new.add_msgtype(conn)
                new.add_connection(conn, old.qos_texts[conn.id])

    def close(self) -> None:
        """Finish the open file and write the final metadata.yaml (idempotent)."""
        if not self._closed:
            with self._guard("close"):
                self._finish(self._storage())
                self._closed = True

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


def _data_files(path) -> tuple[Path, list[Path]]:
    """The bag directory and its ``.mcap`` files in split order."""
    bag = Path(path)
    if not bag.is_dir():
        what = "is not a directory" if bag.exists() else "does not exist"
        raise BagError(f"{bag} {what}; expected a rosbag2 bag directory")

    def key(file: Path):
        match = re.search(r"_(\d+)\.mcap$", file.name)
        return (0, int(match.group(1)), file.name) if match else (1, 0, file.name)
    return bag, sorted(bag.glob("*.mcap"), key=key)


def _check(path) -> tuple[Path, dict, list[Path]]:
    """Validate a bag directory; returns (dir, metadata info, listed data files)."""
    bag, on_disk = _data_files(path)
    meta = bag / "metadata.yaml"
    if not meta.exists():
        if not on_disk:
            raise BagError(f"{bag} is not a rosbag2 bag: no metadata.yaml and no .mcap files")
        raise BagError(f"{bag}: metadata.yaml is missing (interrupted recording?); {_hint(bag)}")
    try:
        info = YAML(typ="safe").load(meta.read_text("utf8"))["rosbag2_bagfile_information"]
        names = list(info["relative_file_paths"])
        types = [(t["topic_metadata"]["name"], t["topic_metadata"]["type"])
                 for t in info["topics_with_message_count"]]
        storage = info["storage_identifier"]
        counts = [info["starting_time"]["nanoseconds_since_epoch"], info["duration"]["nanoseconds"],
                  info["message_count"], *(t["message_count"] for t in info["topics_with_message_count"]),
                  *(f["message_count"] for f in info.get("files") or [])]
        paths = [f["path"] for f in info.get("files") or []]
    except Exception as err:  # YAML syntax, missing keys, wrong shapes
        raise BagError(f"{meta}: invalid rosbag2 metadata ({err}); {_hint(bag)}") from None
    if not all(isinstance(v, str) for v in [*names, *paths, *(v for tv in types for v in tv)]) \
            or not all(isinstance(n, int) and not isinstance(n, bool) for n in counts):
        raise BagError(f"{meta}: invalid rosbag2 metadata (file paths, topic names and types must be strings, "
                       f"times and message counts integers); {_hint(bag)}")
    if storage != "mcap":
        raise BagError(f"{meta}: storage {storage!r} is not supported (only mcap)")
    if bad := [(t, ty) for t, ty in types if ty not in TYPESTORE.fielddefs]:
        raise _unknown(meta, *bad[0])
    names = [Path(n).name for n in names]
    if missing := [n for n in names if not (bag / n).exists()]:
        raise BagError(f"{bag}: data files listed in metadata.yaml are missing: {missing}")
    if unlisted := [f.name for f in on_disk if f.name not in names]:
        raise BagError(f"{bag}: {unlisted} not listed in metadata.yaml (interrupted "
                       f"recording?); {_hint(bag)}")
    return bag, info, [bag / n for n in names]


def _open_reader(path: Path, bag: Path) -> Reader:
    reader = Reader(path)
    try:
        reader.open()
    except Exception as err:  # ReaderError, or struct/value errors on damaged data
        raise BagError(f"{path} is damaged or unreadable ({err}); {_hint(bag)}") from None
    return reader


@contextmanager
def open_bag(path) -> Iterator[Reader]:
    """Validate a bag and yield an open ``rosbags.rosbag2.Reader`` for it (closed after)."""
    bag = _check(path)[0]
    reader = _open_reader(bag, bag)
    try:
        yield reader
    finally:
        reader.close()


def read_messages(path, topics=None) -> Iterator[tuple[str, str, int, bytes]]:
    """Iterate ``(topic, type_name, timestamp_ns, cdr)`` in time order across all files."""
    bag, _info, files = _check(path)
    return _iter_messages(bag, files, None if topics is None else set(topics))


def _iter_messages(bag: Path, files: list[Path], topics: set[str] | None):
    with ExitStack() as stack:
        streams = []
        for file in files:
            reader = _open_reader(file, bag)
            stack.callback(reader.close)
            conns = [c for c in reader.connections if topics is None or c.topic in topics]
            if bad := [c for c in conns if c.msgtype not in TYPESTORE.fielddefs]:
                raise _unknown(file, bad[0].topic, bad[0].msgtype)
            if conns:
                streams.append(((t, c.topic, c.msgtype, d) for c, t, d in reader.messages(conns)))
        try:
            for t, topic, type_name, data in heapq.merge(*streams, key=lambda m: m[0]):
                yield topic, type_name, t, bytes(data)
        except Exception as err:  # damaged chunk data surfaces only while iterating
            raise BagError(f"{bag}: damaged data while reading ({err}); {_hint(bag)}") from None


def bag_summary(path) -> dict:
    """Topics (type, count), start/end time (ns), duration (s) and data files of a bag."""
    with open_bag(path) as reader:
        topics = {name: {"type": t.msgtype, "count": t.msgcount}
                  for name, t in sorted(reader.topics.items())}
    bag, info, _files = _check(path)
    start = info["starting_time"]["nanoseconds_since_epoch"]
    duration = info["duration"]["nanoseconds"]
    return {"path": str(bag), "topics": topics, "message_count": info["message_count"],
            "start_ns": start, "end_ns": start + duration, "duration_s": duration / 1e9,
            "files": [{"path": f["path"], "message_count": f["message_count"]}
                      for f in info.get("files") or []]}


@dataclass
class RepairReport:
    """Outcome of :func:`repair_bag`; counts are messages, ``bytes_dropped`` bytes."""

    path: str
    files: list[str]  # data files of the bag after repair, in order
    repaired: list[str]  # damaged files that were rewritten
    messages_recovered: int  # messages salvaged from the damaged files
    message_count: int  # messages in the whole bag after repair
    bytes_dropped: int  # unreadable bytes after the last complete record


class _Strict:
    """File reader whose short reads raise EndOfFile: a truncated record is never accepted."""

    def __init__(self, fh, size: int):
        self.fh, self.size = fh, size

    def read(self, n: int = -1) -> bytes:
        if n is not None and n >= 0 and self.fh.tell() + n > self.size:
            raise EndOfFile()
        return self.fh.read(n)


def _salvage(file: Path) -> tuple[int, int]:
    """Rewrite ``file`` with every complete record; returns (messages, bytes dropped)."""
    size, tmp = file.stat().st_size, file.with_name(file.name + ".repair")
    with file.open("rb") as fh:
        if not MAGIC.startswith(fh.read(8)):
            raise BagError(f"{file} is not an MCAP file (bad magic); cannot repair it")
        fh.seek(0)
        tmp.unlink(missing_ok=True)
        out, schemas, conns, good_end = _McapFile(tmp), {}, {}, 0
        try:
            for rec in StreamReader(_Strict(fh, size), emit_chunks=True).records:
                if isinstance(rec, Chunk) and not rec.compression \
                        and len(rec.data) != rec.uncompressed_size:
                    break
                for item in breakup_chunk(rec, True) if isinstance(rec, Chunk) else [rec]:
                    if isinstance(item, Schema):
                        schemas[item.id] = item
                    elif isinstance(item, Channel) and item.id not in conns \
                            and (schema := schemas.get(item.schema_id)):
                        conns[item.id] = conn = _connection(item, schema)
                        if all(s.name != conn.msgtype for s in out.schemas):
                            out.add_msgtype(conn)
                        out.add_connection(conn, item.metadata.get("offered_qos_profiles", ""))
                    elif isinstance(item, Message) and item.channel_id in conns:
                        out.write(conns[item.channel_id], item.log_time, item.data)
                good_end = fh.tell()
        except OSError:
            out.abort()
            tmp.unlink(missing_ok=True)
            raise
        except Exception:  # the first incomplete or corrupt record ends the good data
            pass
    out.close(9, "")
    os.replace(tmp, file)
    return sum(out.channel_stats.values()), size - good_end


def _connection(channel: Channel, schema: Schema) -> Connection:
    fmt = MessageDefinitionFormat.IDL if "idl" in schema.encoding else MessageDefinitionFormat.MSG
    qos = parse_qos(channel.metadata.get("offered_qos_profiles", ""))
    return Connection(channel.id, channel.topic, schema.name,
                      MessageDefinition(fmt, schema.data.decode()), "", 0,
                      ConnectionExtRosbag2(channel.message_encoding, qos), None)


def _summary(file: Path):
    """The mcap Summary of a complete, rosbags-readable file, else None."""
    try:
        with file.open("rb") as fh:
            summary = make_reader(fh).get_summary()
        reader = Reader(file)  # rosbags must be able to open it too
        reader.open()
        reader.close()
    except Exception:
        return None
    return summary if summary is not None and summary.statistics is not None else None


def _custom_data(bag: Path) -> dict[str, str]:
    """``custom_data`` of a bag's metadata.yaml ({} when it is missing or unreadable)."""
    try:
        data = YAML(typ="safe").load((bag / "metadata.yaml").read_text("utf8"))
        custom = data["rosbag2_bagfile_information"].get("custom_data") or {}
        return {str(k): str(v) for k, v in custom.items()}
    except Exception:  # no metadata.yaml yet, or damaged: custom data is optional
        return {}


def bag_custom_data(path) -> dict[str, str]:
    """The ``custom_data`` string pairs of a valid bag's metadata.yaml."""
    return _custom_data(_check(path)[0])


def repair_bag(path) -> RepairReport:
    """Salvage complete chunks of damaged/unfinished data files; rewrite metadata.yaml."""
    bag, files = _data_files(path)
    if not files:
        raise BagError(f"{bag} is not a rosbag2 MCAP bag: it has no .mcap files")
    repaired, recovered, dropped, infos, topics = [], 0, 0, [], {}
    try:
        for file in files:
            if (summary := _summary(file)) is None:
                count, lost = _salvage(file)
                repaired.append(file.name)
                recovered, dropped = recovered + count, dropped + lost
                if (summary := _summary(file)) is None:
                    raise BagError(f"{file}: repaired file is still unreadable")
            stats = summary.statistics
            infos.append(_file_info(file.name, stats.message_start_time,
                                    stats.message_end_time, stats.message_count))
            for cid, ch in summary.channels.items():
                key = (ch.topic, summary.schemas[ch.schema_id].name, ch.message_encoding,
                       ch.metadata.get("offered_qos_profiles", ""))
                topics[key] = topics.get(key, 0) + stats.channel_message_counts.get(cid, 0)
        _write_metadata(bag, _metadata(infos, [_topic_entry(t, ty, fmt, parse_qos(q), n)
                                               for (t, ty, fmt, q), n in topics.items()], _custom_data(bag)))
    except OSError as err:
        raise BagError(f"cannot repair bag {bag}: {err.strerror or err}") from None
    return RepairReport(str(bag), [f.name for f in files], repaired, recovered,
                        sum(i["message_count"] for i in infos), dropped)


@dataclass(frozen=True)
class TopicInfo:
    """A bag topic for playing it back: its type, message count and the QoS its
    publishers offered when recorded (``None``: not recorded or a system default)."""

    type_name: str
    message_count: int
    reliable: bool | None
    transient_local: bool | None
    depth: int | None


def bag_topics(path) -> dict[str, TopicInfo]:
    """Per topic of a validated bag: type, count and one QoS that suits all recorded offers
    (as rosbag2's player adapts them: reliable / transient-local only if every offer was,
    the deepest keep-last depth)."""
    out: dict[str, TopicInfo] = {}
    with open_bag(path) as reader:
        for name, topic in sorted(reader.topics.items()):
            offers = [q for c in topic.connections for q in c.ext.offered_qos_profiles]
            rel = [q.reliability for q in offers
                   if q.reliability in (QosReliability.RELIABLE, QosReliability.BEST_EFFORT)]
            dur = [q.durability for q in offers
                   if q.durability in (QosDurability.TRANSIENT_LOCAL, QosDurability.VOLATILE)]
            depths = [q.depth for q in offers if q.history == QosHistory.KEEP_LAST and q.depth > 0]
            out[name] = TopicInfo(
                topic.msgtype, topic.msgcount,
                all(r == QosReliability.RELIABLE for r in rel) if rel else None,
                all(d == QosDurability.TRANSIENT_LOCAL for d in dur) if dur else None,
                max(depths) if depths else None)
    return out
