"""rosbag2 bags (MCAP storage, metadata version 9) without ROS: write, read, repair.

Built on ``rosbags`` (writer/reader, ROS 2 Jazzy message definitions) and the ``mcap``
library (sequential record reading to salvage the files of a killed writer).
Times are integer nanoseconds since the epoch; sizes are bytes.

The code lives in :mod:`~hdrqn_ros.recording.bag_format` (the shared format pieces),
:mod:`~hdrqn_ros.recording.bag_writer` (writing, splitting),
:mod:`~hdrqn_ros.recording.bag_reader` (validating, reading, summaries) and
:mod:`~hdrqn_ros.recording.bag_repair`; this module gathers their public names.
"""
from __future__ import annotations

from hdrqn_ros.recording.bag_format import MAGIC, TYPESTORE, BagError, _McapFile  # noqa: F401  (_McapFile: tests)
from hdrqn_ros.recording.bag_reader import (TopicInfo, bag_custom_data, bag_summary, bag_topics, open_bag,
                                            read_messages, select_topics)
from hdrqn_ros.recording.bag_repair import RepairReport, repair_bag
from hdrqn_ros.recording.bag_writer import BagWriter

__all__ = ["TYPESTORE", "MAGIC", "BagError", "BagWriter", "open_bag", "read_messages", "bag_summary",
           "bag_custom_data", "bag_topics", "select_topics", "TopicInfo", "repair_bag", "RepairReport"]
