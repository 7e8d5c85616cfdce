"""Managed (lifecycle) nodes on rclpy (issue 27): a real rclpy client drives every transition
of a node process through its ``~/change_state`` / ``~/get_state`` services, as Nav2's
lifecycle manager does (transitions by id), and checks what the node does in each state.

- a driving sub-controller (free-running on a costmap): refused transitions, a configure
  that fails on a bad checkpoint and succeeds once the parameter is corrected, acting only
  while active, the zero command on deactivate, released topics on cleanup, a second
  configure, shutdown ending the process;
- the robot graph with its three deployed nodes managed, brought up and down in Nav2's
  order (configure and activate front to back, deactivate back to front): episodes run
  only while active;
- ``--managed`` where it cannot be: a node without a managed mode.
"""
from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from lifecycle_msgs.msg import Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402

from hdrqn_ros.nodes import nav  # noqa: E402
from hdrqn_ros.nodes.qos import LATCHED_QOS  # noqa: E402
from hdrqn_ros.robot_graph import NODE_MODULES  # noqa: E402
from hdrqn_ros.supervisor import python_command  # noqa: E402

from ros_probe import RosProbe  # noqa: E402
from test_graph import ENV, read_jsonl  # noqa: E402
from test_robot_nodes import checkpoint, start  # noqa: E402, F401  (checkpoint: a fixture)

CONFIG = Path(__file__).resolve().parents[1] / "config"
ZERO = (0.0, 0.0, 0.0)


class LifecycleClient:
    """The test's rclpy node: a lifecycle client for node processes, a costmap publisher,
    and the listener of cmd_vel, /diagnostics and env_step."""

    def __init__(self):
        self.mw = RosProbe(["lifecycle_client"])
        self.node = self.mw.create_node("lifecycle_client")
        self.cmd_vel: list[tuple[float, float, float]] = []
        self.diagnostics: dict[str, object] = {}
        self.node.create_subscription(nav.TWIST, "/cmd_vel", lambda m: self.cmd_vel.append(
            (m.linear.x, m.linear.y, m.angular.z)))
        self.node.create_subscription("diagnostic_msgs/msg/DiagnosticArray", "/diagnostics",
                                      lambda m: self.diagnostics.update({s.name: s for s in m.status}))
        self.costmap_pub = self.node.create_publisher(nav.OCCUPANCY_GRID, "/local_costmap/costmap", LATCHED_QOS)
        self.clients: dict[str, tuple] = {}

    def spin(self, seconds: float) -> None:
        self.mw.spin(timeout_s=seconds)

    def until(self, cond, timeout: float, what: str, proc: subprocess.Popen | None = None) -> None:
        end = time.monotonic() + timeout
        while not cond():
            assert proc is None or proc.poll() is None, f"the node exited ({proc.returncode}) waiting for {what}"
            assert time.monotonic() < end, f"timed out after {timeout} s waiting for {what}"
            self.spin(0.1)

    def _call(self, client, request, what: str):
        assert client.wait_for_service(timeout_sec=60), f"no service for {what}"
        future = client.call_async(request)
        self.mw.spin(until=future.done, timeout_s=60)
        assert future.done(), f"no answer within 60 s: {what}"
        return future.result()

    def _services(self, node: str):
        if node not in self.clients:
            self.clients[node] = (self.node.create_client(ChangeState, f"/{node}/change_state"),
                                  self.node.create_client(GetState, f"/{node}/get_state"))
        return self.clients[node]

    def state(self, node: str) -> str:
        return self._call(self._services(node)[1], GetState.Request(), f"{node} get_state").current_state.label

    def change(self, node: str, transition_id: int) -> bool:
        """A transition by id, as Nav2's lifecycle manager sends it: whether it succeeded."""
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return self._call(self._services(node)[0], request, f"{node} transition {transition_id}").success

    def set_parameter(self, node: str, name: str, value):
        client = AsyncParameterClient(self.node, f"/{node}")
        self.mw.spin(until=client.services_are_ready, timeout_s=60)
        future = client.set_parameters([Parameter(name, value=value)])
        self.mw.spin(until=future.done, timeout_s=60)
        return future.result().results[0]

    def describe(self, node: str, name: str):
        client = AsyncParameterClient(self.node, f"/{node}")
        self.mw.spin(until=client.services_are_ready, timeout_s=60)
        future = client.describe_parameters([name])
        self.mw.spin(until=future.done, timeout_s=60)
        return future.result().descriptors[0]

    def publish_costmap(self) -> None:
        msg = self.node.msg
        grid = msg(nav.OCCUPANCY_GRID)()
        grid.header.frame_id = "odom"
        grid.info.resolution, grid.info.width, grid.info.height = 0.25, 20, 20
        grid.info.origin.position.x = grid.info.origin.position.y = -2.5
        grid.data = self.node.pack(np.zeros(400, np.int8))
        self.costmap_pub.publish(grid)

    def status(self, node: str) -> str:
        status = self.diagnostics.get(f"hdrqn_ros: /{node}")
        return "" if status is None else status.message

    def close(self) -> None:
        self.mw.shutdown()


