"""Run trained controllers without a learner: ``ros2 launch hdrqn_ros run_policy.launch.py checkpoint:=...``
(torch) or ``policy:=...`` (an exported ONNX policy: the controllers never import torch).

Starts, in ``namespace`` (default ``/``), a ``sub_controller`` and, for hierarchical
agents (hdrqn-v2, hdrqn-v1, hdqn), a ``critic`` and a ``meta_controller``, both
controllers acting with exactly one of: the weights of ``checkpoint``
(``RUN_DIR/checkpoints/last.pt``), or the exported policy directory ``policy``
(``hdrqn export --checkpoint ... --out DIR``; numpy and onnxruntime only, see
``docs/deploy.md``); and a fixed ``epsilon`` (default 0.0: greedy). With ``with_environment:=true`` (default) the simulator runs too,
with ``wait_for_learner: false``; when it exits (``max_episodes`` reached) the launch
shuts down. With ``with_environment:=false`` something else must publish the
environment's topics (``env_step``, ``observation``, ``subgoal_images``), and the Nav2
adapter parameters connect the controllers to a robot (``docs/nav2.md``)::

    ros2 launch hdrqn_ros run_policy.launch.py checkpoint:=runs/x/checkpoints/last.pt
    ros2 launch hdrqn_ros run_policy.launch.py policy:=runs/x/policy
    ros2 launch hdrqn_ros run_policy.launch.py checkpoint:=runs/x/checkpoints/last.pt algo:=hdrqn-v1 \\
        env:=hdrqn/FourRooms-2Goals-v0 epsilon:=0.05
    ros2 launch hdrqn_ros run_policy.launch.py checkpoint:=runs/x/checkpoints/last.pt with_environment:=false \\
        subgoal_table:=/path/subgoals.yaml action_table:=/path/actions.yaml observation_source:=costmap

The ``algo``, ``env`` and ``view`` must be those the checkpoint was trained with (a
policy's algo, sizes and hDRQNv2 ``meta_state`` are checked by the nodes: exit 2 naming
the mismatch). Parameters: the params file (default: this package's
``config/ros/run_policy.yaml``) first, then the launch arguments, which win; an empty
argument keeps the file's value. ``checkpoint`` and ``policy`` (the one not given as
``""``), ``epsilon`` and ``observation_source`` are always passed.
"""
from __future__ import annotations

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, LogInfo, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch_ros.actions import Node

from hdrqn_ros.launch_support import (ALGOS, DEFAULT_ALGO, HIERARCHICAL_ALGOS, PACKAGE, SHARED_ARGS, arg, bool_arg,
                                      float_arg, share_dir, shared_file_parameters)

META_NAV_ARGS = ("subgoal_table", "goal_pose_topic")
"""meta_controller's Nav2 adapter parameters (``hdrqn_ros.nodes.nav.META_PARAMETERS``)."""
SUB_NAV_ARGS = ("action_table", "cmd_vel_topic", "costmap_topic")
"""sub_controller's Nav2 adapter parameters (``hdrqn_ros.nodes.nav.SUB_PARAMETERS``), besides
``observation_source``, which is always passed."""
OBSERVATION_SOURCES = ("topic", "costmap")


