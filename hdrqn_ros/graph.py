"""The training node graph as OS processes: what ``hdrqn up`` starts.

One learner, and per environment group (namespace ``/group<i>``, or ``/`` for a single
group) an environment, a sub-controller and, for hierarchical agents, a critic and a
meta-controller. The parameters go into ``RUN_DIR/params.yaml``, a standard ROS 2
parameters file (``/**`` for what all nodes share), passed with ``--params-file`` as
``ros2 launch`` would.
"""
from __future__ import annotations

from pathlib import Path

import yaml

from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.config import TrainConfig
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.nodes.executables import entry_point
from hdrqn_ros.protocol.wire import group_namespaces
from hdrqn_ros.supervisor import ProcessSpec, python_command

NODE_MODULES = {name: entry_point(name) for name in ("environment", "critic", "meta_controller", "sub_controller",
                                                     "learner")}
"""The training graph's node executables (:mod:`hdrqn_ros.nodes.executables`)."""


def view_parameter(cfg: TrainConfig) -> str:
    return str(cfg.env_kwargs.get("view", 5))


def write_params(cfg: TrainConfig, run_dir: Path, groups: int, config_file: Path, extra: dict | None = None,
                 num_envs: int = 1) -> Path:
    """Write ``run_dir/params.yaml`` for the graph of ``cfg`` (``num_envs`` environments
    per environment node) and return its path."""
    shared = {"algo": cfg.algo, "env": cfg.env, "view": view_parameter(cfg), "seed": cfg.seed}
    doc = {
        "/**": {"ros__parameters": shared},
        "/**/environment": {"ros__parameters": {"wait_for_learner": True, "num_envs": num_envs}},
        "/**/critic": {"ros__parameters": {"num_envs": num_envs}},
        "/**/meta_controller": {"ros__parameters": {"meta_state": cfg.meta_state, "num_envs": num_envs}},
        "/**/sub_controller": {"ros__parameters": {"meta_state": cfg.meta_state, "num_envs": num_envs}},
        "/learner": {"ros__parameters": {"config": str(config_file), "episodes": cfg.episodes,
                                        "run_dir": str(run_dir), "groups": group_namespaces(groups)}},
    }
    for node, values in (extra or {}).items():  # extra: {"environment": {...}} -> key "/**/environment"
        key = "/learner" if node == "learner" else f"/**/{node}"
        doc.setdefault(key, {"ros__parameters": {}})["ros__parameters"].update(values)
    path = run_dir / "params.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def graph_processes(cfg: TrainConfig, params: Path, groups: int, respawn: bool = True) -> list[ProcessSpec]:
    """The processes of the graph: per group its nodes (seeded ``seed + 1000 * i``), then the learner."""
    hierarchical = ALGO_SPECS[cfg.algo].hierarchical
    nodes = ["environment", "critic", "meta_controller", "sub_controller"] if hierarchical else \
        ["environment", "sub_controller"]
    specs = []
    for i, ns in enumerate(group_namespaces(groups)):
        for node in nodes:
            argv = python_command(NODE_MODULES[node]) + ["--ros-args", "--params-file", str(params), "-r", f"__ns:={ns}",
                                     "-p", f"seed:={cfg.seed + 1000 * i}"]
            if node == "environment" and i > 0:
                argv += ["-p", "publish_clock:=false"]  # one sim clock: group 0's
            specs.append(ProcessSpec(name=f"{ns.strip('/') or 'graph'}/{node}", argv=argv, respawn=respawn,
                                     stack_dump_signal=STACK_DUMP_SIGNAL))
    learner_argv = python_command(NODE_MODULES["learner"]) + ["--ros-args", "--params-file", str(params), "-p", "resume:=true"]
    specs.append(ProcessSpec(name="learner", argv=learner_argv, respawn=respawn, required=True,
                             stack_dump_signal=STACK_DUMP_SIGNAL))
    return specs
