"""Train an agent as a ROS 2 node graph: ``ros2 launch hdrqn_ros train.launch.py``.

The same graph ``hdrqn up`` starts without ROS (``hdrqn_ros/graph.py``): per environment
group (namespace ``/`` for one group, ``/group0``, ``/group1``... for several) an
``environment`` (``wait_for_learner: true``), for hierarchical agents (hdrqn-v2, hdrqn-v1,
hdqn) a ``critic`` and a ``meta_controller``, and a ``sub_controller``; plus one
``learner`` in ``/`` (``groups`` = the list of namespaces, ``resume: true``). Group ``i``'s
nodes get ``seed + 1000 * i``.

Parameters: the params file (default: this package's ``config/ros/train.yaml``) first,
then the launch arguments given on the command line, which win. A launch argument left
empty keeps the params file's value (or the node's default). Examples::

    ros2 launch hdrqn_ros train.launch.py
    ros2 launch hdrqn_ros train.launch.py algo:=hdrqn-v1 groups:=4 episodes:=5000 run_dir:=runs/v1
    ros2 launch hdrqn_ros train.launch.py params_file:=/path/to/my_train.yaml respawn:=false
    ros2 launch hdrqn_ros train.launch.py record:=bags/graph-run

When the learner exits, the whole launch is shut down: always with ``respawn:=false``;
with ``respawn:=true`` (default) when it exits with 0 (training finished, or it was
stopped) or 2 (bad parameters, which a restart cannot fix). Any other exit (a crash, an
exception in training) restarts it after ``respawn_delay`` and it resumes from
``run_dir``'s last checkpoint. The other nodes are restarted, with ``respawn:=true``, after a
crash; one that exits with 0 or 2 (bad parameters, or a ROS package it needs is missing) is not.
"""
from __future__ import annotations

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, LogInfo, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch_ros.actions import Node

from hdrqn_ros.protocol.wire import group_namespaces
from hdrqn_ros.launch_support import (ALGOS, DEFAULT_ALGO, HIERARCHICAL_ALGOS, NOT_RESTARTED, PACKAGE, SHARED_ARGS,
                                      arg, bool_arg, int_arg, restarted_node, share_dir, shared_file_parameters)

RESPAWN_DELAY_S = 2.0


def _graph(context):
    params_file = arg(context, "params_file")
    file_shared = shared_file_parameters(params_file)
    groups = int_arg(context, "groups", 1) or 1
    respawn = bool_arg(context, "respawn")

    shared = {name: arg(context, name) for name in SHARED_ARGS if arg(context, name)}
    algo = shared.get("algo") or str(file_shared.get("algo", DEFAULT_ALGO))
    if algo not in ALGOS:
        raise RuntimeError(f"unknown algo {algo!r}; choose one of {', '.join(ALGOS)}")
    seed = int_arg(context, "seed", 0)
    if seed is None:
        seed = int(file_shared.get("seed", 0))
    hierarchical = algo in HIERARCHICAL_ALGOS
    namespaces = group_namespaces(groups)

    actions = [LogInfo(msg=f"hdrqn_ros training graph: {algo}, {groups} group(s) {namespaces}, "
                           f"params {params_file}, respawn {respawn}")]
    num_envs = int_arg(context, "num_envs", 1)
    for i, ns in enumerate(namespaces):
        group = {**shared, "seed": seed + 1000 * i, **({"num_envs": num_envs} if num_envs is not None else {})}
        nodes = [("environment", {**group, "wait_for_learner": True}), ("critic", group),
                 ("meta_controller", group), ("sub_controller", group)]
        for name, parameters in nodes:
            if name in ("critic", "meta_controller") and not hierarchical:
                continue

            def make_node(name=name, ns=ns, parameters=parameters):
                return Node(package=PACKAGE, executable=name, name=name, namespace=ns,
                            parameters=[params_file, parameters], output="screen")

            actions.extend(restarted_node(make_node, RESPAWN_DELAY_S) if respawn else [make_node()])

    learner_params = {**shared, "seed": seed, "groups": namespaces, "resume": True}
    episodes = int_arg(context, "episodes", 1)
    if episodes is not None:
        learner_params["episodes"] = episodes
    for name in ("run_dir", "config", "record"):
        if arg(context, name):
            learner_params[name] = arg(context, name)
    learner = Node(package=PACKAGE, executable="learner", name="learner", namespace="/",
                   parameters=[params_file, learner_params],
                   respawn=respawn, respawn_delay=RESPAWN_DELAY_S, output="screen")
    actions.append(learner)

    def on_learner_exit(event, _context):
        if respawn and event.returncode not in NOT_RESTARTED:
            return [LogInfo(msg=f"learner exited with {event.returncode}: restarting it (resume from run_dir)")]
        return [LogInfo(msg=f"learner exited with {event.returncode}: shutting the training graph down"),
                EmitEvent(event=Shutdown(reason=f"learner exited with {event.returncode}"))]

    actions.append(RegisterEventHandler(OnProcessExit(target_action=learner, on_exit=on_learner_exit)))
    return actions


def generate_launch_description() -> LaunchDescription:
    default_params = str(share_dir() / "config" / "ros" / "train.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS 2 parameters file for all nodes (/** shared, then per node)"),
        DeclareLaunchArgument("groups", default_value="1",
                              description="environment groups (environment + controllers each) feeding the learner"),
        DeclareLaunchArgument("num_envs", default_value="",
                              description="environments each environment node steps as one batch, 1..64 "
                                          "(empty: params file, else 1)"),
        DeclareLaunchArgument("algo", default_value="",
                              description=f"agent: {', '.join(ALGOS)} (empty: params file, else {DEFAULT_ALGO})"),
        DeclareLaunchArgument("env", default_value="",
                              description="environment id, e.g. hdrqn/GridWorld-2Goals-v0 (empty: params file)"),
        DeclareLaunchArgument("view", default_value="",
                              description="gridworld view: odd number of cells or 'full' (empty: params file)"),
        DeclareLaunchArgument("seed", default_value="",
                              description="base seed; group i uses seed + 1000 i (empty: params file, else 0)"),
        DeclareLaunchArgument("episodes", default_value="",
                              description="training episodes of the learner (empty: params file)"),
        DeclareLaunchArgument("run_dir", default_value="",
                              description="learner output directory, relative to the launch's working directory "
                                          "(empty: params file)"),
        DeclareLaunchArgument("config", default_value="",
                              description="training config YAML for the learner, as hdrqn train --config "
                                          "(empty: params file)"),
        DeclareLaunchArgument("record", default_value="",
                              description="bag directory: the learner records every message it takes from the "
                                          "groups (rosbag2 MCAP; empty: params file, else no recording)"),
        DeclareLaunchArgument("respawn", default_value="true",
                              description="restart nodes that exit (the learner resumes from run_dir)"),
        OpaqueFunction(function=_graph),
    ])
