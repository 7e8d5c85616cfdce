"""Reading rosbag2 (MCAP) bags: validation, messages in time order, summaries, the
topics' recorded QoS (for playing them back) and ``custom_data``."""
from __future__ import annotations

import heapq
import re
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from rosbags.interfaces import QosDurability, QosHistory, QosReliability
from rosbags.rosbag2 import Reader
from ruamel.yaml import YAML

from hdrqn_ros.recording.bag_format import TYPESTORE, BagError, _hint, _unknown


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


NEAR_MATCHES = 3
"""How many recorded topics an unknown ``--topics`` name suggests."""


def select_topics(wanted: list[str], recorded: set[str], where: str) -> set[str]:
    """The recorded topics that ``wanted`` names (a leading ``/`` optional): a name as
    recorded, or the name of a group's topic without its namespace (``/observation`` selects
    ``/group0/observation``, ``/group1/observation``, ... of a multi-group recording). Raises
    :class:`BagError` for a name that selects nothing, naming it, ``where`` and the few
    recorded topics closest to it."""
    selected: set[str] = set()
    for name in wanted:
        topic = name if name.startswith("/") else "/" + name
        found = {topic} & recorded or {t for t in recorded if t.endswith(topic) and t[: -len(topic)].count("/") == 1}
        if not found:
            import difflib

            close = difflib.get_close_matches(topic, sorted(recorded), n=NEAR_MATCHES, cutoff=0.4)
            hint = f"; closest: {', '.join(sorted(close))}" if close else ""
            raise BagError(f"topic {topic} is not in {where} ({len(recorded)} topics recorded{hint}; "
                           f"hdrqn bag info lists them)")
        selected |= found
    return selected
