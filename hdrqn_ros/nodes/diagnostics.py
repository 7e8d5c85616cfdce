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
from typing import Callable

import numpy as np

from hdrqn_ros.hashing import file_sha256

DIAGNOSTICS = "/diagnostics"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
OK, WARN, ERROR = 0, 1, 2
WINDOW_S = 10.0
"""Decisions per second and latency are over the last this many seconds."""


def policy_source(params: dict) -> str:
    """The acting weights: an exported policy or a checkpoint, with its sha256 (first 12 hex)."""
    from pathlib import Path

    if params.get("policy"):
        files = sorted(Path(params["policy"]).glob("*.onnx"))
        return f"onnx {params['policy']} " + " ".join(f"{f.name}:{file_sha256(f)[:12]}" for f in files)
    if params.get("checkpoint"):
        return f"checkpoint {params['checkpoint']} sha256:{file_sha256(params['checkpoint'])[:12]}"
    return "random weights until the learner's (no checkpoint, no policy)"


class Diagnostics:
    """Publishes ``check()``'s ``(level, message, values)`` with the decision figures every ``period_s``."""

    def __init__(self, node, check: Callable[[], tuple[int, str, dict[str, str]]], period_s: float = 1.0):
        self.node, self.check = node, check
        self.name = f"hdrqn_ros: {node.fully_qualified_name}"
        self.decisions: deque[tuple[float, float]] = deque()  # (monotonic time, seconds it took)
        self.pub = node.create_publisher(DIAGNOSTIC_ARRAY, DIAGNOSTICS)
        node.create_timer(period_s, self.publish)

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
        node = self.node
        level, message, values = self.status()
        msg = node.msg
        key_value = msg("diagnostic_msgs/msg/KeyValue")
        status = msg("diagnostic_msgs/msg/DiagnosticStatus")(
            level=bytes([level]) if node.backend_name == "rclpy" else level, name=self.name, message=message,
            hardware_id=node.name, values=[key_value(key=k, value=str(v)) for k, v in values.items()])
        stamp = time.time_ns()
        header = msg("std_msgs/msg/Header")(stamp=msg("builtin_interfaces/msg/Time")(
            sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="")
        self.pub.publish(msg(DIAGNOSTIC_ARRAY)(header=header, status=[status]))
