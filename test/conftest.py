"""Fixtures shared by the multi-process tests: the middleware backend the node processes run on."""
from __future__ import annotations

import pytest

from hdrqn_ros.graph import NODE_MODULES
from hdrqn_ros.middleware import BACKEND_ENV, open_middleware
from hdrqn_ros.middleware.rclpy_backend import rclpy_available
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.supervisor import ProcessSpec, python_command

NO_RCLPY = pytest.mark.skipif(not rclpy_available(), reason="rclpy (the ROS 2 Jazzy wheels, extra [ros]) is not "
                                                            "installed: scripts/install installs it on Linux x86-64")
BACKEND_PARAMS = [pytest.param("rclpy", marks=NO_RCLPY), "cyclone"]
PROCESS_MODULES = {"test_graph", "test_faults", "test_multihost", "test_player", "test_bag", "test_robot_nodes",
                   "test_managed_nodes", "test_deploy_nodes", "test_loopback", "test_ros_tooling", "test_bounds",
                   "test_untrusted_data"}
"""Modules whose tests start node processes or join DDS (each on a domain of its own): marked
``processes``. ``scripts/test`` runs them one at a time in one pytest while a second pytest
runs every other test beside it (the load of one busy core, which ``scripts/stress`` shows
they stand, repeating ``-m processes``)."""


def pytest_collection_modifyitems(items):
    for item in items:
        module = getattr(item.module, "__name__", None)
        if module in PROCESS_MODULES:
            item.add_marker(pytest.mark.processes)
        elif {"backend", "domain"} & set(getattr(item, "fixturenames", ())):
            raise pytest.UsageError(f"{item.nodeid} starts node processes: add {module} to PROCESS_MODULES in "
                                    "test/conftest.py, so that it never runs beside another such test")


@pytest.fixture(scope="session", autouse=True)
def ros_log_dir(tmp_path_factory):
    """rcl's log files of every rclpy context (this process's and its children's) go to a
    temporary directory, not ~/.ros/log."""
    mp = pytest.MonkeyPatch()
    mp.setenv("ROS_LOG_DIR", str(tmp_path_factory.mktemp("ros_log")))
    yield
    mp.undo()


@pytest.fixture(params=BACKEND_PARAMS)
def backend(request, monkeypatch) -> str:
    """Each test runs twice: node processes (and the test's own probe node) on real rclpy,
    then on the Cyclone DDS backend (``HDRQN_MIDDLEWARE`` is inherited by subprocesses)."""
    monkeypatch.setenv(BACKEND_ENV, request.param)
    return request.param


def probe_middleware(backend: str):
    """The test process's own middleware, on ``backend`` (loopback defaults applied)."""
    return open_middleware(["probe"], backend)


def node_process(name: str, node: str, *ros_args: str) -> ProcessSpec:
    """Process ``name`` running the graph's ``node`` (``"sub_controller"``...) with ``ros_args``
    (after ``--ros-args``); if it outlives its stop's SIGINT grace, its log gets its stacks."""
    return ProcessSpec(name, python_command(NODE_MODULES[node]) + (["--ros-args", *ros_args] if ros_args else []),
                       stack_dump_signal=STACK_DUMP_SIGNAL)
