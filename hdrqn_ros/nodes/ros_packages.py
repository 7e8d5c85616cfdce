"""The ROS packages the nodes import, and how to get one that is missing. Imports no ROS."""
from __future__ import annotations

ROS_PACKAGES = ("rclpy", "rcl_interfaces", "builtin_interfaces", "ament_index_python", "std_msgs", "std_srvs",
                "sensor_msgs", "geometry_msgs", "nav_msgs", "rosgraph_msgs", "diagnostic_msgs", "visualization_msgs")
"""The ROS packages ``hdrqn_ros`` imports: package.xml's ``exec_depend``s and setup.py's ``ros``
extra (``test/test_packaging.py`` keeps the three in step)."""


def install_hint(package: str) -> str:
    """How to get ROS package ``package``: apt on a ROS 2 install, else the ``ros`` extra."""
    return (f"on a ROS 2 Jazzy install: sudo apt install ros-jazzy-{package.replace('_', '-')}; "
            f"without ROS (Linux x86-64): pip install 'hdrqn_ros[ros]'")