@pytest.fixture
def client(domain, monkeypatch, tmp_path):
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path / "ros_log"))
    c = LifecycleClient()
    yield c
    c.close()


def node_process(executable: str, *params: str, log: Path, managed: bool = True) -> subprocess.Popen:
    """``ros2 run hdrqn_ros EXECUTABLE [--managed] --ros-args -p ...`` as a process."""
    argv = python_command(NODE_MODULES[executable]) + (["--managed"] if managed else [])
    argv += ["--ros-args"] + [a for p in params for a in ("-p", p)]
    return subprocess.Popen(argv, stdout=log.open("w"), stderr=subprocess.STDOUT)


def stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.terminate()
        try:
            return proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()


def test_sub_controller_every_transition(client, tmp_path):
    log = tmp_path / "sub.log"
    proc = node_process("sub_controller", "algo:=dqn", f"env:={ENV}", "observation_source:=costmap",
                        "costmap_topic:=/local_costmap/costmap", f"action_table:={CONFIG / 'nav2' / 'actions.yaml'}",
                        "checkpoint:=/nonexistent/last.pt", "epsilon:=0.0", log=log)
    try:
        node = "sub_controller"
        client.until(lambda: client._services(node)[1].service_is_ready(), 120, "the lifecycle services", proc)
        assert client.state(node) == "unconfigured"
        # refused: activate before configure (by id, as Nav2 sends it): answered, not a crash
        assert not client.change(node, Transition.TRANSITION_ACTIVATE)
        assert client.state(node) == "unconfigured" and proc.poll() is None
        # configure fails on the bad checkpoint: the node stays unconfigured and says why
        assert not client.change(node, Transition.TRANSITION_CONFIGURE)
        assert client.state(node) == "unconfigured"
        client.until(lambda: "/nonexistent/last.pt" in log.read_text(), 30, "the reason in the log", proc)
        assert "configure failed" in log.read_text()
        # unconfigured: a read-at-configure parameter may be corrected (its rules still hold)
        assert not client.set_parameter(node, "algo", "nonsense").successful
        assert client.set_parameter(node, "checkpoint", "").successful
        assert client.change(node, Transition.TRANSITION_CONFIGURE)
        assert client.state(node) == "inactive"
        refused = client.set_parameter(node, "checkpoint", "/other.pt")
        assert not refused.successful and "unconfigured" in refused.reason and "checkpoint" in refused.reason
        described = client.describe(node, "checkpoint")
        assert not described.read_only and "unconfigured" in described.additional_constraints
        assert client.set_parameter(node, "epsilon", 0.0).successful  # live parameters stay live
        # inactive: costmaps come, no command goes; the diagnostics say inactive
        client.until(lambda: client.status(node).startswith("inactive"), 30, "inactive diagnostics", proc)
        for _ in range(5):
            client.publish_costmap()
            client.spin(0.2)
        assert client.cmd_vel == []
        assert not client.change(node, Transition.TRANSITION_CONFIGURE)  # refused: already configured
        # active: one command per costmap
        assert client.change(node, Transition.TRANSITION_ACTIVATE)
        assert client.state(node) == "active"

        def acting() -> bool:
            client.publish_costmap()
            return len(client.cmd_vel) >= 3

        client.until(acting, 60, "commands while active", proc)
        client.until(lambda: client.status(node) and not client.status(node).startswith("inactive"), 30,
                     "active diagnostics", proc)
        # deactivate: the zero command, then nothing more
        assert client.change(node, Transition.TRANSITION_DEACTIVATE)
        client.until(lambda: client.cmd_vel[-1] == ZERO, 30, "the zero command on deactivate", proc)
        heard = len(client.cmd_vel)
        for _ in range(5):
            client.publish_costmap()
            client.spin(0.2)
        assert len(client.cmd_vel) == heard and client.state(node) == "inactive"
        # cleanup: back to unconfigured, its command publisher released
        assert client.change(node, Transition.TRANSITION_CLEANUP)
        assert client.state(node) == "unconfigured"
        client.until(lambda: client.node.count_publishers("/cmd_vel") == 0, 30, "the cmd_vel publisher released",
                     proc)
        # configure again (parameters as left), activate, and shut down from active
        assert client.change(node, Transition.TRANSITION_CONFIGURE)
        assert client.change(node, Transition.TRANSITION_ACTIVATE)
        client.cmd_vel.clear()
        client.until(acting, 60, "commands after the second activate", proc)
        assert client.change(node, Transition.TRANSITION_ACTIVE_SHUTDOWN)
        assert proc.wait(60) == 0, log.read_text()
        client.until(lambda: client.cmd_vel[-1] == ZERO, 30, "the zero command on shutdown")
    finally:
        stop(proc)


