"""The node executables (``ros2 run hdrqn_ros <name>``, ``setup.py``'s console scripts).

Each imports its node's module and runs its ``main``. A ROS package the module imports that
is not installed (a message package missing from the workspace) exits 2 with one line naming
it and how to get it, rather than a traceback that a launch file's respawn would repeat.
"""
from __future__ import annotations

import importlib
import sys
from functools import partial

from hdrqn_ros.nodes.ros_packages import BUILT_PACKAGES, ROS_PACKAGES, install_hint

NODES = {"environment": "environment:main", "critic": "critic:main", "meta_controller": "controllers:main_meta",
         "sub_controller": "controllers:main_sub", "learner": "learner:main", "player": "player:main",
         "robot_environment": "robot_environment:main", "loopback_robot": "loopback_robot:main"}
"""Executable name -> ``module:function`` in :mod:`hdrqn_ros.nodes`."""


def entry_point(executable: str) -> str:
    """``executable``'s ``module:function`` for :func:`hdrqn_ros.supervisor.python_command`."""
    if executable not in NODES:
        raise KeyError(f"no node executable {executable!r}; the executables are {', '.join(NODES)}")
    return f"{__name__}:{executable}"


def run(executable: str) -> int:
    """Import ``executable``'s node module and run its main; exit code 2 when a ROS package it
    needs is not installed."""
    module, _, function = NODES[executable].partition(":")
    try:
        entry = getattr(importlib.import_module(f"hdrqn_ros.nodes.{module}"), function)
    except ModuleNotFoundError as exc:
        package = (exc.name or "").split(".")[0]
        if package not in ROS_PACKAGES + BUILT_PACKAGES:
            raise
        print(f"error: {executable} needs the ROS package {package}, which is not installed: {install_hint(package)}",
              file=sys.stderr)
        return 2
    return entry()


# the console scripts of setup.py, one per executable
environment = partial(run, "environment")
critic = partial(run, "critic")
meta_controller = partial(run, "meta_controller")
sub_controller = partial(run, "sub_controller")
learner = partial(run, "learner")
player = partial(run, "player")
robot_environment = partial(run, "robot_environment")
loopback_robot = partial(run, "loopback_robot")
