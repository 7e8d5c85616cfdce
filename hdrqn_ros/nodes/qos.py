"""The QoS profiles of the package's topics (rclpy's own ``QoSProfile``)."""
from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def keep_last(depth: int = 10, reliable: bool = True, transient_local: bool = False) -> QoSProfile:
    """A keep-last profile of ``depth`` samples (e.g. a bag topic's offered QoS)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE)


DEFAULT_QOS = keep_last(10)
"""ROS 2's default: reliable, volatile, keep-last 10."""
LATCHED_QOS = keep_last(1, transient_local=True)
"""Reliable, transient-local, keep-last 1: late joiners get the last sample (weights, status, places)."""
STEP_QOS = keep_last(1000)
"""The per-step protocol topics (:mod:`hdrqn_ros.protocol.wire`): reliable, volatile, keep-last
1000. A node off the critical path (the meta-controller between option ends, the learner during
an update) may fall behind by many steps without losing a sample; 1000 steps of observations
are about 6 MB per reader."""
CLOCK_QOS = keep_last(1, reliable=False)
"""``/clock`` read: best effort, keep-last 1 (matches a reliable or a best-effort publisher)."""
