"""package.xml and setup.py's ``ros`` extra declare every ROS package the code imports; a node
whose ROS package is missing exits 2 with one line naming it."""
from __future__ import annotations

import ast
import importlib.metadata
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from hdrqn_ros.nodes.ros_packages import BUILT_PACKAGES, ROS_PACKAGES

ROOT = Path(__file__).resolve().parents[1]
NOT_ON_PYPI = {"launch", "launch_ros"}
"""ROS packages the launch files import that come only with a ROS 2 install."""


def installed_ros_packages() -> set[str]:
    """Top-level modules of the installed ROS 2 distributions (PyPI ``ros-<package>`` wheels)."""
    names = set()
    for dist in importlib.metadata.distributions():
        name = (dist.metadata["Name"] or "").lower()
        if name.startswith("ros-") and not name.startswith("ros-jazzy-"):
            names |= set((dist.read_text("top_level.txt") or "").split())
    return names


def imported_modules(*folders: str) -> dict[str, set[str]]:
    """Top-level module -> the files under ``folders`` that import it (anywhere in the file)."""
    found: dict[str, set[str]] = {}
    for folder in folders:
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    found.setdefault(name.split(".")[0], set()).add(str(path.relative_to(ROOT)))
    return found


def package_xml_depends(*tags: str) -> set[str]:
    root = ET.parse(ROOT / "package.xml").getroot()
    return {element.text.strip() for tag in tags for element in root.iter(tag)}


def ros_extra() -> set[str]:
    """The ROS packages setup.py's ``ros`` extra installs (``ros-jazzy-<package>`` wheels)."""
    text = (ROOT / "setup.py").read_text(encoding="utf-8")
    wheels = re.findall(r'"ros-jazzy-([a-z0-9-]+)(?:\[[a-z]+\])?"', text)
    return {wheel.replace("-", "_") for wheel in wheels}


def ros_imports(*folders: str) -> dict[str, set[str]]:
    ros = installed_ros_packages() | NOT_ON_PYPI | set(BUILT_PACKAGES)
    return {module: files for module, files in imported_modules(*folders).items() if module in ros}


def test_package_xml_declares_every_ros_package_the_code_imports():
    declared = package_xml_depends("exec_depend", "depend")
    missing = {module: sorted(files) for module, files in ros_imports("hdrqn_ros", "launch").items()
               if module not in declared}
    assert not missing, f"package.xml lacks <exec_depend> for: {missing}"
    unbuilt = sorted(set(BUILT_PACKAGES) - declared)  # the robot nodes load them by name, too
    assert not unbuilt, f"package.xml lacks <exec_depend> for the built interface packages: {unbuilt}"
    test_declared = declared | package_xml_depends("test_depend")
    missing_in_tests = sorted(set(ros_imports("test")) - test_declared)
    assert not missing_in_tests, f"package.xml lacks <test_depend> for: {missing_in_tests}"


def test_the_ros_extra_and_the_nodes_list_match_package_xml():
    nodes = set(ros_imports("hdrqn_ros")) - NOT_ON_PYPI - set(BUILT_PACKAGES)
    assert ros_extra() == nodes, "setup.py's ros extra must install exactly the ROS packages hdrqn_ros imports"
    assert set(ROS_PACKAGES) == nodes, "hdrqn_ros/nodes/ros_packages.py ROS_PACKAGES must list them too"


def test_installed_ros_packages_are_found():
    """The check above cannot pass vacuously: the ROS wheels are seen as ROS packages."""
    pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")
    assert {"rclpy", "std_msgs", "diagnostic_msgs"} <= installed_ros_packages()


def test_a_node_without_its_message_package_exits_2_naming_it(tmp_path):
    """``diagnostic_msgs`` hidden from the import system: the controller's executable prints one
    line naming the package and how to get it, and exits 2 (no traceback to respawn on)."""
    blocker = tmp_path / "sitecustomize.py"
    blocker.write_text("import sys\nsys.modules['diagnostic_msgs'] = None\n")
    code = "import sys; from hdrqn_ros.nodes.executables import sub_controller; sys.exit(sub_controller())"
    env = {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert lines and "diagnostic_msgs" in lines[-1] and "ros-jazzy-diagnostic-msgs" in lines[-1], out.stderr
    assert "hdrqn_ros[ros]" in lines[-1] and "Traceback" not in out.stderr, out.stderr
