"""Nav2's lifecycle manager with its default settings (issue 38 item 6): the three managed
nodes (``robot_environment``, ``meta_controller``, ``sub_controller`` with ``--managed``,
real node processes) driven by a manager that does what Nav2's does
(:mod:`nav2_lifecycle_manager`):

- ``bond_timeout`` 4 s (Nav2's default): each node's bond heartbeat forms within 2 s of its
  activate and goes on; shutdown (deactivate, cleanup, shutdown, ``get_state`` after each)
  reaches every node: all end ``finalized``, each process exits 0, and each node ended its
  bond itself at deactivate;
- a node killed while up: the manager sees its bond broken within ``bond_timeout`` and
  brings the others down;
- ``bond_timeout: 0.0`` (no bonds): up and down as before;
- the node's side of a bond (in process, on DDS): activated through ``~/change_state`` a
  node bonds, activated by its own process it does not; a manager that ends the bond first
  is answered with ``active: false`` at once, and the heartbeats stop.
"""
from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from lifecycle_msgs.msg import Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState  # noqa: E402
from rclpy.qos import QoSProfile  # noqa: E402

from hdrqn_ros.nodes import bond as node_bond  # noqa: E402
from hdrqn_ros.nodes.lifecycle import ManagedNode  # noqa: E402
from hdrqn_ros.robot_graph import RobotRun, robot_processes, write_params  # noqa: E402
from hdrqn_ros.supervisor import Supervisor  # noqa: E402

from nav2_lifecycle_manager import BOND_TIMEOUT_S, Nav2LifecycleManager  # noqa: E402
from ros_probe import RosProbe  # noqa: E402
from test_graph import ENV  # noqa: E402
from test_robot_nodes import checkpoint  # noqa: E402, F401  (checkpoint: a fixture)

MANAGED = ("robot_environment", "meta_controller", "sub_controller")
"""The managed nodes, in the order a lifecycle manager's ``node_names`` lists them."""
NEEDS_BOND = pytest.mark.skipif(importlib.util.find_spec("bond") is None,
                                reason="ROS package bond is not installed (scripts/install builds it)")


@pytest.fixture
def managed(tmp_path: Path, checkpoint: Path, domain):  # noqa: F811
    """The three managed node processes (unconfigured) and the manager's own rclpy context."""
    run = RobotRun(algo="hdrqn-v2", env=ENV, view="5", checkpoint=str(checkpoint), mode="sub-drives", episodes=50,
                   seed=2, real_time_factor=40.0, episode_log=str(tmp_path / "episodes.jsonl"))
    params = write_params(run, tmp_path / "params.yaml")
    specs = [s for s in robot_processes(run, params, hierarchical=True, managed=MANAGED) if s.name in MANAGED]
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    probe = RosProbe(["nav2_lifecycle_manager"])
    sup.start()
    yield sup, probe
    sup.stop()
    probe.shutdown()


def logs(sup: Supervisor, manager: Nav2LifecycleManager) -> str:
    return "\n".join(["manager:", *manager.log] + [f"{n}:\n{sup.log_tail(n)}" for n in MANAGED])


def exit_codes(sup: Supervisor, probe: RosProbe, timeout_s: float) -> dict[str, int | None]:
    """The processes' exit codes once all exited, or within ``timeout_s`` (None: running)."""
    def exited() -> bool:
        sup.poll()
        return all(sup.returncodes[n] is not None for n in MANAGED)

    probe.spin(until=exited, timeout_s=timeout_s)
    return {n: sup.returncodes[n] for n in MANAGED}


@NEEDS_BOND
def test_default_bond_timeout_up_and_down(managed):
    sup, probe = managed
    manager = Nav2LifecycleManager(probe, MANAGED)
    assert manager.bond_timeout == BOND_TIMEOUT_S == 4.0
    manager.wait_for_nodes(120)
    assert manager.startup(), logs(sup, manager)
    assert [line for line in manager.log if "connected with bond" in line] == \
        [f"Server {n} connected with bond." for n in MANAGED]
    for name in MANAGED:  # the heartbeat's fields as Nav2's servers send them
        heard = manager.heard[name]
        assert heard.active and heard.heartbeat_period == pytest.approx(0.1), heard
        assert heard.heartbeat_timeout == pytest.approx(4.0), heard
    assert manager.supervise(2 * BOND_TIMEOUT_S) is None, logs(sup, manager)  # heartbeats go on
    assert manager.shutdown(), logs(sup, manager)
    assert manager.states == {n: "finalized" for n in MANAGED}, logs(sup, manager)
    assert manager.ended_by == set(MANAGED), "each node ends its bond when deactivated"
    assert exit_codes(sup, probe, 60) == {n: 0 for n in MANAGED}, logs(sup, manager)


