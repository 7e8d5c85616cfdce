"""A managed node's side of its bond with a lifecycle manager: ROS's ``bond`` protocol, kept
as Nav2's servers keep theirs, so that Nav2's ``lifecycle_manager`` with its default
``bond_timeout`` (4 s) brings the node up and notices when it dies.

Both sides of a bond publish ``bond/msg/Status`` on the topic ``bond`` (relative: in the
node's namespace), each message carrying the bond's ``id`` (the node's name: what the manager
lists in ``node_names``), the side's own ``instance_id`` (a UUID), ``active``, and the side's
``heartbeat_timeout`` and ``heartbeat_period`` (seconds). A side's *sister* is whoever sends
the same ``id`` with another ``instance_id``.

- **waiting**: from activate on, ``active: true`` every :data:`HEARTBEAT_PERIOD_S`. The
  manager makes its side after the node's activate and waits ``bond_timeout / 2`` for a
  heartbeat, else it aborts the bring-up.
- **formed**: the sister's first ``active: true``; heartbeats go on.
- **breaking**: the node breaks the bond (deactivate, shutdown, the process stopping):
  ``active: false`` at once, then every :data:`DEAD_PUBLISH_PERIOD_S` until the sister
  answers with ``active: false`` or :data:`DISCONNECT_TIMEOUT_S` passes.
- **broken**: no more heartbeats. Reached from breaking; from waiting or formed when the
  sister sends ``active: false`` first (the manager deactivating the node), answered at once
  with ``active: false``; or from waiting after :data:`CONNECT_TIMEOUT_S` with no sister
  (nobody watches: a manager with ``bond_timeout: 0``, or ``ros2 lifecycle set``).

The manager's side breaks when it has heard no heartbeat for its ``bond_timeout`` (the node
died) and then resets every node it manages. The node's side never times out on the
manager's heartbeats (Nav2's servers disable that): a manager that dies leaves its nodes in
the state they are in.
"""
from __future__ import annotations

import time
import uuid

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile

from hdrqn_ros.nodes.ros_messages import interface_class

TOPIC = "bond"
STATUS_TYPE = "bond/msg/Status"
HEARTBEAT_PERIOD_S = 0.1
"""How often a side says it is alive (Nav2's servers and manager: 0.1 s)."""
HEARTBEAT_TIMEOUT_S = 4.0
"""The ``heartbeat_timeout`` this side announces (Nav2's servers: 4 s; it does not apply it)."""
CONNECT_TIMEOUT_S = 10.0
"""How long a side waits for its sister before it gives up (bondcpp's default)."""
DISCONNECT_TIMEOUT_S = 2.0
"""How long a side that broke the bond waits for its sister's answer (bondcpp's default)."""
DEAD_PUBLISH_PERIOD_S = 0.05
"""How often a breaking side repeats ``active: false`` (bondcpp's)."""
WAITING, FORMED, BREAKING, BROKEN = "waiting", "formed", "breaking", "broken"


class Bond:
    """The bond ``bond_id`` of ``node`` with its lifecycle manager, heartbeating from construction
    on; :meth:`end` breaks it, :meth:`close` breaks it and destroys its topics and timer.
    ``state`` is one of :data:`WAITING`, :data:`FORMED`, :data:`BREAKING`, :data:`BROKEN`.
    :class:`~hdrqn_ros.nodes.ros_messages.MissingRosPackage` where ``bond`` is not installed."""

    def __init__(self, node: Node, bond_id: str):
        self.status_type = interface_class(STATUS_TYPE)
        self.node, self.id = node, bond_id
        self.instance_id = str(uuid.uuid4())
        self.state = WAITING
        self.sister_broke_first = False
        self.deadline = time.monotonic() + CONNECT_TIMEOUT_S  # of waiting, then of breaking
        self.clock = Clock(clock_type=ClockType.STEADY_TIME)
        self.pub = node.create_publisher(self.status_type, TOPIC, QoSProfile(depth=5))
        self.sub = node.create_subscription(self.status_type, TOPIC, self._on_status, QoSProfile(depth=100))
        self.timer = node.create_timer(HEARTBEAT_PERIOD_S, self._tick, clock=self.clock)
        self._publish(True)

    def end(self) -> None:
        """Break the bond (the node is deactivated or goes away): ``active: false`` now; a formed
        bond repeats it until the manager answers or :data:`DISCONNECT_TIMEOUT_S` passes."""
        if self.state == WAITING:
            self._publish(False)
            self._broken()
        elif self.state == FORMED:
            self._publish(False)
            self.state, self.deadline = BREAKING, time.monotonic() + DISCONNECT_TIMEOUT_S
            self.node.destroy_timer(self.timer)
            self.timer = self.node.create_timer(DEAD_PUBLISH_PERIOD_S, self._tick, clock=self.clock)

    def close(self) -> None:
        """:meth:`end`, then destroy the bond's publisher, subscription and timer."""
        if self.pub is None:
            return
        self.end()
        self.node.destroy_timer(self.timer)
        self.node.destroy_subscription(self.sub)
        self.node.destroy_publisher(self.pub)
        self.pub = self.sub = self.timer = None

    def _tick(self) -> None:
        if self.state in (WAITING, BREAKING) and time.monotonic() >= self.deadline:
            if self.state == WAITING:
                self.node.get_logger().info(f"no lifecycle manager joined the bond {self.id!r} within "
                                            f"{CONNECT_TIMEOUT_S:g} s (none, or one with bond_timeout 0): its "
                                            "heartbeats stop")
            self._broken()
        elif self.state in (WAITING, FORMED):
            self._publish(True)
        elif self.state == BREAKING:
            self._publish(False)

    def _on_status(self, msg) -> None:
        if msg.id != self.id or msg.instance_id == self.instance_id or self.pub is None:
            return
        if msg.active:
            if self.state == WAITING:
                self.state = FORMED
                self.node.get_logger().info(f"bond {self.id!r} formed with the lifecycle manager (heartbeats every "
                                            f"{HEARTBEAT_PERIOD_S:g} s on {self.pub.topic_name})")
            return
        if self.state in (WAITING, FORMED):
            self.sister_broke_first = True
            self.node.get_logger().info(f"the lifecycle manager ended the bond {self.id!r}")
            self._broken()
        if self.state == BROKEN and self.sister_broke_first:
            self._publish(False)  # the answer to the manager's breaking, again while it repeats it
        elif self.state == BREAKING:
            self._broken()

    def _broken(self) -> None:
        self.state = BROKEN
        self.timer.cancel()

    def _publish(self, active: bool) -> None:
        msg = self.status_type(id=self.id, instance_id=self.instance_id, active=active,
                               heartbeat_timeout=HEARTBEAT_TIMEOUT_S, heartbeat_period=HEARTBEAT_PERIOD_S)
        msg.header.stamp = self.clock.now().to_msg()
        self.pub.publish(msg)
