"""Helpers shared by the multi-process tests: node processes and the test's own probe node (rclpy)."""
from __future__ import annotations

import fcntl
import importlib.util
import itertools
import os
import tempfile
from pathlib import Path

import pytest

from hdrqn_ros.graph import NODE_MODULES
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.supervisor import ProcessSpec, python_command

NEEDS_RCLPY = pytest.mark.skipif(importlib.util.find_spec("rclpy") is None, reason="rclpy (ROS 2 Jazzy) cannot be imported: "
                                                                "scripts/install installs its wheels on Linux x86-64")
"""For a test outside PROCESS_MODULES (those skip without rclpy as a whole) that needs rclpy."""
PROCESS_MODULES = {"test_graph", "test_faults", "test_multihost", "test_player", "test_bag", "test_robot_nodes",
                   "test_managed_nodes", "test_deploy_nodes", "test_loopback", "test_ros_tooling", "test_bounds",
                   "test_untrusted_data", "test_lifecycle_bonds", "test_interfaces", "test_loopback_nav2",
                   "test_tf_listener", "test_navigate_action",
                   "test_robot_frames", "test_motion_primitives_nodes"}
"""Modules whose tests start node processes or join DDS (each on a domain of its own): marked
``processes``. ``scripts/test`` runs them one at a time in one pytest while a second pytest
runs every other test beside it (the load of one busy core, which ``scripts/stress`` shows
they stand, repeating ``-m processes``). They need rclpy: without it they are skipped."""


def pytest_collection_modifyitems(items):
    for item in items:
        module = getattr(item.module, "__name__", None)
        if module in PROCESS_MODULES:
            item.add_marker(pytest.mark.processes)
            item.add_marker(NEEDS_RCLPY)
        elif "domain" in getattr(item, "fixturenames", ()):
            raise pytest.UsageError(f"{item.nodeid} starts node processes: add {module} to PROCESS_MODULES in "
                                    "test/conftest.py, so that it never runs beside another such test")


_domains = itertools.count(os.getpid() % 200)
DOMAIN_LOCKS = Path(tempfile.gettempdir()) / "hdrqn-test-domains"
"""One lock file per DDS domain id a test holds: test sessions side by side on one machine
(a second checkout's suite, a stress run) never share a domain."""
_held: list = []  # domain locks held until this process exits (new_domain)


def claim_domain():
    """``(id, lock)``: a DDS domain id (20..219) no other test process on this machine holds,
    claimed with an exclusive lock on its file in :data:`DOMAIN_LOCKS` (closing ``lock``
    releases it)."""
    DOMAIN_LOCKS.mkdir(exist_ok=True)
    for _ in range(200):
        d = next(_domains) % 200 + 20
        lock = open(DOMAIN_LOCKS / f"{d}.lock", "w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            continue
        return d, lock
    raise RuntimeError(f"every DDS domain 20..219 is held by a test process ({DOMAIN_LOCKS})")


def new_domain() -> int:
    """A domain of :func:`claim_domain` held until this process exits (a module's fixture)."""
    d, lock = claim_domain()
    _held.append(lock)
    return d


@pytest.fixture
def domain(monkeypatch):
    """A DDS domain (``ROS_DOMAIN_ID``) of this test's own, for the test process and the
    processes it starts, so that tests side by side never meet; the loopback default."""
    d, lock = claim_domain()
    monkeypatch.setenv("ROS_DOMAIN_ID", str(d))
    monkeypatch.delenv("HDRQN_DDS_INTERFACE", raising=False)
    yield d
    lock.close()


@pytest.fixture(scope="session", autouse=True)
def ros_log_dir(tmp_path_factory):
    """rcl's log files of every rclpy context (this process's and its children's) go to a
    temporary directory, not ~/.ros/log."""
    mp = pytest.MonkeyPatch()
    mp.setenv("ROS_LOG_DIR", str(tmp_path_factory.mktemp("ros_log")))
    yield
    mp.undo()


def ros_probe():
    """The test process's own rclpy context and executor (:class:`ros_probe.RosProbe`, loopback
    defaults applied), on the test's ``domain`` (``ROS_DOMAIN_ID``)."""
    from ros_probe import RosProbe

    return RosProbe(["probe"])


def node_process(name: str, node: str, *ros_args: str) -> ProcessSpec:
    """Process ``name`` running the graph's ``node`` (``"sub_controller"``...) with ``ros_args``
    (after ``--ros-args``); if it outlives its stop's SIGINT grace, its log gets its stacks."""
    return ProcessSpec(name, python_command(NODE_MODULES[node]) + (["--ros-args", *ros_args] if ros_args else []),
                       stack_dump_signal=STACK_DUMP_SIGNAL)
