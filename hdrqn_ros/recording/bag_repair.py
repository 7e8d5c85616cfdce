"""Repairing rosbag2 (MCAP) bags whose recorder was killed: every complete record of a
damaged or unfinished data file is kept (the ``mcap`` library's sequential record
reader), and ``metadata.yaml`` is rewritten from the files."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from rosbags.interfaces import Connection, ConnectionExtRosbag2, MessageDefinition, MessageDefinitionFormat
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.metadata import parse_qos

from hdrqn_ros.recording.bag_format import (MAGIC, BagError, _file_info, _McapFile, _metadata, _topic_entry,
                                            _write_metadata)
from hdrqn_ros.recording.bag_reader import _custom_data, _data_files


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
