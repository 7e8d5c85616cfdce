"""Nav2's lifecycle manager (``nav2_lifecycle_manager``, Jazzy) for the tests, in rclpy, written
from its documented behaviour (Nav2 has no Python wheel to run the real one here).

- Start: it waits for each managed node's ``~/get_state`` service.
- A transition for one node: ``~/change_state`` by id (the service awaited up to 10 s), then
  ``~/get_state`` (awaited and answered within 2 s, else an exception), which must give the
  transition's goal state; otherwise "Failed to change state for node: NAME".
- ``startup``: configure every node in ``node_names`` order, then activate every node; right
  after a node's activate, with ``bond_timeout`` > 0 (default 4.0 s), its side of the node's
  bond: ``bond/msg/Status`` on ``bond``, ``id`` the node's name, heartbeats every 0.1 s,
  ``heartbeat_timeout`` = ``bond_timeout``; the node's heartbeat must form it within
  ``bond_timeout / 2``, else "Server NAME was unable to be reached after ... by bond" and the
  bring-up aborts. ``bond_timeout`` <= 0: no bonds.
- ``shutdown``: deactivate, then cleanup, then shutdown, each over the nodes in reverse order;
  a phase stops at its first failure (the next phase still runs). Deactivate ends the node's
  bond (``active: false``).
- While the nodes are active it checks their bonds every 200 ms (:meth:`supervise`): a bond
  with no heartbeat for ``bond_timeout`` or ended by the node is broken: "CRITICAL FAILURE:
  SERVER NAME IS DOWN ...", then a hard reset: deactivate and cleanup in reverse order, going
  on past refused transitions; an exception ends a phase, and a deactivate phase that ended
  so skips the cleanup.
"""
from __future__ import annotations

import time
import uuid

from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.qos import QoSProfile

from hdrqn_ros.nodes.ros_messages import interface_class

from ros_probe import RosProbe

BOND_TIMEOUT_S = 4.0
HEARTBEAT_PERIOD_S = 0.1
BOND_CHECK_PERIOD_S = 0.2
CHANGE_STATE_WAIT_S = 10.0
GET_STATE_TIMEOUT_S = 2.0
GOAL = {Transition.TRANSITION_CONFIGURE: State.PRIMARY_STATE_INACTIVE,
        Transition.TRANSITION_ACTIVATE: State.PRIMARY_STATE_ACTIVE,
        Transition.TRANSITION_DEACTIVATE: State.PRIMARY_STATE_INACTIVE,
        Transition.TRANSITION_CLEANUP: State.PRIMARY_STATE_UNCONFIGURED,
        Transition.TRANSITION_UNCONFIGURED_SHUTDOWN: State.PRIMARY_STATE_FINALIZED}
LABEL = {Transition.TRANSITION_CONFIGURE: "Configuring", Transition.TRANSITION_ACTIVATE: "Activating",
         Transition.TRANSITION_DEACTIVATE: "Deactivating", Transition.TRANSITION_CLEANUP: "Cleaning up",
         Transition.TRANSITION_UNCONFIGURED_SHUTDOWN: "Shutting down"}
FORWARD = (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE)


class ServiceError(RuntimeError):
    """A lifecycle service that is not there or does not answer in time (Nav2 throws)."""


class ManagerBond:
    """The manager's side of one node's bond."""

    def __init__(self, node_id: str, timeout_s: float):
        self.id, self.timeout_s = node_id, timeout_s
        self.instance_id = str(uuid.uuid4())
        self.formed = self.broken = False
        self.heard_at = 0.0  # monotonic time of the node's last heartbeat

    def hear(self, msg, now: float) -> bool:
        """The node's ``msg``; whether to answer its ``active: false``."""
        if self.broken:
            return not msg.active
        if msg.active:
            self.formed, self.heard_at = True, now
            return False
        self.broken = True
        return True

    def check(self, now: float) -> bool:
        """Broken: ended by the node, or formed and no heartbeat for ``timeout_s``."""
        if self.formed and not self.broken and now - self.heard_at > self.timeout_s:
            self.broken = True
        return self.broken


