"""The test process's own rclpy node, to talk to the node processes under test.

``probe = RosProbe()`` initialises a private rclpy context (with the package's loopback
network defaults) and an executor; ``probe.create_node(name)`` makes a :class:`ProbeNode`,
an ``rclpy.node.Node`` that also takes message types by name (``"std_msgs/msg/String"``) and
is a message factory for :mod:`hdrqn_ros.protocol.wire` (``msg``, ``pack``);
``probe.spin(until=..., timeout_s=...)`` runs its callbacks; ``probe.shutdown()`` ends it.
"""
from __future__ import annotations

import os
import time
from typing import Any, Callable

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions

from hdrqn_ros.dds import INTERFACE_ENV, apply_rmw_network_defaults
from hdrqn_ros.nodes.qos import DEFAULT_QOS
from hdrqn_ros.nodes.ros_messages import interface_class, pack, to_cdr


SPIN_STEP_S = 0.05
"""The one timeout :meth:`RosProbe.spin` gives ``spin_once``."""


class ProbeNode(Node):
    """An rclpy node whose publishers and subscriptions take a type name or a class."""

    msg = staticmethod(interface_class)
    pack = staticmethod(pack)
    to_cdr = staticmethod(to_cdr)

    def create_publisher(self, msg_type, topic: str, qos: QoSProfile | int = DEFAULT_QOS, **kwargs):
        return super().create_publisher(_cls(msg_type), topic, qos, **kwargs)

    def create_subscription(self, msg_type, topic: str, callback: Callable[[Any], None],
                            qos: QoSProfile | int = DEFAULT_QOS, **kwargs):
        return super().create_subscription(_cls(msg_type), topic, callback, qos, **kwargs)


def _cls(msg_type) -> type:
    return interface_class(msg_type) if isinstance(msg_type, str) else msg_type


class RosProbe:
    """A private rclpy context and executor for the test's probe nodes."""

    def __init__(self, argv: list[str] | None = None):
        apply_rmw_network_defaults(os.environ.get(INTERFACE_ENV) or None)
        self.context = Context()
        rclpy.init(args=argv or ["probe"], context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.nodes: list[Node] = []

    def create_node(self, name: str, namespace: str = "", **kwargs) -> ProbeNode:
        node = ProbeNode(name, namespace=namespace, context=self.context, **kwargs)
        self.executor.add_node(node)
        self.nodes.append(node)
        return node

    def spin(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> None:
        """Run callbacks until ``until()`` is true or ``timeout_s`` passed (steps of 50 ms).

        Every step waits the same 50 ms: rclpy's executor keeps its list of ready callbacks
        only while ``spin_once`` gets the same arguments, and with a new one each call it would
        run only the first ready subscription, starving those created later under a backlog."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while self.context.ok() and not (until is not None and until()):
            if deadline is not None and time.monotonic() >= deadline:
                return
            self.executor.spin_once(timeout_sec=SPIN_STEP_S)

    def shutdown(self) -> None:
        """Destroy the nodes and the context; safe to call twice."""
        if not self.context.ok():
            return
        self.executor.shutdown()
        for node in self.nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self.context.destroy()

    def __enter__(self) -> "RosProbe":
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()