MANAGED = ("robot_environment", "meta_controller", "sub_controller")
"""The deployed nodes, in the order a lifecycle manager's ``node_names`` lists them."""


def test_robot_graph_managed_in_nav2_order(client, tmp_path, checkpoint):  # noqa: F811
    sup, log = start(tmp_path, checkpoint, "sub-drives", episodes=50, managed=MANAGED)
    try:
        for node in MANAGED:
            client.until(lambda: client._services(node)[1].service_is_ready(), 120, f"{node}'s lifecycle services")
            assert client.state(node) == "unconfigured"
        client.spin(2.0)
        assert not log.exists() and client.cmd_vel == [], "nothing runs before the nodes are brought up"
        for node in MANAGED:
            assert client.change(node, Transition.TRANSITION_CONFIGURE), node
        for node in MANAGED:
            assert client.change(node, Transition.TRANSITION_ACTIVATE), node
        client.until(lambda: log.exists() and len(read_jsonl(log)) >= 1, 240, "a robot episode while active")
        for node in reversed(MANAGED):
            assert client.change(node, Transition.TRANSITION_DEACTIVATE), node
        client.until(lambda: client.cmd_vel and client.cmd_vel[-1] == ZERO, 30, "the zero command on deactivate")
        episodes = len(read_jsonl(log))
        client.spin(3.0)
        assert len(read_jsonl(log)) == episodes, "an episode ended while deactivated"
        for node in reversed(MANAGED):
            assert client.change(node, Transition.TRANSITION_CLEANUP), node
            assert client.change(node, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN), node
        def exited() -> bool:
            sup.poll()
            return all(sup.returncodes[n] is not None for n in MANAGED)

        client.until(exited, 60, "the managed nodes to exit on shutdown")
    finally:
        codes = sup.stop()
    assert all(codes[n] == 0 for n in MANAGED), codes


def test_managed_needs_a_managed_node(tmp_path, domain):  # noqa: F811
    out = subprocess.run(python_command(NODE_MODULES["critic"]) + ["--managed"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "no managed (lifecycle) mode" in out.stderr, out.stderr
