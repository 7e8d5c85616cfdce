"""Launch files and ROS 2 params files: what can be checked without ROS, and a real test with it.

Without ROS: the launch files compile; every ``Node(executable=...)`` is a console script
of ``setup.py``. With rclpy (the nodes' parameter tables): the params YAMLs name only
parameters their nodes declare, with the types the nodes expect. With ROS 2 (``launch``
importable): the real ``generate_launch_description()`` is expanded in a ``LaunchService``'s
context.
"""
from __future__ import annotations

import ast
import functools
import importlib
import importlib.util
import py_compile
from pathlib import Path

import pytest
import yaml

from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.nodes.executables import NODES

from conftest import NEEDS_RCLPY

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "launch" / "train.launch.py"
RUN_POLICY = ROOT / "launch" / "run_policy.launch.py"
ROBOT = ROOT / "launch" / "robot.launch.py"
LAUNCH_FILES = (TRAIN, RUN_POLICY, ROBOT)
TRAIN_YAML = ROOT / "config" / "ros" / "train.yaml"
RUN_POLICY_YAML = ROOT / "config" / "ros" / "run_policy.yaml"
PARAM_FILES = (TRAIN_YAML, RUN_POLICY_YAML)

GRAPH_NODES = ("environment", "critic", "robot_environment", "loopback_robot", "meta_controller", "sub_controller",
               "learner")
"""The executables the launch files start."""
HIERARCHICAL_NODES = ("environment", "critic", "meta_controller", "sub_controller")
FLAT_NODES = ("environment", "sub_controller")


