"""The package's layers hold: no module imports from a layer above its own (docs/architecture.md).

Every ``import``/``from ... import`` of ``hdrqn_ros`` modules in ``hdrqn_ros/`` is read with
:mod:`ast` (imports inside functions count too) and each side is given its layer by the
longest matching prefix in :data:`LAYERS`. The core layers (up to and including the
protocol and recording) also import no ROS or DDS library.
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from hdrqn_ros.nodes.ros_packages import ROS_PACKAGES

PACKAGE = Path(__file__).resolve().parents[1] / "hdrqn_ros"

LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("base", ("hdrqn_ros.throttle", "hdrqn_ros.yaml_files", "hdrqn_ros.hashing", "hdrqn_ros.extras", "hdrqn_ros.dds")),
    ("envs and critic", ("hdrqn_ros.envs", "hdrqn_ros.__init__")),
    ("robot task and kinematics", ("hdrqn_ros.robot",)),
    ("algorithm table", ("hdrqn_ros.agents.specs",)),
    ("torch-free policy", ("hdrqn_ros.deploy",)),
    ("config", ("hdrqn_ros.config",)),
    ("agents", ("hdrqn_ros.agents",)),
    ("training", ("hdrqn_ros.training",)),
    ("protocol", ("hdrqn_ros.protocol",)),
    ("recording", ("hdrqn_ros.recording",)),
    ("nodes", ("hdrqn_ros.nodes",)),
    ("launch and cli", ("hdrqn_ros.graph", "hdrqn_ros.robot_graph", "hdrqn_ros.supervisor", "hdrqn_ros.launch_support",
                        "hdrqn_ros.experiments", "hdrqn_ros.cluster", "hdrqn_ros.cli")),
]
"""Lowest first. A module may import from its own layer and the layers below. ``dds`` (the
RMW's network defaults, set before ``rclpy.init``) is a base helper that imports no ROS.
The algorithm table (``agents.specs``, torch-free) sits below the torch-free policy and the
config, which both read it. The protocol builds its messages through a factory it is given
(rclpy's in the nodes, the ``rosbags`` type store's in bags), so it and recording import no
ROS; only the nodes and what starts them use rclpy. ``hdrqn_ros/__init__.py`` only registers
the gymnasium ids."""

CORE_TOP = "recording"
"""This layer and those below import no ROS or DDS library (:data:`MIDDLEWARE_LIBRARIES`)."""
MIDDLEWARE_LIBRARIES = (*ROS_PACKAGES, "rosidl_runtime_py", "rmw", "launch", "launch_ros")


def layer_of(module: str) -> int:
    """Index in :data:`LAYERS` of ``module`` (longest prefix wins); KeyError if none."""
    best, index = -1, None
    for i, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
                best, index = len(prefix), i
    if index is None:
        raise KeyError(f"module {module} is in no layer of test_layers.LAYERS: add it")
    return index


def module_name(path: Path, package: Path) -> str:
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" and len(parts) > 1 else parts)


def imports_of(path: Path, module: str, package: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in the file (relative ones resolved);
    ``from m import x`` counts as importing ``m.x`` where ``x`` is a module of ``package``."""
    found = []
    parent = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = parent.split(".")[: len(parent.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            submodules = [f"{base}.{a.name}" for a in node.names if _is_module(f"{base}.{a.name}", package)]
            found += [(node.lineno, target) for target in submodules or [base]]
    return found


def _is_module(name: str, package: Path) -> bool:
    path = package.parent / Path(*name.split("."))
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def violations(package: Path) -> list[str]:
    """Every import in ``package`` that points to a higher layer, or from the core to ROS/DDS."""
    core_top = [name for name, _ in LAYERS].index(CORE_TOP)
    found = []
    for path in sorted(package.rglob("*.py")):
        module = module_name(path, package)
        own = layer_of(module if module != "hdrqn_ros" else "hdrqn_ros.__init__")
        for line, target in imports_of(path, module, package):
            where = f"{path.relative_to(package.parent)}:{line}"
            if target.split(".")[0] in MIDDLEWARE_LIBRARIES and own <= core_top:
                found.append(f"{where}: {module} ({LAYERS[own][0]}) imports the middleware library {target}")
            if not target.startswith("hdrqn_ros."):
                continue
            theirs = layer_of(target)
            if theirs > own:
                found.append(f"{where}: {module} ({LAYERS[own][0]}) imports {target} ({LAYERS[theirs][0]})")
    return found


def test_no_module_imports_from_a_layer_above_its_own():
    assert violations(PACKAGE) == []


def test_every_module_has_a_layer():
    for path in PACKAGE.rglob("*.py"):
        module = module_name(path, PACKAGE)
        layer_of(module if module != "hdrqn_ros" else "hdrqn_ros.__init__")


def test_the_check_catches_an_upward_import(tmp_path):
    """The checker on a made-up package: an agents module importing a node, a training module
    importing rclpy inside a function, a relative import up from the protocol, the protocol
    importing a message package, and ``dds`` importing rclpy."""
    pkg = tmp_path / "hdrqn_ros"
    for sub in ("agents", "training", "protocol", "nodes", "dds"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "agents" / "policy.py").write_text("from hdrqn_ros.nodes.process import run_node\n")
    (pkg / "training" / "loop.py").write_text("def f():\n    import rclpy\n")
    (pkg / "protocol" / "wire.py").write_text("from ..nodes import process\nfrom std_msgs.msg import Header\n")
    (pkg / "nodes" / "process.py").write_text("import rclpy\nfrom hdrqn_ros.agents import policy\n")
    (pkg / "dds" / "__init__.py").write_text("from rclpy.qos import QoSProfile\n")
    found = violations(pkg)
    assert len(found) == 5, found
    assert any("agents/policy.py:1" in v and "hdrqn_ros.nodes.process (nodes)" in v for v in found)
    assert any("training/loop.py:2" in v and "middleware library rclpy" in v for v in found)
    assert any("protocol/wire.py:1" in v and "hdrqn_ros.nodes" in v for v in found)
    assert any("protocol/wire.py:2" in v and "middleware library std_msgs.msg" in v for v in found)
    assert any("dds/__init__.py:1" in v and "hdrqn_ros.dds (base)" in v and "rclpy.qos" in v for v in found)


def test_unknown_module_is_named():
    with pytest.raises(KeyError, match="hdrqn_ros.elsewhere"):
        layer_of("hdrqn_ros.elsewhere")


LIGHT_NODE_MODULES = ("hdrqn_ros.nodes.environment", "hdrqn_ros.nodes.critic")
HEAVY_LIBRARIES = ("torch", "onnxruntime", "pydantic", "rosbags", "mcap", "zstandard", "apsw")
"""What the environment and critic nodes (numpy only) never load: the learner's and the
controllers' libraries; each would add to every group's resident memory."""


@pytest.mark.parametrize("module", LIGHT_NODE_MODULES)
def test_the_environment_and_critic_nodes_import_no_heavy_library(module):
    probe = f"import sys, {module}; print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY_LIBRARIES!r})))"
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]", f"{module} loads {run.stdout.strip()}"
