"""A trained agent on the loopback robot: ``ros2 launch hdrqn_ros robot.launch.py checkpoint:=...``
(torch) or ``policy:=...`` (an exported ONNX policy).

Starts ``loopback_robot`` (a kinematic robot on the gridworld map publishing ``/clock``,
tf ``map -> odom -> base_link``, ``odom``, a rolling ``local_costmap/costmap`` in ``odom``
and its updates, ``global_costmap/costmap``, each episode's places on ``subgoal_poses``, and
serving ``navigate_to_pose``), ``robot_environment`` (the environment node's place on a
robot), ``critic``, ``meta_controller`` and ``sub_controller``, all on simulated time, with
the parameters ``hdrqn_ros.robot_graph.robot_parameters`` gives (the same as ``hdrqn
robot``). ``mode:=sub-drives`` (default): each action is a motion primitive streamed on
``cmd_vel``; ``mode:=meta-only``: the meta-controller sends one ``navigate_to_pose`` goal
per option and the robot drives there. The launch shuts down when
``robot_environment`` has run ``episodes`` episodes::

    ros2 launch hdrqn_ros robot.launch.py checkpoint:=runs/x/checkpoints/last.pt
    ros2 launch hdrqn_ros robot.launch.py policy:=runs/x/policy mode:=meta-only episodes:=20

``algo``, ``env`` and ``view`` must be those the agent was trained with (defaults: the
quick-start agent's, hdrqn-v2 on hdrqn/GridWorld-2Goals-v0 with a 5x5 view).
"""
from __future__ import annotations

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, LogInfo, OpaqueFunction, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch_ros.actions import Node

from hdrqn_ros.launch_support import DEFAULT_ALGO, HIERARCHICAL_ALGOS, PACKAGE, arg, float_arg, int_arg, share_dir
from hdrqn_ros.robot_graph import MODES, RobotRun, robot_parameters


def _nodes(context):
    mode = arg(context, "mode")
    if mode not in MODES:
        raise RuntimeError(f"launch argument mode must be one of {MODES}, got {mode!r}")
    checkpoint, policy = arg(context, "checkpoint"), arg(context, "policy")
    if bool(checkpoint) == bool(policy):
        raise RuntimeError("give exactly one of the launch arguments checkpoint and policy; got "
                           f"{'both' if checkpoint else 'neither'}")
    run = RobotRun(algo=arg(context, "algo"), env=arg(context, "env"), view=arg(context, "view"),
                   checkpoint=checkpoint, policy=policy, mode=mode, episodes=int_arg(context, "episodes", 1),
                   seed=int_arg(context, "seed", 0), real_time_factor=float_arg(context, "real_time_factor"),
                   action_table=str(share_dir() / "config" / "nav2" / "actions_holonomic.yaml"))
    params = robot_parameters(run)
    shared = params.pop("/**")

    def parameters(name: str) -> list[dict]:
        return [{**shared, **params[name]}]

    robot_environment = Node(package=PACKAGE, executable="robot_environment", name="robot_environment",
                             parameters=parameters("robot_environment"), output="screen")
    actions = [LogInfo(msg=f"hdrqn_ros robot: {run.algo} from {checkpoint or policy}, {mode}, {run.episodes} episodes"),
               Node(package=PACKAGE, executable="loopback_robot", name="loopback_robot",
                    parameters=parameters("loopback_robot"), output="screen"),
               robot_environment,
               RegisterEventHandler(OnProcessExit(
                   target_action=robot_environment,
                   on_exit=[LogInfo(msg="the robot environment finished: shutting down"),
                            EmitEvent(event=Shutdown(reason="robot_environment finished"))]))]
    if run.algo in HIERARCHICAL_ALGOS:
        actions.append(Node(package=PACKAGE, executable="critic", name="critic", parameters=parameters("critic"),
                            output="screen"))
        actions.append(Node(package=PACKAGE, executable="meta_controller", name="meta_controller",
                            parameters=parameters("meta_controller"), output="screen"))
    actions.append(Node(package=PACKAGE, executable="sub_controller", name="sub_controller",
                        parameters=parameters("sub_controller"), output="screen"))
    return actions


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription([
        DeclareLaunchArgument("checkpoint", default_value="", description="trained weights (this or policy)"),
        DeclareLaunchArgument("policy", default_value="", description="exported policy directory (this or checkpoint)"),
        DeclareLaunchArgument("mode", default_value="sub-drives", description=f"one of {MODES}"),
        DeclareLaunchArgument("episodes", default_value="10", description="episodes before shutting down"),
        DeclareLaunchArgument("seed", default_value="0", description="layouts: the simulator's for this seed"),
        DeclareLaunchArgument("real_time_factor", default_value="20.0",
                              description="simulated seconds per wall second (0: as fast as possible)"),
        DeclareLaunchArgument("algo", default_value=DEFAULT_ALGO, description="the agent's algorithm"),
        DeclareLaunchArgument("env", default_value="hdrqn/GridWorld-2Goals-v0", description="the agent's domain"),
        DeclareLaunchArgument("view", default_value="5", description="the agent's view (cells)"),
        OpaqueFunction(function=_nodes),
    ])
