"""The ROS packages the nodes import, and how to get one that is missing. Imports no ROS."""
from __future__ import annotations

import importlib.util

ROS_PACKAGES = ("rclpy", "rcl_interfaces", "builtin_interfaces", "ament_index_python", "std_msgs", "std_srvs",
                "sensor_msgs", "geometry_msgs", "nav_msgs", "rosgraph_msgs", "diagnostic_msgs", "visualization_msgs")
"""The ROS packages ``hdrqn_ros`` imports: package.xml's ``exec_depend``s and setup.py's ``ros``
extra (``test/test_packaging.py`` keeps the three in step)."""


BUILT_PACKAGES = ("tf2_msgs", "nav2_msgs", "bond", "map_msgs")
"""ROS 2 Jazzy interface packages the robot nodes use that PyPI has no wheels for:
``scripts/build_interfaces`` (run by ``scripts/install``) builds them into the venv from their
documented definitions in ``ros_interfaces/`` (only the types the nodes use); a sourced ROS 2's
own packages win."""


def install_hint(package: str) -> str:
    """How to get ROS package ``package``: apt on a ROS 2 install, else the ``ros`` extra or,
    for :data:`BUILT_PACKAGES`, ``scripts/build_interfaces``."""
    apt = f"on a ROS 2 Jazzy install: sudo apt install ros-jazzy-{package.replace('_', '-')}"
    if package in BUILT_PACKAGES:
        return (f"{apt}; without ROS (Linux x86-64, no PyPI wheel): scripts/install builds it into the venv "
                f"(or scripts/build_interfaces alone; it needs g++ and the Python headers)")
    return f"{apt}; without ROS (Linux x86-64): pip install 'hdrqn_ros[ros]'"


class RosNotInstalled(ImportError):
    """rclpy (ROS 2 Jazzy) cannot be imported here."""


RCLPY_INSTALL_HINT = ("pip install 'hdrqn_ros[ros]' (ROS 2 Jazzy's PyPI wheels: Linux x86-64, CPython 3.10-3.13), "
                      "or source ROS 2 Jazzy (source /opt/ros/jazzy/setup.bash), or RoboStack's conda ROS 2 on macOS "
                      "and ARM; hdrqn train, eval, experiment, export and bag info need no ROS")


def require_rclpy() -> None:
    """:class:`RosNotInstalled` naming what to install where ``rclpy`` cannot be found."""
    if importlib.util.find_spec("rclpy") is None:
        raise RosNotInstalled(f"the ROS 2 nodes need rclpy (ROS 2 Jazzy), which is not installed: {RCLPY_INSTALL_HINT}")
