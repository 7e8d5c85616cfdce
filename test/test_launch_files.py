"""Launch files and ROS 2 params files: what can be checked without ROS, and a real test with it.

Without ROS: the launch files compile; every ``Node(executable=...)`` is a console script
of ``setup.py``; the params YAMLs load with the middleware's parser and name only
parameters their nodes declare, with the types the nodes expect. With ROS 2 (``launch`` importable): the
real ``generate_launch_description()`` is expanded in a ``LaunchService``'s context.
"""
from __future__ import annotations

import ast
import importlib.util
import py_compile
from pathlib import Path

import pytest

from hdrqn_ros.agents.algorithms import ALGO_SPECS
from hdrqn_ros.middleware.port import ParameterError
from hdrqn_ros.middleware.ros_args import load_params_file
from hdrqn_ros.nodes import critic, environment, learner, loopback_robot, nav, robot_environment
from hdrqn_ros.nodes.common import ENV_DEFAULTS
from hdrqn_ros.nodes.controllers import CONTROLLER_PARAMETERS

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "launch" / "train.launch.py"
RUN_POLICY = ROOT / "launch" / "run_policy.launch.py"
ROBOT = ROOT / "launch" / "robot.launch.py"
LAUNCH_FILES = (TRAIN, RUN_POLICY, ROBOT)
TRAIN_YAML = ROOT / "config" / "ros" / "train.yaml"
RUN_POLICY_YAML = ROOT / "config" / "ros" / "run_policy.yaml"
PARAM_FILES = (TRAIN_YAML, RUN_POLICY_YAML)

GLOBAL_PARAMETERS = {"dds_interface": "", "ros_domain_id": 0, "max_message_bytes": 0, "use_sim_time": False}
"""Read by the middleware (Cyclone backend) or by rclpy itself, allowed on every node."""
NODE_PARAMETERS = {
    "environment": environment.PARAMETERS,
    "critic": critic.PARAMETERS,
    "robot_environment": robot_environment.PARAMETERS,
    "loopback_robot": loopback_robot.PARAMETERS,
    # the Nav2 adapter parameters are being wired into the controllers (hdrqn_ros/nodes/nav.py)
    "meta_controller": {**CONTROLLER_PARAMETERS, **nav.META_PARAMETERS},
    "sub_controller": {**CONTROLLER_PARAMETERS, **nav.SUB_PARAMETERS},
    "learner": learner.PARAMETERS,
}
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


def check_value(where: str, name: str, value, default) -> None:
    """``value`` has the type rclpy would accept for a parameter declared with ``default``
    (no int for a double: rclpy refuses it, unlike the Cyclone backend)."""
    if isinstance(default, list):
        assert isinstance(value, (list, tuple)) and value, f"{where}: {name} must be a non-empty list, got {value!r}"
        assert all(type(v) is type(default[0]) for v in value), f"{where}: {name} items must be like {default!r}"
    else:
        assert type(value) is type(default), \
            f"{where}: {name} = {value!r} ({type(value).__name__}) but the node declares {type(default).__name__}"


def check_parameters(where: str, node: str, params: dict) -> None:
    allowed = {**NODE_PARAMETERS[node], **GLOBAL_PARAMETERS}
    for name, value in params.items():
        assert name in allowed, f"{where}: {node} has no parameter {name!r} (it declares {sorted(allowed)})"
        check_value(where, name, value, allowed[name])


# -- static checks ------------------------------------------------------------------------------
@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_compiles(path, tmp_path):
    py_compile.compile(str(path), cfile=str(tmp_path / "out.pyc"), doraise=True)