class Nav2LifecycleManager:
    """The manager of ``node_names`` (root namespace) on ``probe``'s executor; ``log`` holds
    its messages, ``heard[name]`` the last ``bond/msg/Status`` each node sent, ``ended_by``
    the nodes that sent ``active: false``, ``states[name]`` the last state read."""

    def __init__(self, probe: RosProbe, node_names: tuple[str, ...], bond_timeout: float = BOND_TIMEOUT_S,
                 transition_timeout_s: float = 60.0, name: str = "lifecycle_manager"):
        self.probe, self.node_names, self.bond_timeout = probe, tuple(node_names), bond_timeout
        self.transition_timeout_s = transition_timeout_s  # Nav2 waits without a limit; a test cannot
        self.node = probe.create_node(name)
        self.log: list[str] = []
        self.heard: dict[str, object] = {}
        self.ended_by: set[str] = set()
        self.states: dict[str, str] = {}
        self.bonds: dict[str, ManagerBond] = {}
        self.own_instances: set[str] = set()
        self.broken: list[str] = []
        self.broken_at = 0.0
        self.active = False
        self.clients = {n: (self.node.create_client(ChangeState, f"/{n}/change_state"),
                            self.node.create_client(GetState, f"/{n}/get_state")) for n in self.node_names}
        if bond_timeout > 0:  # bonds: bond/msg/Status must be installed
            self.status_type = interface_class("bond/msg/Status")
            self.bond_pub = self.node.create_publisher(self.status_type, "bond", QoSProfile(depth=5))
            self.node.create_subscription(self.status_type, "bond", self._on_status, QoSProfile(depth=100))
            self.node.create_timer(HEARTBEAT_PERIOD_S, self._heartbeats)

    # -- what the tests call -------------------------------------------------------------------
    def wait_for_nodes(self, timeout_s: float) -> None:
        """Nav2's service clients wait for each node's ``~/get_state`` at start."""
        for name in self.node_names:
            get_state = self.clients[name][1]
            self.probe.spin(until=get_state.service_is_ready, timeout_s=timeout_s)
            assert get_state.service_is_ready(), f"{name}'s get_state service did not appear in {timeout_s} s"

    def startup(self) -> bool:
        self.say("Starting managed nodes bringup...")
        if not (self._all(Transition.TRANSITION_CONFIGURE) and self._all(Transition.TRANSITION_ACTIVATE)):
            self.say("Failed to bring up all requested nodes. Aborting bringup.")
            return False
        self.say("Managed nodes are active")
        self.active = True
        return True

    def shutdown(self) -> bool:
        """Nav2's shutdown; whether every transition succeeded (Nav2 answers true regardless)."""
        self.active = False
        self.say("Shutting down managed nodes...")
        results = [self._all(t) for t in (Transition.TRANSITION_DEACTIVATE, Transition.TRANSITION_CLEANUP,
                                          Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)]
        self.say("Managed nodes have been shut down")
        return all(results)

    def supervise(self, timeout_s: float) -> str | None:
        """Check the bonds every 200 ms for ``timeout_s``: the first node whose bond broke (the
        system then reset), or None. ``broken_at``: when it was seen; ``broken``: every node
        whose bond was broken then."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.probe.spin(timeout_s=BOND_CHECK_PERIOD_S)
            now = time.monotonic()
            self.broken = [n for n in self.node_names if self.active and n in self.bonds and self.bonds[n].check(now)]
            for name in self.broken[:1]:
                self.broken_at = now
                self.say(f"Have not received a heartbeat from {name}.")
                self.say(f"CRITICAL FAILURE: SERVER {name} IS DOWN after not receiving a heartbeat for "
                         f"{int(self.bond_timeout * 1000)} ms. Shutting down related nodes.")
                self.reset(hard=True)
                self.bonds.clear()
                return name
        return None

    def reset(self, hard: bool = False) -> bool:
        self.active = False
        self.say("Resetting managed nodes...")
        if not (self._all(Transition.TRANSITION_DEACTIVATE, hard) and self._all(Transition.TRANSITION_CLEANUP, hard)):
            if not hard:
                self.say("Failed to reset nodes: aborting reset")
                return False
        self.say("Managed nodes have been reset")
        return True

    def say(self, line: str) -> None:
        self.log.append(line)
        self.node.get_logger().info(line)

    # -- transitions -------------------------------------------------------------------------------
    def _all(self, transition: int, hard: bool = False) -> bool:
        names = self.node_names if transition in FORWARD else tuple(reversed(self.node_names))
        for name in names:
            try:
                if not self._change(name, transition) and not hard:
                    return False
            except ServiceError as exc:
                self.say(f"Failed to change state for node: {name}. Exception: {exc}.")
                return False
        return True

    def _change(self, name: str, transition: int) -> bool:
        self.say(f"{LABEL[transition]} {name}")
        if not self._change_state(name, transition) or self._get_state(name) != GOAL[transition]:
            self.say(f"Failed to change state for node: {name}")
            return False
        if transition == Transition.TRANSITION_ACTIVATE:
            return self._bond(name)
        if transition == Transition.TRANSITION_DEACTIVATE:
            self._end_bond(name)
        return True

    def _call(self, client, request, wait_s: float, answer_s: float, what: str):
        self.probe.spin(until=client.service_is_ready, timeout_s=wait_s)
        if not client.service_is_ready():
            raise ServiceError(f"{what} service is not available!")
        future = client.call_async(request)
        self.probe.spin(until=future.done, timeout_s=answer_s)
        if not future.done():
            client.remove_pending_request(future)
            raise ServiceError(f"{what} service did not answer within {answer_s:g} s")
        return future.result()

    def _change_state(self, name: str, transition: int) -> bool:
        request = ChangeState.Request(transition=Transition(id=transition))
        return self._call(self.clients[name][0], request, CHANGE_STATE_WAIT_S, self.transition_timeout_s,
                          "change_state").success

    def _get_state(self, name: str) -> int:
        state = self._call(self.clients[name][1], GetState.Request(), GET_STATE_TIMEOUT_S, GET_STATE_TIMEOUT_S,
                           "get_state").current_state
        self.states[name] = state.label
        return state.id

    # -- bonds -----------------------------------------------------------------------------------
    def _bond(self, name: str) -> bool:
        if self.bond_timeout <= 0 or name in self.bonds:
            return True
        bond = self.bonds[name] = ManagerBond(name, self.bond_timeout)
        self.own_instances.add(bond.instance_id)
        self._publish(bond, True)
        self.probe.spin(until=lambda: bond.formed, timeout_s=self.bond_timeout / 2)
        if not bond.formed:
            self.say(f"Server {name} was unable to be reached after {self.bond_timeout:0.2f}s by bond. "
                     "This server may be misconfigured.")
            return False
        self.say(f"Server {name} connected with bond.")
        return True

    def _end_bond(self, name: str) -> None:
        bond = self.bonds.pop(name, None)
        if bond is not None and not bond.broken:
            self._publish(bond, False)

    def _heartbeats(self) -> None:
        for bond in self.bonds.values():
            if not bond.broken:
                self._publish(bond, True)

    def _on_status(self, msg) -> None:
        if msg.instance_id in self.own_instances or msg.id not in self.node_names:
            return
        self.heard[msg.id] = msg
        if not msg.active:
            self.ended_by.add(msg.id)
        bond = self.bonds.get(msg.id)
        if bond is not None and bond.hear(msg, time.monotonic()):
            self._publish(bond, False)

    def _publish(self, bond: ManagerBond, active: bool) -> None:
        msg = self.status_type(id=bond.id, instance_id=bond.instance_id, active=active,
                               heartbeat_timeout=bond.timeout_s, heartbeat_period=HEARTBEAT_PERIOD_S)
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.bond_pub.publish(msg)