@NEEDS_BOND
def test_a_node_that_dies_breaks_its_bond(managed):
    sup, probe = managed
    manager = Nav2LifecycleManager(probe, MANAGED)
    manager.wait_for_nodes(120)
    assert manager.startup(), logs(sup, manager)
    # a killed node's services stay in the DDS graph until its lease ends: calls to it time out
    manager.transition_timeout_s = 5.0
    sup.kill("robot_environment")
    killed = time.monotonic()
    assert manager.supervise(60) == "robot_environment", logs(sup, manager)
    assert manager.broken == ["robot_environment"], "the other nodes' heartbeats go on"
    assert manager.broken_at - killed <= BOND_TIMEOUT_S + 1.0, f"seen after {manager.broken_at - killed:.1f} s"
    assert any(line.startswith("CRITICAL FAILURE: SERVER robot_environment IS DOWN") for line in manager.log)
    assert manager.states["sub_controller"] == manager.states["meta_controller"] == "inactive", \
        logs(sup, manager)
    codes = sup.stop()
    assert codes["sub_controller"] == codes["meta_controller"] == 0, logs(sup, manager)


def test_bond_timeout_zero_up_and_down(managed):
    sup, probe = managed
    manager = Nav2LifecycleManager(probe, MANAGED, bond_timeout=0.0)
    manager.wait_for_nodes(120)
    assert manager.startup(), logs(sup, manager)
    assert not any("bond" in line for line in manager.log)
    assert manager.shutdown(), logs(sup, manager)
    assert manager.states == {n: "finalized" for n in MANAGED}, logs(sup, manager)
    assert exit_codes(sup, probe, 60) == {n: 0 for n in MANAGED}, logs(sup, manager)


@NEEDS_BOND
def test_a_bond_only_when_a_manager_activates(domain):  # noqa: F811
    probe = RosProbe(["bond_test"])
    try:
        by_itself = ManagedNode("by_itself", {}, context=probe.context)
        by_manager = ManagedNode("by_manager", {}, context=probe.context)
        for node in (by_itself, by_manager):
            probe.executor.add_node(node)
            probe.nodes.append(node)
        by_itself.trigger_configure()
        by_itself.trigger_activate()
        assert by_itself.active and by_itself.bond is None
        client = probe.create_node("manager").create_client(ChangeState, "/by_manager/change_state")
        for transition in (Transition.TRANSITION_CONFIGURE, Transition.TRANSITION_ACTIVATE):
            probe.spin(until=client.service_is_ready, timeout_s=60)
            future = client.call_async(ChangeState.Request(transition=Transition(id=transition)))
            probe.spin(until=future.done, timeout_s=60)
            assert future.done() and future.result().success, transition
        assert by_manager.active and by_manager.bond is not None and by_manager.bond.id == "by_manager"
        assert by_manager.bond.state == node_bond.WAITING
    finally:
        probe.shutdown()


@NEEDS_BOND
def test_the_node_answers_a_manager_that_ends_the_bond(domain):  # noqa: F811
    probe = RosProbe(["bond_test"])
    try:
        bond = node_bond.Bond(probe.create_node("sub_controller"), "sub_controller")
        manager = probe.create_node("lifecycle_manager")
        status = manager.msg(node_bond.STATUS_TYPE)
        heard = []
        manager.create_subscription(status, "bond", heard.append, QoSProfile(depth=100))
        pub = manager.create_publisher(status, "bond", QoSProfile(depth=5))

        def manager_says(active: bool) -> None:
            pub.publish(status(id="sub_controller", instance_id="the-manager", active=active, heartbeat_timeout=4.0,
                               heartbeat_period=0.1))

        def formed() -> bool:
            manager_says(True)
            probe.spin(timeout_s=0.1)
            return bond.state == node_bond.FORMED

        def node_heard() -> bool:  # the node's side formed, and its heartbeat reached the manager's subscription
            return formed() and any(m.instance_id == bond.instance_id for m in heard)

        probe.spin(until=node_heard, timeout_s=60)
        assert bond.state == node_bond.FORMED
        node_says = [m for m in heard if m.instance_id == bond.instance_id]
        assert node_says and all(m.active for m in node_says)
        assert node_says[-1].heartbeat_period == pytest.approx(0.1) and node_says[-1].heartbeat_timeout == 4.0
        heard.clear()
        manager_says(False)  # the manager ends the bond (it deactivates the node)
        probe.spin(until=lambda: bond.state == node_bond.BROKEN, timeout_s=60)
        probe.spin(until=lambda: any(m.instance_id == bond.instance_id for m in heard), timeout_s=60)
        assert bond.state == node_bond.BROKEN
        said = [m.active for m in heard if m.instance_id == bond.instance_id]  # heartbeats, then the answer
        assert said[-1] is False and said.count(False) == 1, said
        heard.clear()
        probe.spin(timeout_s=5 * node_bond.HEARTBEAT_PERIOD_S)
        assert not [m for m in heard if m.instance_id == bond.instance_id], "no heartbeat after the bond broke"
    finally:
        probe.shutdown()
