"""Launch files and ROS 2 params files: what can be checked without ROS, and a real test with it.

Without ROS: the launch files compile; every ``Node(executable=...)`` is a console script
of ``setup.py``; the launch files are run against small stand-ins for ``launch`` /
``launch_ros`` (recording what they would start) so the nodes, namespaces, seeds and
every parameter name and type they pass are checked against the nodes' own parameter
dicts; the params YAMLs load with the middleware's parser and name only parameters their
nodes declare, with the types the nodes expect. With ROS 2 (``launch`` importable): the
real ``generate_launch_description()`` is expanded in a ``LaunchService``'s context.
"""
from __future__ import annotations

import ast
import importlib.util
import itertools
import py_compile
import sys
import types
from pathlib import Path

import pytest

from hdrqn_ros.agents.algorithms import ALGO_SPECS
from hdrqn_ros.config import ALGOS
from hdrqn_ros.graph import group_namespaces
from hdrqn_ros.middleware.ros_args import load_params_file
from hdrqn_ros.nodes import environment, learner, nav
from hdrqn_ros.nodes.common import ENV_DEFAULTS
from hdrqn_ros.nodes.controllers import CONTROLLER_PARAMETERS

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "launch" / "train.launch.py"
RUN_POLICY = ROOT / "launch" / "run_policy.launch.py"
LAUNCH_FILES = (TRAIN, RUN_POLICY)
TRAIN_YAML = ROOT / "config" / "ros" / "train.yaml"
RUN_POLICY_YAML = ROOT / "config" / "ros" / "run_policy.yaml"
PARAM_FILES = (TRAIN_YAML, RUN_POLICY_YAML)

