"""A deployed node's health on ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``), about once a second.

The ROS convention that ``diagnostic_aggregator``, ``rqt_robot_monitor`` and Foxglove read:
one ``DiagnosticStatus`` named ``hdrqn_ros: <node>`` with a level (OK, WARN, ERROR), a
message saying what is wrong, and key-value pairs (the policy's source and hash, decisions
per second, per-decision latency, and what the node adds). The node supplies its check;
this module keeps the decision timings and builds the message.
"""
from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.clock import Clock, ClockType
from rclpy.node import Node

from hdrqn_ros.hashing import file_sha256

DIAGNOSTICS = "/diagnostics"
OK, WARN, ERROR = (int.from_bytes(level, "little") for level in (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                                                                  DiagnosticStatus.ERROR))
WINDOW_S = 10.0
"""Decisions per second and latency are over the last this many seconds."""


def policy_source(params: dict) -> str:
    """The acting weights: an exported policy or a checkpoint, with its sha256 (first 12 hex)."""
    if params.get("policy"):
        files = sorted(Path(params["policy"]).glob("*.onnx"))
        return f"onnx {params['policy']} " + " ".join(f"{f.name}:{file_sha256(f)[:12]}" for f in files)
    if params.get("checkpoint"):
        return f"checkpoint {params['checkpoint']} sha256:{file_sha256(params['checkpoint'])[:12]}"
    return "random weights until the learner's (no checkpoint, no policy)"


class Diagnostics:
    """Publishes ``check()``'s ``(level, message, values)`` with the decision figures every
    ``period_s`` of wall time (also on simulated time)."""

    def __init__(self, node: Node, check: Callable[[], tuple[int, str, dict[str, str]]], period_s: float = 1.0):
        self.node, self.check = node, check
        self.name = f"hdrqn_ros: {node.get_fully_qualified_name()}"
        self.decisions: deque[tuple[float, float]] = deque()  # (monotonic time, seconds it took)
        self.pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS, 10)
        node.create_timer(period_s, self.publish, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def decision(self, seconds: float) -> None:
        """One decision took ``seconds``."""
        now = time.monotonic()
        self.decisions.append((now, seconds))
        while self.decisions and now - self.decisions[0][0] > WINDOW_S:
            self.decisions.popleft()

    def figures(self) -> dict[str, str]:
        now = time.monotonic()
        recent = [s for t, s in self.decisions if now - t <= WINDOW_S]
        return {"decisions_per_s": f"{len(recent) / WINDOW_S:.2f}",
                "decision_ms_median": f"{1e3 * float(np.median(recent)):.3f}" if recent else "-"}

    def status(self) -> tuple[int, str, dict[str, str]]:
        level, message, values = self.check()
        return level, message, {**values, **self.figures()}

    def publish(self) -> None:
        level, message, values = self.status()
        status = DiagnosticStatus(level=bytes([level]), name=self.name, message=message,
                                  hardware_id=self.node.get_name(),
                                  values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.pub.publish(msg)
