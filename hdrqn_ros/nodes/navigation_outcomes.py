"""How an option that the robot's navigator drives ends when the navigator says so.

With ``navigation: action`` the meta-controller sends each option's place as one
``navigate_to_pose`` goal; when its result comes (SUCCEEDED, ABORTED or CANCELED, or the
goal is rejected) it publishes the outcome on ``navigation_outcome``
(``std_msgs/Int64MultiArray``, step QoS): one record ``(key, status)``, ``key`` the step
key at which the option started (its ``subgoal``'s key), ``status`` the goal's
``action_msgs/GoalStatus`` code (4 SUCCEEDED, 5 CANCELED, 6 ABORTED; a rejected goal
reads 6). The critic (its ``navigation_outcome`` parameter on) then ends that option at
its next step (``option_done``; the intrinsic reward stays the internal critic's: the robot
environment still decides from the robot's pose whether the place was reached and
visited), instead of waiting for the place or ``option_timeout``. An outcome that arrives
after the critic judged a step is used at the step after it.
"""
from __future__ import annotations

from collections import deque

import numpy as np
from rclpy.node import Node
from std_msgs.msg import Int64MultiArray

from hdrqn_ros.nodes.qos import STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription
from hdrqn_ros.protocol import wire

NAVIGATION_OUTCOME = "navigation_outcome"
OUTCOME_FIELDS = ("key", "status")
STATUS_EXECUTING, STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED = 2, 4, 5, 6
"""``action_msgs/msg/GoalStatus`` codes (its documented constants)."""
ENDED = {STATUS_SUCCEEDED: "SUCCEEDED", STATUS_CANCELED: "CANCELED", STATUS_ABORTED: "ABORTED"}
"""The terminal goal statuses, by code."""
REMEMBERED = 64
"""Outcomes kept (the latest options'); an option's outcome is needed only while it runs."""


def outcome_message(key: int, status: int) -> Int64MultiArray:
    """The ``navigation_outcome`` record of the option started at step ``key``."""
    return wire.make_records(ROS_MESSAGES, wire.INTS, OUTCOME_FIELDS, [[int(key), int(status)]])


def read_outcome(msg: Int64MultiArray) -> dict[str, int]:
    """The record of a ``navigation_outcome`` message; :class:`~hdrqn_ros.protocol.wire.ProtocolError`
    when it is malformed or its status is not a terminal one."""
    record = wire.read_record(msg, OUTCOME_FIELDS, dtype=np.int64)
    if record["status"] not in ENDED:
        raise wire.ProtocolError(f"status {record['status']} is not a terminal goal status "
                                 f"({', '.join(f'{code} {name}' for code, name in ENDED.items())})")
    return record


class NavigationOutcomes:
    """The options whose navigation ended, heard on ``navigation_outcome`` by ``node`` (a
    node that reads with ``decode(topic, read)``: a malformed message is logged and counted)."""

    def __init__(self, node: Node, max_message_bytes: int, logger):
        self.node = node
        self.ended_keys: deque[int] = deque(maxlen=REMEMBERED)
        bounded_subscription(node, Int64MultiArray, NAVIGATION_OUTCOME, self._on_outcome, STEP_QOS,
                             max_message_bytes, logger)

    def _on_outcome(self, msg: Int64MultiArray) -> None:
        record = self.node.decode(NAVIGATION_OUTCOME, lambda: read_outcome(msg))
        if record is not None:
            self.ended_keys.append(int(record["key"]))

    def ended(self, option_key: int) -> bool:
        """The navigation of the option started at step ``option_key`` has ended."""
        return int(option_key) in self.ended_keys

    def clear(self) -> None:
        self.ended_keys.clear()