GLOBAL_PARAMETERS = {"dds_interface": "", "ros_domain_id": 0, "max_message_bytes": 0, "use_sim_time": False}
"""Read by the middleware (Cyclone backend) or by rclpy itself, allowed on every node."""
NODE_PARAMETERS = {
    "environment": environment.PARAMETERS,
    "critic": ENV_DEFAULTS,
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


def test_launch_constants_match_the_code():
    for path in LAUNCH_FILES:
        mod = load_with_stubs(path)
        assert set(mod.ALGOS) == set(ALGOS) == set(ALGO_SPECS)
        assert set(mod.HIERARCHICAL_ALGOS) == {a for a, s in ALGO_SPECS.items() if s.hierarchical}
        assert mod.DEFAULT_ALGO == ENV_DEFAULTS["algo"]
        assert mod.PACKAGE == "hdrqn_ros"
    mod = load_with_stubs(TRAIN)
    for groups in (1, 2, 5):
        assert mod.group_namespaces(groups) == group_namespaces(groups)


# -- the launch files run against stand-ins for launch / launch_ros ------------------------------------
class _Recorded:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class _LaunchConfiguration(_Recorded):
    def perform(self, context) -> str:
        return context.launch_configurations[self.args[0]]


class _PackageNotFoundError(KeyError):
    pass


def _no_package(name):
    raise _PackageNotFoundError(name)


def _stub_modules() -> dict[str, types.ModuleType]:
    def module(name, **attrs):
        mod = types.ModuleType(name)
        mod.__dict__.update(attrs)
        return mod

    def recorder(name):
        return type(name, (_Recorded,), {})

    return {
        "ament_index_python": module("ament_index_python"),
        "ament_index_python.packages": module("ament_index_python.packages", PackageNotFoundError=_PackageNotFoundError,
                                              get_package_share_directory=_no_package),
        "launch": module("launch", LaunchDescription=recorder("LaunchDescription")),
        "launch.actions": module("launch.actions", **{n: recorder(n) for n in (
            "DeclareLaunchArgument", "EmitEvent", "LogInfo", "OpaqueFunction", "RegisterEventHandler")}),
        "launch.event_handlers": module("launch.event_handlers", OnProcessExit=recorder("OnProcessExit")),
        "launch.events": module("launch.events", Shutdown=recorder("Shutdown")),
        "launch.substitutions": module("launch.substitutions", LaunchConfiguration=_LaunchConfiguration),
        "launch_ros": module("launch_ros"),
        "launch_ros.actions": module("launch_ros.actions", Node=recorder("Node")),
    }


_counter = itertools.count()


def _load(path: Path) -> types.ModuleType:
    spec = importlib.util.spec_from_file_location(f"_hdrqn_launch_{path.stem.split('.')[0]}_{next(_counter)}", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def load_with_stubs(path: Path) -> types.ModuleType:
    saved = {name: sys.modules.get(name) for name in _stub_modules()}
    sys.modules.update(_stub_modules())
    try:
        return _load(path)
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


class _Context:
    def __init__(self, configurations: dict[str, str]):
        self.launch_configurations = configurations


def expand_with_stubs(path: Path, **args: str):
    """(declared argument defaults, the actions the OpaqueFunction returns) for launch ``args``."""
    mod = load_with_stubs(path)
    description = mod.generate_launch_description()
    (entities,) = description.args
    declared = {e.args[0]: e.kwargs.get("default_value") for e in entities if type(e).__name__ == "DeclareLaunchArgument"}
    configurations = {name: default for name, default in declared.items() if default is not None}
    configurations.update(args)
    missing = set(declared) - set(configurations)
    if missing:
        raise KeyError(f"required launch arguments not given: {sorted(missing)}")
    (opaque,) = [e for e in entities if type(e).__name__ == "OpaqueFunction"]
    actions = opaque.kwargs["function"](_Context(configurations))
    return declared, actions


def nodes_of(actions) -> list[dict]:
    """Each Node's kwargs, with ``params`` = the merged dict parameters (the file comes first)."""
    out = []
    for a in actions:
        if type(a).__name__ != "Node":
            continue
        kw = dict(a.kwargs)
        files, dicts = kw["parameters"][0], kw["parameters"][1:]
        assert isinstance(files, str) and all(isinstance(d, dict) for d in dicts), "params file first, then dicts"
        kw["params_file"] = files
        kw["params"] = {k: v for d in dicts for k, v in d.items()}
        out.append(kw)
    return out


def check_nodes(nodes: list[dict]) -> None:
    scripts = console_scripts()
    for n in nodes:
        assert n["package"] == "hdrqn_ros" and n["executable"] in scripts and n["name"] == n["executable"]
        assert n["output"] == "screen"
        check_parameters(f"{n['namespace']}/{n['name']} (launch)", n["executable"], n["params"])
        assert Path(n["params_file"]).is_file()


def test_train_launch_one_group_defaults():
    declared, actions = expand_with_stubs(TRAIN)
    assert {"params_file", "groups", "algo", "env", "episodes", "run_dir", "respawn"} <= set(declared)
    assert declared["groups"] == "1" and declared["respawn"] == "true"
    assert Path(declared["params_file"]) == TRAIN_YAML  # source tree fallback of the share directory
    nodes = nodes_of(actions)
    check_nodes(nodes)
    assert [(n["namespace"], n["executable"]) for n in nodes] == \
        [("/", e) for e in HIERARCHICAL_NODES] + [("/", "learner")]  # the YAML's algo is hierarchical
    by = {n["executable"]: n for n in nodes}
    assert by["environment"]["params"]["wait_for_learner"] is True
    assert all(n["params"]["seed"] == 0 and n["respawn"] is True for n in nodes)
    assert by["learner"]["params"]["groups"] == ["/"] and by["learner"]["params"]["resume"] is True
    assert "algo" not in by["environment"]["params"]  # empty launch args leave the file's values


def test_train_launch_groups_seeds_and_overrides(tmp_path):
    _, actions = expand_with_stubs(TRAIN, groups="3", algo="hdrqn-v1", env="hdrqn/FourRooms-3Goals-v0", view="3",
                                   seed="7", episodes="42", run_dir=str(tmp_path / "run"), respawn="false")
    nodes = nodes_of(actions)
    check_nodes(nodes)
    namespaces = ["/group0", "/group1", "/group2"]
    assert [(n["namespace"], n["executable"]) for n in nodes] == \
        [(ns, e) for ns in namespaces for e in HIERARCHICAL_NODES] + [("/", "learner")]
    for n in nodes:
        assert n["params"]["algo"] == "hdrqn-v1" and n["params"]["env"] == "hdrqn/FourRooms-3Goals-v0"
        assert n["params"]["view"] == "3"  # stays a string
        assert n["respawn"] is False
        i = namespaces.index(n["namespace"]) if n["namespace"] != "/" else 0
        assert n["params"]["seed"] == 7 + 1000 * i
    lp = nodes[-1]["params"]
    assert lp["groups"] == namespaces and lp["episodes"] == 42 and lp["run_dir"] == str(tmp_path / "run")


def test_train_launch_flat_agent_has_no_critic_or_meta():
    _, actions = expand_with_stubs(TRAIN, algo="dqn", groups="2")
    nodes = nodes_of(actions)
    check_nodes(nodes)
    assert [(n["namespace"], n["executable"]) for n in nodes] == \
        [(ns, e) for ns in ("/group0", "/group1") for e in FLAT_NODES] + [("/", "learner")]


def test_train_launch_algo_from_the_params_file(tmp_path):
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    algo: drqn\n    seed: 5\n")
    _, actions = expand_with_stubs(TRAIN, params_file=str(params))
    nodes = nodes_of(actions)
    assert [n["executable"] for n in nodes] == list(FLAT_NODES) + ["learner"]
    assert all(n["params_file"] == str(params) and n["params"]["seed"] == 5 for n in nodes)


@pytest.mark.parametrize("args, message", [({"algo": "ppo"}, "unknown algo"), ({"groups": "0"}, "groups"),
                                           ({"episodes": "many"}, "episodes"), ({"respawn": "maybe"}, "respawn")])
def test_train_launch_rejects_bad_arguments(args, message):
    with pytest.raises(RuntimeError, match=message):
        expand_with_stubs(TRAIN, **args)


def _learner_exit_handler(actions):
    (register,) = [a for a in actions if type(a).__name__ == "RegisterEventHandler"]
    (handler,) = register.args
    learner_action = [a for a in actions if type(a).__name__ == "Node" and a.kwargs["executable"] == "learner"][0]
    assert handler.kwargs["target_action"] is learner_action
    return handler.kwargs["on_exit"]


def _shuts_down(result) -> bool:
    return any(type(a).__name__ == "EmitEvent" and type(a.kwargs["event"]).__name__ == "Shutdown" for a in result)


def test_train_launch_learner_exit_shuts_down():
    on_exit = _learner_exit_handler(expand_with_stubs(TRAIN)[1])  # respawn true
    assert _shuts_down(on_exit(types.SimpleNamespace(returncode=0), None))  # finished
    assert _shuts_down(on_exit(types.SimpleNamespace(returncode=2), None))  # bad parameters
    assert not _shuts_down(on_exit(types.SimpleNamespace(returncode=1), None))  # crash: respawn and resume
    on_exit = _learner_exit_handler(expand_with_stubs(TRAIN, respawn="false")[1])
    assert all(_shuts_down(on_exit(types.SimpleNamespace(returncode=rc), None)) for rc in (0, 1, -9))


def test_run_policy_launch_defaults():
    declared, actions = expand_with_stubs(RUN_POLICY, checkpoint="runs/x/checkpoints/last.pt")
    assert declared["checkpoint"] is None  # required
    assert declared["epsilon"] == "0.0" and declared["with_environment"] == "true"
    assert declared["observation_source"] == "topic"
    assert {"subgoal_table", "action_table", "observation_source", "cmd_vel_topic", "goal_pose_topic"} <= set(declared)
    assert Path(declared["params_file"]) == RUN_POLICY_YAML
    nodes = nodes_of(actions)
    check_nodes(nodes)
    assert [n["executable"] for n in nodes] == list(HIERARCHICAL_NODES)
    by = {n["executable"]: n for n in nodes}
    assert by["environment"]["params"]["wait_for_learner"] is False
    for role in ("meta_controller", "sub_controller"):
        assert by[role]["params"]["checkpoint"] == "runs/x/checkpoints/last.pt"
        assert by[role]["params"]["epsilon"] == 0.0
    assert by["sub_controller"]["params"]["observation_source"] == "topic"
    assert "subgoal_table" not in by["meta_controller"]["params"]  # empty: the file's value
    (register,) = [a for a in actions if type(a).__name__ == "RegisterEventHandler"]
    assert register.args[0].kwargs["target_action"] is [a for a in actions if type(a).__name__ == "Node"][0]


def test_run_policy_launch_nav2_without_environment():
    _, actions = expand_with_stubs(
        RUN_POLICY, checkpoint="c.pt", with_environment="false", epsilon="0.05", namespace="/robot1",
        subgoal_table="/t/subgoals.yaml", goal_pose_topic="goal_pose", action_table="/t/actions.yaml",
        cmd_vel_topic="cmd_vel_nav", observation_source="costmap", costmap_topic="/local_costmap/costmap")
    nodes = nodes_of(actions)
    check_nodes(nodes)
    assert [(n["namespace"], n["executable"]) for n in nodes] == \
        [("/robot1", e) for e in ("critic", "meta_controller", "sub_controller")]
    by = {n["executable"]: n["params"] for n in nodes}
    assert by["meta_controller"]["subgoal_table"] == "/t/subgoals.yaml" and "action_table" not in by["meta_controller"]
    assert by["sub_controller"]["action_table"] == "/t/actions.yaml" and "subgoal_table" not in by["sub_controller"]
    assert by["sub_controller"]["observation_source"] == "costmap" and by["sub_controller"]["epsilon"] == 0.05
    assert not [a for a in actions if type(a).__name__ == "RegisterEventHandler"]


def test_run_policy_launch_flat_agent_and_bad_arguments():
    nodes = nodes_of(expand_with_stubs(RUN_POLICY, checkpoint="c.pt", algo="drqn")[1])
    assert [n["executable"] for n in nodes] == list(FLAT_NODES)
    with pytest.raises(KeyError, match="checkpoint"):
        expand_with_stubs(RUN_POLICY)
    for args, message in (({"epsilon": "2"}, "epsilon"), ({"observation_source": "lidar"}, "observation_source"),
                          ({"algo": "a2c"}, "unknown algo"), ({"checkpoint": ""}, "checkpoint")):
        with pytest.raises(RuntimeError, match=message):
            expand_with_stubs(RUN_POLICY, **{"checkpoint": "c.pt", **args})


# -- with ROS 2 (skipped where launch / launch_ros are not installed) --------------------------------
def _ros_launch():
    pytest.importorskip("launch_ros")
    launch = pytest.importorskip("launch")
    if not hasattr(launch, "LaunchService"):  # the repository's launch/ folder seen as a namespace package
        pytest.skip("the ROS 2 launch package is not installed")
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
    mod = _load(path)
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


def test_run_policy_launch_with_ros():
    nodes = _real_nodes(RUN_POLICY, checkpoint="c.pt")
    assert sorted(n.node_executable for n in nodes) == sorted(HIERARCHICAL_NODES)