def console_scripts() -> set[str]:
    """The console script names declared in setup.py's entry_points."""
    tree = ast.parse((ROOT / "setup.py").read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            for key, value in zip(node.keys, node.values):
                if isinstance(key, ast.Constant) and key.value == "console_scripts":
                    return {ast.literal_eval(item).split("=")[0].strip() for item in value.elts}
    raise AssertionError("setup.py declares no console_scripts")


@functools.cache
def node_tables() -> dict[str, dict]:
    """Executable -> what it declares (its module's ``PARAMETERS``) and rclpy's own ``use_sim_time``."""
    from hdrqn_ros.nodes.parameters import Param

    rclpy_own = {"use_sim_time": Param(False, "declared by rclpy on every node")}
    return {node: {**importlib.import_module(f"hdrqn_ros.nodes.{node}").PARAMETERS, **rclpy_own}
            for node in GRAPH_NODES}


def shared_table() -> dict:
    """What a ``/**`` entry may set: the graph's shared parameters and rclpy's own."""
    from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES

    return {**ENV_PARAMETERS, **MAX_MESSAGE_BYTES, "use_sim_time": node_tables()["critic"]["use_sim_time"]}


def params_entries(path: Path) -> list[tuple[str, str, object]]:
    """(node pattern, parameter, value) of each parameter of a ROS 2 params file (plain YAML:
    ``pattern: {ros__parameters: {name: value}}``)."""
    doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    assert isinstance(doc, dict), f"{path.name}: not a mapping of node patterns"
    entries = []
    for pattern, section in doc.items():
        assert isinstance(section, dict) and set(section) == {"ros__parameters"}, \
            f"{path.name} [{pattern}]: expected only ros__parameters"
        entries += [(pattern, name, value) for name, value in section["ros__parameters"].items()]
    return entries


def check_value(where: str, name: str, value, param) -> None:
    """``value`` has the type rclpy accepts for ``param`` (no int for a double) and keeps its rules."""
    default = param.default
    if isinstance(default, list):
        assert isinstance(value, (list, tuple)) and value, f"{where}: {name} must be a non-empty list, got {value!r}"
        assert all(type(v) is type(default[0]) for v in value), f"{where}: {name} items must be like {default!r}"
    else:
        assert type(value) is type(default), \
            f"{where}: {name} = {value!r} ({type(value).__name__}) but the node declares {type(default).__name__}"
    assert param.refusal(name, value) is None, f"{where}: {param.refusal(name, value)}"


def check_parameters(where: str, node: str, params: dict) -> None:
    allowed = node_tables()[node]
    for name, value in params.items():
        assert name in allowed, f"{where}: {node} has no parameter {name!r} (it declares {sorted(allowed)})"
        check_value(where, name, value, allowed[name])


# -- static checks ------------------------------------------------------------------------------
@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_compiles(path, tmp_path):
    py_compile.compile(str(path), cfile=str(tmp_path / "out.pyc"), doraise=True)


def loop_values(tree: ast.AST, call: ast.Call, variable: str) -> set:
    """The literal values ``variable`` takes in the ``for`` loops around ``call``: ``for
    variable in [...]`` or ``for variable, ... in [(..., ...), ...]``, the list written in
    the loop or assigned to a name."""
    assigned = {target.id: node.value for node in ast.walk(tree) if isinstance(node, ast.Assign)
                for target in node.targets if isinstance(target, ast.Name)}
    values = set()
    for loop in ast.walk(tree):
        if not isinstance(loop, ast.For) or call not in ast.walk(loop):
            continue
        unpacked = isinstance(loop.target, ast.Tuple)
        names = [getattr(t, "id", None) for t in (loop.target.elts if unpacked else [loop.target])]
        if variable not in names:
            continue
        items = assigned.get(loop.iter.id) if isinstance(loop.iter, ast.Name) else loop.iter
        assert isinstance(items, (ast.List, ast.Tuple)), f"line {loop.lineno}: {variable} loops over no literal list"
        for item in items.elts:
            values.add(ast.literal_eval(item.elts[names.index(variable)] if unpacked else item))
    return values


def started_executables(path: Path) -> list[tuple[int, str]]:
    """(line, executable) of every ``Node(...)`` of a launch file, one per value of an
    executable given by a loop variable; its ``name=`` must be the executable's."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for call in ast.walk(tree):
        if not (isinstance(call, ast.Call) and getattr(call.func, "id", None) == "Node"):
            continue
        kwargs = {k.arg: k.value for k in call.keywords}
        where = f"{path.name}:{call.lineno}"
        assert "executable" in kwargs, f"{where}: Node without executable="
        exe, name = kwargs["executable"], kwargs.get("name")
        if isinstance(exe, ast.Constant):
            assert isinstance(name, ast.Constant) and name.value == exe.value, f"{where}: node name = executable name"
            found.append((call.lineno, exe.value))
            continue
        assert isinstance(exe, ast.Name), f"{where}: executable must be a literal string or a loop variable"
        assert isinstance(name, ast.Name) and name.id == exe.id, f"{where}: node name = executable name"
        values = loop_values(tree, call, exe.id)
        assert values, f"{where}: executable {exe.id} is no variable of a loop over literals"
        found += [(call.lineno, value) for value in sorted(values)]
    return found


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_every_executable_is_a_console_script(path):
    scripts = console_scripts()
    started = started_executables(path)
    assert started, f"{path.name} starts no Node"
    for line, exe in started:
        assert exe in scripts, f"{path.name}:{line}: {exe!r} is not a console script {scripts}"
        assert exe in GRAPH_NODES and exe in NODES, f"{path.name}:{line}: {exe!r} is not a graph node"


def test_train_launch_starts_each_graph_node(tmp_path):
    """The executables of train.launch.py, read through its loop over node names; a typo in
    one is caught."""
    assert sorted({exe for _, exe in started_executables(TRAIN)}) == sorted(HIERARCHICAL_NODES + ("learner",))
    typo = tmp_path / "train.launch.py"
    typo.write_text(TRAIN.read_text(encoding="utf-8").replace('("critic", group)', '("critc", group)'))
    assert "critc" in {exe for _, exe in started_executables(typo)}


@NEEDS_RCLPY
@pytest.mark.parametrize("path", PARAM_FILES, ids=lambda p: p.name)
def test_params_file_names_declared_parameters(path):
    entries = params_entries(path)
    assert entries
    for pattern, name, value in entries:
        where = f"{path.name} [{pattern}]"
        if pattern == "/**":
            allowed = shared_table()
            assert name in allowed, f"{where}: {name!r} is not a parameter the graph's nodes share"
            check_value(where, name, value, allowed[name])
            continue
        node = pattern.rsplit("/", 1)[-1]
        assert node in GRAPH_NODES, f"{where}: unknown node {node!r}"
        assert pattern in (f"/**/{node}", f"/{node}"), \
            f"{where}: use /**/{node} (any namespace) or /{node}; a bare name matches only the root namespace in rcl"
        check_parameters(where, node, {name: value})


def test_params_files_agree_with_the_nodes_modes():
    train = {(p, n): v for p, n, v in params_entries(TRAIN_YAML)}
    policy = {(p, n): v for p, n, v in params_entries(RUN_POLICY_YAML)}
    assert train[("/**/environment", "wait_for_learner")] is True
    assert policy[("/**/environment", "wait_for_learner")] is False
    assert policy[("/**/sub_controller", "epsilon")] == 0.0
    assert train[("/**/sub_controller", "epsilon")] < 0  # the learner's schedule
    assert ("/learner", "groups") not in train and ("/learner", "resume") not in train  # set by the launch file


@NEEDS_RCLPY
@pytest.mark.parametrize("mode", ["sub-drives", "meta-only"])
def test_robot_graph_parameters_are_declared(mode):
    """What ``hdrqn robot`` and robot.launch.py give each node is what it declares, typed alike."""
    from hdrqn_ros.robot_graph import RobotRun, robot_parameters

    params = robot_parameters(RobotRun("hdrqn-v2", "hdrqn/GridWorld-2Goals-v0", "5", checkpoint="c.pt", mode=mode))
    for name, value in params.pop("/**").items():
        check_value("/**", name, value, shared_table()[name])
    for node, values in params.items():
        check_parameters(f"robot graph [{node}]", node, values)


def test_launch_constants_match_the_code():
    from hdrqn_ros import launch_support

    assert set(launch_support.ALGOS) == set(ALGO_SPECS)
    assert set(launch_support.HIERARCHICAL_ALGOS) == {a for a, s in ALGO_SPECS.items() if s.hierarchical}


@NEEDS_RCLPY
def test_the_launch_default_algo_is_the_nodes():
    from hdrqn_ros import launch_support
    from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS

    assert launch_support.DEFAULT_ALGO == ENV_PARAMETERS["algo"].default


# -- with ROS 2 (skipped where launch / launch_ros are not installed) --------------------------------
def _ros_launch():
    reason = "ROS 2 Jazzy's launch and launch_ros are not installed here (they come with ROS, not pip)"
    pytest.importorskip("launch_ros", reason=reason)
    launch = pytest.importorskip("launch", reason=reason)
    if not hasattr(launch, "LaunchService"):  # the repository's launch/ folder seen as a namespace package
        pytest.skip(reason)
    return launch


def _expand_real(launch, entities, context) -> list:
    from launch_ros.actions import Node

    nodes = []
    for entity in entities:
        if isinstance(entity, Node):
            nodes.append(entity)  # not executed: nothing is started
        elif isinstance(entity, (launch.actions.DeclareLaunchArgument, launch.actions.OpaqueFunction)):
            nodes += _expand_real(launch, entity.visit(context) or [], context)
    return nodes


def _real_nodes(path: Path, **args: str) -> list:
    launch = _ros_launch()
    spec = importlib.util.spec_from_file_location(path.stem.replace(".", "_"), path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    description = mod.generate_launch_description()
    service = launch.LaunchService()
    service.context.launch_configurations.update(args)
    return _expand_real(launch, description.entities, service.context)


def test_train_launch_with_ros_one_group_has_five_nodes():
    nodes = _real_nodes(TRAIN)
    assert len(nodes) == 5
    assert sorted(n.node_executable for n in nodes) == sorted(HIERARCHICAL_NODES + ("learner",))


def test_train_launch_with_ros_two_flat_groups():
    nodes = _real_nodes(TRAIN, groups="2", algo="dqn")
    assert sorted(n.node_executable for n in nodes) == sorted(FLAT_NODES * 2 + ("learner",))


def test_robot_launch_with_ros():
    nodes = _real_nodes(ROBOT, checkpoint="c.pt", mode="sub-drives", episodes="10", seed="0",
                        real_time_factor="20.0", algo="hdrqn-v2", env="hdrqn/GridWorld-2Goals-v0", view="5")
    assert sorted(n.node_executable for n in nodes) == sorted(["loopback_robot", "robot_environment", "critic",
                                                               "meta_controller", "sub_controller"])


def test_run_policy_launch_with_ros():
    nodes = _real_nodes(RUN_POLICY, checkpoint="c.pt")
    assert sorted(n.node_executable for n in nodes) == sorted(HIERARCHICAL_NODES)
    nodes = _real_nodes(RUN_POLICY, policy="policy_dir", algo="dqn")
    assert sorted(n.node_executable for n in nodes) == sorted(FLAT_NODES)
    for both_or_neither in ({"checkpoint": "c.pt", "policy": "policy_dir"}, {}):
        with pytest.raises(RuntimeError, match="exactly one of the launch arguments checkpoint"):
            _real_nodes(RUN_POLICY, **both_or_neither)


def test_run_policy_launch_takes_checkpoint_or_policy():
    """Both optional launch arguments (exactly one is required, checked when expanded), both
    passed to the two controllers."""
    tree = ast.parse(RUN_POLICY.read_text(encoding="utf-8"))
    declared = {}
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "DeclareLaunchArgument":
            kwargs = {k.arg: k.value for k in call.keywords}
            declared[ast.literal_eval(call.args[0])] = kwargs.get("default_value")
    for name in ("checkpoint", "policy"):
        assert name in declared and isinstance(declared[name], ast.Constant) and declared[name].value == "", name
    source = RUN_POLICY.read_text(encoding="utf-8")
    assert '"checkpoint": checkpoint, "policy": policy' in source
