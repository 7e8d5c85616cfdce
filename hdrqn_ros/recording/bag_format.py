"""What the bag modules share: the rosbag2 (MCAP storage, metadata version 9) format.

The type store (ROS 2 Jazzy), :class:`BagError`, one MCAP data file as rosbags writes it
(flushed chunk by chunk) and ``metadata.yaml`` (``rosbag2_bagfile_information``).
Times are integer nanoseconds since the epoch; sizes are bytes.
"""
from __future__ import annotations

import os
from io import StringIO
from pathlib import Path

from rosbags.interfaces import Connection, Qos, QosReliability, QosTime
from rosbags.rosbag2.enums import CompressionMode
from rosbags.rosbag2.metadata import dump_qos_v9
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