def _nodes(context):
    params_file = arg(context, "params_file")
    file_shared = shared_file_parameters(params_file)
    shared = {name: arg(context, name) for name in SHARED_ARGS if arg(context, name)}
    algo = shared.get("algo") or str(file_shared.get("algo", DEFAULT_ALGO))
    if algo not in ALGOS:
        raise RuntimeError(f"unknown algo {algo!r}; choose one of {', '.join(ALGOS)}")
    checkpoint, policy = arg(context, "checkpoint"), arg(context, "policy")
    if bool(checkpoint) == bool(policy):
        raise RuntimeError("give exactly one of the launch arguments checkpoint (e.g. "
                           "checkpoint:=runs/x/checkpoints/last.pt) and policy (an exported policy directory, e.g. "
                           f"policy:=runs/x/policy); got {'both' if checkpoint else 'neither'}")
    epsilon = float_arg(context, "epsilon")
    if not 0.0 <= epsilon <= 1.0:
        raise RuntimeError(f"launch argument epsilon must be in [0, 1], got {epsilon}")
    observation_source = arg(context, "observation_source")
    if observation_source not in OBSERVATION_SOURCES:
        raise RuntimeError(f"launch argument observation_source must be one of {OBSERVATION_SOURCES}, "
                           f"got {observation_source!r}")
    with_environment = bool_arg(context, "with_environment")
    ns = arg(context, "namespace") or "/"
    hierarchical = algo in HIERARCHICAL_ALGOS

    acting = {**shared, "checkpoint": checkpoint, "policy": policy, "epsilon": epsilon}
    meta_params = {**acting, **{name: arg(context, name) for name in META_NAV_ARGS if arg(context, name)}}
    sub_params = {**acting, "observation_source": observation_source,
                  **{name: arg(context, name) for name in SUB_NAV_ARGS if arg(context, name)}}

    source = f"checkpoint {checkpoint}" if checkpoint else f"exported policy {policy} (onnxruntime)"
    actions = [LogInfo(msg=f"hdrqn_ros policy: {algo} from {source} in {ns}, epsilon {epsilon}, "
                           f"environment {'on' if with_environment else 'off'}, params {params_file}")]
    if with_environment:
        environment = Node(package=PACKAGE, executable="environment", name="environment", namespace=ns,
                           parameters=[params_file, {**shared, "wait_for_learner": False}], output="screen")
        actions.append(environment)
        actions.append(RegisterEventHandler(OnProcessExit(
            target_action=environment,
            on_exit=[LogInfo(msg="the environment exited: shutting down"),
                     EmitEvent(event=Shutdown(reason="the environment exited"))])))
    if hierarchical:
        actions.append(Node(package=PACKAGE, executable="critic", name="critic", namespace=ns,
                            parameters=[params_file, shared], output="screen"))
        actions.append(Node(package=PACKAGE, executable="meta_controller", name="meta_controller", namespace=ns,
                            parameters=[params_file, meta_params], output="screen"))
    actions.append(Node(package=PACKAGE, executable="sub_controller", name="sub_controller", namespace=ns,
                        parameters=[params_file, sub_params], output="screen"))
    return actions


def generate_launch_description() -> LaunchDescription:
    default_params = str(share_dir() / "config" / "ros" / "run_policy.yaml")
    return LaunchDescription([
        DeclareLaunchArgument("checkpoint", default_value="",
                              description="trained weights: RUN_DIR/checkpoints/last.pt (this or policy)"),
        DeclareLaunchArgument("policy", default_value="",
                              description="exported policy directory (hdrqn export; the controllers act with "
                                          "onnxruntime, no torch; this or checkpoint)"),
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ROS 2 parameters file for all nodes (/** shared, then per node)"),
        DeclareLaunchArgument("algo", default_value="",
                              description=f"agent the checkpoint holds: {', '.join(ALGOS)} "
                                          f"(empty: params file, else {DEFAULT_ALGO})"),
        DeclareLaunchArgument("env", default_value="",
                              description="environment id the checkpoint was trained on (empty: params file)"),
        DeclareLaunchArgument("view", default_value="",
                              description="gridworld view the checkpoint was trained with (empty: params file)"),
        DeclareLaunchArgument("epsilon", default_value="0.0",
                              description="fixed exploration rate of both controllers (0.0: greedy)"),
        DeclareLaunchArgument("with_environment", default_value="true",
                              description="also start the simulator (environment node, wait_for_learner false)"),
        DeclareLaunchArgument("namespace", default_value="/",
                              description="namespace of the nodes (their relative topics resolve in it)"),
        DeclareLaunchArgument("subgoal_table", default_value="",
                              description="meta_controller: subgoal -> goal pose table YAML (Nav2; empty: params file)"),
        DeclareLaunchArgument("goal_pose_topic", default_value="",
                              description="meta_controller: where subgoal poses go (empty: params file)"),
        DeclareLaunchArgument("action_table", default_value="",
                              description="sub_controller: action -> velocity table YAML (Nav2; empty: params file)"),
        DeclareLaunchArgument("cmd_vel_topic", default_value="",
                              description="sub_controller: where velocity commands go (empty: params file)"),
        DeclareLaunchArgument("observation_source", default_value="topic",
                              description="sub_controller: 'topic' (the environment's observation) or 'costmap'"),
        DeclareLaunchArgument("costmap_topic", default_value="",
                              description="sub_controller: OccupancyGrid for observation_source costmap "
                                          "(empty: params file)"),
        OpaqueFunction(function=_nodes),
    ])