@pytest.mark.parametrize("path", LAUNCH_FILES, ids=lambda p: p.name)
def test_every_executable_is_a_console_script(path):
    scripts = console_scripts()
    calls = [n for n in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
             if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "Node"]
    assert calls, f"{path.name} starts no Node"
    for call in calls:
        kwargs = {k.arg: k.value for k in call.keywords}
        assert "executable" in kwargs, f"{path.name}:{call.lineno}: Node without executable="
        exe = kwargs["executable"]
        assert isinstance(exe, ast.Constant), f"{path.name}:{call.lineno}: executable must be a literal string"
        assert exe.value in scripts, f"{path.name}:{call.lineno}: {exe.value!r} is not a console script {scripts}"
        assert exe.value in NODE_PARAMETERS
        name = kwargs.get("name")
        assert isinstance(name, ast.Constant) and name.value == exe.value, "node name = executable name"


@pytest.mark.parametrize("path", PARAM_FILES, ids=lambda p: p.name)
def test_params_file_names_declared_parameters(path):
    entries = load_params_file(path)
    assert entries
    for pattern, name, value in entries:
        where = f"{path.name} [{pattern}]"
        if pattern == "/**":
            allowed = {**ENV_DEFAULTS, **GLOBAL_PARAMETERS}  # every node declares ENV_DEFAULTS
            assert name in allowed, f"{where}: {name!r} is not a parameter every node declares"
            check_value(where, name, value, allowed[name])
            continue
        node = pattern.rsplit("/", 1)[-1]
        assert node in NODE_PARAMETERS, f"{where}: unknown node {node!r}"
        assert pattern in (f"/**/{node}", f"/{node}"), \
            f"{where}: use /**/{node} (any namespace) or /{node}; a bare name matches only the root namespace in rcl"
        check_parameters(where, node, {name: value})


def test_params_files_agree_with_the_nodes_modes():
    train = {(p, n): v for p, n, v in load_params_file(TRAIN_YAML)}
    policy = {(p, n): v for p, n, v in load_params_file(RUN_POLICY_YAML)}
    assert train[("/**/environment", "wait_for_learner")] is True
    assert policy[("/**/environment", "wait_for_learner")] is False
    assert policy[("/**/sub_controller", "epsilon")] == 0.0
    assert train[("/**/sub_controller", "epsilon")] < 0  # the learner's schedule
    assert ("/learner", "groups") not in train and ("/learner", "resume") not in train  # set by the launch file


@pytest.mark.parametrize("mode", ["sub-drives", "meta-only"])
def test_robot_graph_parameters_are_declared(mode):
    """What ``hdrqn robot`` and robot.launch.py give each node is what it declares, typed alike."""
    from hdrqn_ros.robot_graph import RobotRun, robot_parameters

    params = robot_parameters(RobotRun("hdrqn-v2", "hdrqn/GridWorld-2Goals-v0", "5", checkpoint="c.pt", mode=mode))
    for name, value in params.pop("/**").items():
        check_value("/**", name, value, {**ENV_DEFAULTS, **GLOBAL_PARAMETERS}[name])
    for node, values in params.items():
        check_parameters(f"robot graph [{node}]", node, values)


def test_launch_constants_match_the_code():
    from hdrqn_ros import launch_support

    assert set(launch_support.ALGOS) == set(ALGO_SPECS)
    assert set(launch_support.HIERARCHICAL_ALGOS) == {a for a, s in ALGO_SPECS.items() if s.hierarchical}
    assert launch_support.DEFAULT_ALGO == ENV_DEFAULTS["algo"]


def test_params_file_as_launch_ros_writes_it_loads(tmp_path):
    """launch_ros dumps a Node's dict parameters with ``yaml.dump``, so lists become
    ``!!python/tuple`` (rcl reads them as sequences); our parser must too, and still refuse
    every other Python tag."""
    import yaml

    path = tmp_path / "launch_params_x"
    path.write_text(yaml.dump({"/learner": {"ros__parameters": {"groups": ("/group0", "/group1"), "resume": True}}}))
    assert "!!python/tuple" in path.read_text()
    assert ("/learner", "groups", ["/group0", "/group1"]) in load_params_file(path)
    path.write_text("/learner:\n  ros__parameters:\n    x: !!python/object/apply:os.getcwd []\n")
    with pytest.raises(ParameterError, match="not valid YAML"):
        load_params_file(path)


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
