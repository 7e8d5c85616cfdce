"""A trained agent on the loopback robot: the nodes and their parameters.

What ``hdrqn robot`` starts as processes and ``launch/robot.launch.py`` as launch nodes:
``loopback_robot``, ``robot_environment``, ``critic``, ``meta_controller`` (hierarchical
agents) and ``sub_controller``, all on simulated time (``use_sim_time``). The loopback robot
speaks as Nav2 ships a robot (:data:`NAV2_LOOPBACK`): tf ``map -> odom -> base_link`` with a
``map -> odom`` offset that drifts with odometry's error, the local costmap in ``odom`` with
inflation, sent as updates while its window stays, a 1 s velocity deadman; the robot
environment reads the pose from tf. Two ways to drive (``docs/nav2.md``):

- ``sub-drives``: each action is a closed-loop motion primitive (one cell, or 90 degrees)
  that the sub-controller streams on ``cmd_vel`` (the holonomic table
  ``config/nav2/actions_holonomic.yaml``: the simulator's moves); the robot starts at a yaw
  of 0.3 rad;
- ``meta-only``: the meta-controller sends each option's place as a ``navigate_to_pose``
  goal, the robot's navigator (differential drive, start yaw 0.5 rad) drives there and stops
  within Nav2's 0.25 m; the goal's result ends the option (ABORTED at once), and an option
  also ends after ``option_timeout`` seconds.

With ``record``, a ``learner`` node records the episodes to a rosbag2 MCAP bag (the
graph's own topics: ``hdrqn train --from-bag`` trains on it).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.nodes.executables import entry_point
from hdrqn_ros.supervisor import ProcessSpec, python_command

MODES = ("sub-drives", "meta-only")
NODE_MODULES = {name: entry_point(name) for name in ("loopback_robot", "robot_environment", "critic",
                                                     "meta_controller", "sub_controller", "learner")}
"""The robot graph's node executables (:mod:`hdrqn_ros.nodes.executables`)."""
NAV2_LOOPBACK = {"odom_frame": "odom", "map_to_odom": [0.8, 0.4, 0.2], "odom_error": [0.02, 0.01],
                 "inflation_radius": 0.7, "always_send_full_costmap": False, "cmd_vel_timeout": 1.0}
"""The loopback robot's settings that make it a Nav2 robot as Nav2 ships one (``nav2_bringup``'s
Jazzy parameters: local costmap in ``odom``, inflation 0.7 m, ``always_send_full_costmap``
false; the velocity smoother's 1 s deadman); ``map -> odom`` starts at (0.8 m, 0.4 m, 0.2 rad) and
drifts with 2% / 1% odometry error."""
START_YAW = {"sub-drives": 0.3, "meta-only": 0.5}
"""The robot's yaw (rad) at each episode's start: never the simulator's facing."""
HOLONOMIC_ACTIONS = Path(__file__).resolve().parents[1] / "config" / "nav2" / "actions_holonomic.yaml"
"""The simulator's moves as velocities (source tree; installed to share/hdrqn_ros/config/nav2)."""


@dataclass
class RobotRun:
    """One robot session's settings (the launch arguments / ``hdrqn robot`` options)."""

    algo: str
    env: str
    view: str
    checkpoint: str = ""
    policy: str = ""
    mode: str = "sub-drives"
    episodes: int = 100
    seed: int = 0
    real_time_factor: float = 20.0
    step_period: float = 2.5
    option_timeout: float = 30.0
    episode_log: str = ""
    action_table: str = str(HOLONOMIC_ACTIONS)
    record: str = ""  # a new bag: a learner node records every message of the robot's episodes
    learner_dir: str = ""  # the recording learner's run directory


def robot_parameters(run: RobotRun) -> dict[str, dict]:
    """Each node's parameters (node name -> {name: value}); ``"/**"`` is what all share."""
    if run.mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {run.mode!r}")
    if bool(run.checkpoint) == bool(run.policy):
        raise ValueError("give exactly one of checkpoint and policy")
    if run.record and not run.policy:
        raise ValueError("recording needs an exported policy (frozen): the recording learner's weights would "
                         "replace a checkpoint's in the controllers")
    drives = run.mode == "sub-drives"
    acting = {"checkpoint": run.checkpoint, "policy": run.policy, "epsilon": 0.0}
    params = {
        "/**": {"algo": run.algo, "env": run.env, "view": run.view, "seed": run.seed, "use_sim_time": True},
        "loopback_robot": {**NAV2_LOOPBACK, "lockstep": "control" if drives else "action",
                           "drive": "holonomic" if drives else "diff", "start_yaw": START_YAW[run.mode],
                           "real_time_factor": run.real_time_factor, "step_period": run.step_period},
        "robot_environment": {"subgoal_poses_topic": "subgoal_poses", "new_layout_each_episode": True,
                              "costmap_topic": "local_costmap/costmap",
                              "visit_rule": "cell" if drives else "tolerance",
                              "global_costmap_topic": "global_costmap/costmap", "step_period": run.step_period,
                              "max_episodes": run.episodes, "episode_log": run.episode_log,
                              "wait_for_learner": bool(run.record)},
        "critic": {"option_timeout": 0.0, "navigation_outcome": False} if drives else
                  {"option_timeout": run.option_timeout, "navigation_outcome": True},
        "meta_controller": {**acting, **({} if drives else {"subgoal_poses_topic": "subgoal_poses",
                                                            "navigation": "action"})},
        "sub_controller": {**acting, **({"action_table": run.action_table, "cmd_vel_topic": "cmd_vel"}
                                        if drives else {})},
    }
    if run.record:
        params["learner"] = {"record": run.record, "episodes": run.episodes, "run_dir": run.learner_dir,
                             "evaluate": False}
    return params


def write_params(run: RobotRun, path: Path) -> Path:
    """``path``: a standard ROS 2 parameters file of :func:`robot_parameters`."""
    doc = {("/**" if node == "/**" else f"/**/{node}"): {"ros__parameters": values}
           for node, values in robot_parameters(run).items()}
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def robot_processes(run: RobotRun, params: Path, hierarchical: bool, managed: tuple[str, ...] = ()) -> list[ProcessSpec]:
    """The node processes (the robot environment is required, its exit ends the session;
    when recording, the learner's exit does: it records every episode first). The nodes
    named in ``managed`` start as managed nodes, unconfigured (``--managed``)."""
    nodes = ["loopback_robot", "robot_environment", "critic", "meta_controller", "sub_controller"] if hierarchical \
        else ["loopback_robot", "robot_environment", "sub_controller"]
    if run.record:
        nodes.append("learner")
    specs = []
    for node in nodes:
        command = python_command(NODE_MODULES[node]) + (["--managed"] if node in managed else [])
        specs.append(ProcessSpec(name=node, argv=command + ["--ros-args", "--params-file", str(params)],
                                 required=node == "robot_environment" and not run.record,
                                 stack_dump_signal=STACK_DUMP_SIGNAL))
    return specs
