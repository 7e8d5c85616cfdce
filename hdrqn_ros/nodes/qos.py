"""The QoS profiles of the package's topics (rclpy's own ``QoSProfile``)."""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from hdrqn_ros.protocol.wire import STEP_DEPTH


def keep_last(depth: int = 10, reliable: bool = True, transient_local: bool = False) -> QoSProfile:
    """A keep-last profile of ``depth`` samples (e.g. a bag topic's offered QoS)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE)


DEFAULT_QOS = keep_last(10)
"""ROS 2's default: reliable, volatile, keep-last 10."""
LATCHED_QOS = keep_last(1, transient_local=True)
"""Reliable, transient-local, keep-last 1: late joiners get the last sample (weights, status, places)."""
STEP_QOS = keep_last(STEP_DEPTH)
"""The per-step protocol topics (:data:`~hdrqn_ros.protocol.wire.STEP_DEPTH`): reliable, volatile."""
CLOCK_QOS = keep_last(1, reliable=False)
"""``/clock`` read: best effort, keep-last 1 (matches a reliable or a best-effort publisher)."""
