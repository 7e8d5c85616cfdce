"""A node's ROS time: simulated (``/clock``) with ``use_sim_time``, else the system clock.

The port's timers run on wall time; a node that paces itself in ROS time (the robot-side
environment's steps) reads it here, on both backends. Integer nanoseconds throughout
(a stamp's: :func:`hdrqn_ros.protocol.wire.key_of`).
"""
from __future__ import annotations

import time
from typing import Callable

from hdrqn_ros.middleware import QoS
from hdrqn_ros.protocol import wire

CLOCK_QOS = QoS(depth=1, reliable=False)
"""Best effort, keep-last 1: matches a reliable or a best-effort ``/clock`` publisher."""


class RosTime:
    """``now_ns()``: the latest ``/clock`` time with ``use_sim_time`` (``None`` before the
    first one arrives), else ``time.time_ns()``. ``on_clock`` is called after each ``/clock``."""

    def __init__(self, node, use_sim_time: bool, on_clock: Callable[[], None] | None = None):
        self.use_sim_time = bool(use_sim_time)
        self.sim_ns: int | None = None
        self.on_clock = on_clock
        if self.use_sim_time:
            node.create_subscription(wire.CLOCK_TYPE, wire.CLOCK, self._on_clock, CLOCK_QOS)

    def _on_clock(self, msg) -> None:
        self.sim_ns = wire.key_of(msg.clock)
        if self.on_clock is not None:
            self.on_clock()

    def now_ns(self) -> int | None:
        return self.sim_ns if self.use_sim_time else time.time_ns()
