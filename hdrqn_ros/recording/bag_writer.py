"""Writing rosbag2 (MCAP) bags: :class:`BagWriter`, with splitting by size or time."""
from __future__ import annotations

import os
from contextlib import contextmanager, suppress
from pathlib import Path

from rosbags.interfaces import Connection, Qos, QosDurability, QosHistory, QosLiveliness
from rosbags.rosbag2 import StoragePlugin, Writer

from hdrqn_ros.recording.bag_format import (_INFINITE, _RELIABILITY, TYPESTORE, BagError, _file_info, _hint,
                                            _McapFile, _metadata, _topic_entry, _unknown, _write_metadata, _yaml)


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
