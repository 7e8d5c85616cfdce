"""``loopback_robot`` node: a kinematic robot on the gridworld / four-rooms map that speaks as a Nav2 robot.

In the spirit of Nav2's ``nav2_loopback_sim`` (which stands in for Gazebo in Nav2's own
tests): no physics, only kinematics (:class:`~hdrqn_ros.robot.loopback_world.LoopbackWorld`,
holonomic or differential drive, starting each episode facing ``start_yaw``). It integrates
``cmd_vel`` (Twist or TwistStamped; a command older than ``cmd_vel_timeout`` simulated
seconds stops the robot, like the velocity smoother's ``velocity_timeout`` deadman; walls
stop it), drives to each ``goal_pose`` along a shortest free path at ``nav_speed`` (a
navigator stand-in, not Nav2's planners), and publishes what a Nav2 robot offers, on
simulated time (``/clock``):

* tf (``tf2_msgs/TFMessage`` on ``/tf``): ``map_frame -> odom_frame`` (AMCL's part: starts at
  ``map_to_odom``, drifts by ``odom_error`` while the robot moves) and ``odom_frame ->
  base_frame`` (odometry's part); composed, always the robot's true pose. With
  ``odom_frame`` equal to ``map_frame`` there is no odometry frame: ``map -> base_link``.
* ``odom`` (nav_msgs/Odometry, ``odom_frame``, child ``base_frame``), every tick;
* ``amcl_pose`` (PoseWithCovarianceStamped in ``map_frame``, reliable, transient local,
  depth 1), only as AMCL publishes it: at each episode's start (an initial pose) and when
  odometry moved more than ``amcl_update_min_d`` or turned more than ``amcl_update_min_a``;
* a rolling ``local_costmap/costmap`` in ``odom_frame`` and the whole map as
  ``global_costmap/costmap`` in ``map_frame`` (OccupancyGrid: Nav2's cost values, with
  inflation costs around the walls when ``inflation_radius`` > 0, and QoS: reliable,
  transient local); with ``always_send_full_costmap`` false, a full local grid only when
  its window moved, else ``map_msgs/OccupancyGridUpdate`` on ``<costmap>_updates``, as Nav2.

Each episode's layout is the simulator's for the same ``seed`` (fires left out); its places
go out as a latched ``geometry_msgs/PoseArray`` in ``map_frame`` on ``subgoal_poses``, and
a new one is drawn when the robot-side environment's ``env_step`` says the episode ended.

Simulated time runs ``real_time_factor`` times faster than the wall clock (0: as fast as it
can); the node keeps it itself and paces it on the wall clock, with or without
``use_sim_time``. With ``lockstep`` (``action`` or ``cmd_vel``) the clock stands at 0 until
the robot-side environment's first step, stops at each agent step until the agent answered
it, and at the next step's time until the robot-side environment published it (as PX4's
lockstep simulation does), so a loaded machine never changes what happens; with ``control``
also, while the robot drives on a velocity command, at each tick until the next command
came (a controller closing its loop on the simulated clock: motion primitives); a hold longer
than ``lockstep_timeout`` wall seconds is logged and released. It is not a robot
simulator: no dynamics, no sensors, no localisation error.
"""
from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import (Point, Pose, PoseArray, PoseStamped, PoseWithCovariance, PoseWithCovarianceStamped,
                               Quaternion, Transform, TransformStamped, Twist, TwistStamped, TwistWithCovariance,
                               Vector3)
from nav_msgs.msg import MapMetaData, OccupancyGrid, Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.time import Time
from rosgraph_msgs.msg import Clock as ClockMsg
from std_msgs.msg import Float64MultiArray, Header, Int64MultiArray

from hdrqn_ros.envs.registration import GRID_IDS
from hdrqn_ros.nodes.graph_parameters import MAX_MESSAGE_BYTES
from hdrqn_ros.nodes.loopback_navigator import LoopbackNavigator
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import NodeConfigError, Param, declare_parameters
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS, STEP_QOS, keep_last
from hdrqn_ros.nodes.ros_messages import bounded_subscription, interface_class, pack
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import done
from hdrqn_ros.robot.loopback_world import AmclUpdates, Costmap, LoopbackWorld
from hdrqn_ros.throttle import Throttle

LOCKSTEP_MODES = ("off", "action", "cmd_vel", "control")
"""``off``; hold the clock until the sub-controller's ``action`` for the step; or until a
velocity command after the step (``cmd_vel``); and, while the robot drives, each tick until a
velocity command after the previous one (``control``: a controller closing its loop on the
simulated clock, as motion primitives do)."""
DRIVES = ("holonomic", "diff")
TF_QOS = keep_last(100)
"""``/tf`` as tf2_ros's broadcaster offers it: reliable, volatile, keep-last 100."""
AMCL_COVARIANCE = [0.0025 if i in (0, 7) else 0.0007 if i == 35 else 0.0 for i in range(36)]
"""``/amcl_pose``'s covariance: 5 cm in x and y, 1.5 degrees in yaw (a localised robot)."""


def _triple(value) -> str | None:
    ok = len(value) == 3 and all(math.isfinite(v) for v in value)
    return None if ok else f"must be [x, y, yaw] (m, m, rad), got {list(value)!r}"


def _pair(value) -> str | None:
    if len(value) != 2:
        return f"must be [distance, rotation], got {list(value)!r}"
    return None if all(-1 < v < 1 for v in value) else f"must be relative errors in (-1, 1), got {list(value)!r}"


PARAMETERS = {
    "env": Param("hdrqn/GridWorld-2Goals-v0", "the map: a gridworld or four-rooms environment id",
                 choices=tuple(sorted(GRID_IDS))),
    "seed": Param(0, "the layouts: the simulator's for this seed, without fire", low=0, high=2**63 - 1),
    "map_frame": Param("map", "the global frame: places, poses, global costmap, amcl_pose"),
    "odom_frame": Param("map", "odometry's frame (odom, local costmap; Nav2: odom); map_frame: none, odometry in "
                               "the map"),
    "base_frame": Param("base_link", "the robot's frame (odom's child_frame_id, tf's last link)"),
    "map_to_odom": Param([0.0, 0.0, 0.0], "map -> odom at the start, [x, y, yaw] (m, m, rad)", check=_triple),
    "odom_error": Param([0.0, 0.0], "odometry's relative error [distance, rotation]: map -> odom drifts while the "
                                    "robot moves", check=_pair),
    "publish_tf": Param(True, "publish tf on /tf (tf2_msgs/TFMessage)"),
    "tick": Param(0.1, "simulated seconds per integration step", positive=True),
    "real_time_factor": Param(20.0, "simulated seconds per wall second (0: as fast as possible)", low=0.0, high=1e6),
    "drive": Param("holonomic", "holonomic, or differential drive (diff: linear.y ignored)", choices=DRIVES),
    "start_yaw": Param(0.0, "the robot's yaw at each episode's start (rad, map frame)", low=-math.pi, high=math.pi),
    "cmd_vel_topic": Param("cmd_vel", "velocity commands in"),
    "cmd_vel_stamped": Param(False, "commands are TwistStamped (else Twist)"),
    "cmd_vel_timeout": Param(2.0, "deadman: simulated seconds after its last command the robot stops (Nav2's "
                                  "velocity smoother: 1.0)", live=True, positive=True),
    "goal_pose_topic": Param("goal_pose", "goal poses the navigator stand-in drives to"),
    "nav_speed": Param(0.25, "m/s toward a goal pose", live=True, positive=True),
    "odom_topic": Param("odom", "nav_msgs/Odometry out, every tick"),
    "amcl_pose_topic": Param("amcl_pose", "the AMCL-like pose out, only after motion ('': none)"),
    "amcl_update_min_d": Param(0.25, "m of odometry along x or y before the next amcl_pose (AMCL's update_min_d)",
                               low=0.0, high=100.0),
    "amcl_update_min_a": Param(0.2, "rad of odometry turn before the next amcl_pose (AMCL's update_min_a)",
                               low=0.0, high=2 * math.pi),
    "costmap_topic": Param("local_costmap/costmap", "the rolling local costmap out"),
    "costmap_size": Param(3.0, "side of the local costmap (m)", live=True, positive=True),
    "costmap_period": Param(0.5, "simulated seconds between local costmaps", live=True, positive=True),
    "always_send_full_costmap": Param(True, "false: a full local grid only when the window moved, else "
                                            "<costmap_topic>_updates (Nav2's setting)"),
    "inflation_radius": Param(0.0, "m of inflation costs around walls in the costmaps (0: none; Nav2: 0.7)",
                              low=0.0, high=10.0),
    "cost_scaling_factor": Param(3.0, "the inflation costs' decay (1/m; Nav2's default 3.0)", low=0.0, high=100.0),
    "global_costmap_topic": Param("global_costmap/costmap", "the whole map out, once per layout"),
    "subgoal_poses_topic": Param("subgoal_poses", "each episode's places out (latched PoseArray)"),
    "lockstep": Param("off", "stop the clock at each agent step until it is answered (control: also at each tick "
                             "while driving, until the next velocity command)", choices=LOCKSTEP_MODES),
    "step_period": Param(2.5, "the robot environment's step period (when lockstep waits for its next step)",
                         live=True, positive=True),
    "lockstep_timeout": Param(10.0, "wall seconds a lockstep hold may last before it is released", live=True,
                              positive=True),
    **MAX_MESSAGE_BYTES,
}
"""The loopback robot's parameters; the live ones take effect at their next use."""
RESEND_S = 1.0
"""Wall seconds between the state's (``/clock``, odometry) repetitions while lockstep holds the clock."""


def _pose(x: float, y: float, yaw: float = 0.0) -> Pose:
    return Pose(position=Point(x=float(x), y=float(y)), orientation=_quaternion(yaw))


def _quaternion(yaw: float) -> Quaternion:
    return Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2))


class LoopbackRobotNode(Node):
    """The simulated robot and its clock."""

    def __init__(self, **kwargs):
        super().__init__("loopback_robot", **kwargs)
        params = self.params = declare_parameters(self, PARAMETERS, apply=self._apply)
        self.has_odom_frame = params["odom_frame"] != params["map_frame"]
        if not self.has_odom_frame and (any(params["map_to_odom"]) or any(params["odom_error"])):
            raise NodeConfigError(f"map_to_odom and odom_error need an odometry frame: set odom_frame (e.g. odom) "
                                  f"to other than map_frame {params['map_frame']!r}")
        if params["base_frame"] in (params["map_frame"], params["odom_frame"]):
            raise NodeConfigError(f"base_frame {params['base_frame']!r} must differ from map_frame and odom_frame")
        grid = GRID_IDS[params["env"]]
        self.world = LoopbackWorld(grid["layout"], grid["n_goals"], params["seed"], nav_speed_m_s=params["nav_speed"],
                                   holonomic=params["drive"] == "holonomic", start_yaw=params["start_yaw"],
                                   map_to_odom=tuple(params["map_to_odom"]), odom_error=tuple(params["odom_error"]),
                                   inflation_radius_m=params["inflation_radius"],
                                   cost_scaling_factor=params["cost_scaling_factor"])
        self.amcl = AmclUpdates(params["amcl_update_min_d"], params["amcl_update_min_a"])
        self.tick_ns = int(round(params["tick"] * 1e9))
        self.now_ns = self.next_costmap_ns = 0  # simulated time (ns), when the next local costmap is due
        self.rejected = Throttle(python_logger(self), "rejected a message")
        # lockstep: the latest agent step (its key, whether it ended the episode)
        self.step_key: int | None = None
        self.step_done = False
        self.action_key = self.answered_key = -1  # the latest action's key; the latest step answered
        self.moves = self.moves_used = 0  # non-zero commands received; those that answered steps
        self.commanded = self.driving = False  # lockstep control: a command since the last tick; the last moved
        self.held_since: float | None = None  # wall time the current hold began
        self.sent_at = 0.0  # wall time the state last went out during a hold
        self.released_key: int | None = -1  # the step whose hold timed out (runs free until the next step;
        #                                     None: the wait for the first step)
        self.grid_window: tuple | None = None  # the last full local grid's (origin, size): updates go on top
        self._subscribe()
        self.pub_clock = self.create_publisher(ClockMsg, wire.CLOCK, DEFAULT_QOS)
        self.pub_odom = self.create_publisher(Odometry, params["odom_topic"], DEFAULT_QOS)
        self.pub_tf = self.create_publisher(interface_class("tf2_msgs/msg/TFMessage"), "/tf", TF_QOS) \
            if params["publish_tf"] else None
        self.pub_amcl = self.create_publisher(PoseWithCovarianceStamped, params["amcl_pose_topic"], LATCHED_QOS) \
            if params["amcl_pose_topic"] else None
        self.pub_costmap = self.create_publisher(OccupancyGrid, params["costmap_topic"], LATCHED_QOS)
        self.pub_updates = None if params["always_send_full_costmap"] else self.create_publisher(
            interface_class("map_msgs/msg/OccupancyGridUpdate"), params["costmap_topic"] + "_updates", LATCHED_QOS)
        self.pub_global = self.create_publisher(OccupancyGrid, params["global_costmap_topic"], LATCHED_QOS)
        self.pub_places = self.create_publisher(PoseArray, params["subgoal_poses_topic"], LATCHED_QOS)
        self._new_layout()
        # the navigate_to_pose action server, driving the robot before each tick (loopback_navigator)
        self.navigator = LoopbackNavigator(self, self.world, params["map_frame"], params["tick"])
        period = params["tick"] / params["real_time_factor"] if params["real_time_factor"] > 0 else 0.001
        self.create_timer(period, self._tick, clock=Clock(clock_type=ClockType.STEADY_TIME))  # paces simulated time

    def _subscribe(self) -> None:
        params, logger = self.params, self.rejected.logger

        def subscribe(msg_type, topic: str, callback, qos) -> None:
            bounded_subscription(self, msg_type, topic, callback, qos, params["max_message_bytes"], logger)

        subscribe(TwistStamped if params["cmd_vel_stamped"] else Twist, params["cmd_vel_topic"], self._on_cmd_vel,
                  DEFAULT_QOS)
        subscribe(PoseStamped, params["goal_pose_topic"], self._on_goal_pose, DEFAULT_QOS)
        subscribe(Float64MultiArray, wire.ENV_STEP, self._on_env_step, STEP_QOS)
        subscribe(Int64MultiArray, wire.ACTION, self._on_action, STEP_QOS)

    def _apply(self, name: str, value) -> None:
        """A live parameter changed (read at its next use)."""
        self.params[name] = value
        if name == "nav_speed":
            self.world.nav_speed = float(value)

    # -- inputs ------------------------------------------------------------------------------------
    def _on_cmd_vel(self, msg: Twist | TwistStamped) -> None:
        twist = msg.twist if self.params["cmd_vel_stamped"] else msg
        values = (twist.linear.x, twist.linear.y, twist.angular.z)
        if not all(math.isfinite(v) for v in values):
            return self.rejected.warn(f"cmd_vel is not finite: {values}")
        self.commanded, self.driving = True, any(values)  # lockstep control
        if any(values):
            self.world.command(*values, self.params["cmd_vel_timeout"])
            self.moves += 1
        else:
            self.world.stop()

    def _on_goal_pose(self, msg: PoseStamped) -> None:
        if msg.header.frame_id != self.params["map_frame"]:
            return self.rejected.warn(f"goal_pose in frame {msg.header.frame_id!r}, the map is "
                                      f"{self.params['map_frame']!r}")
        try:
            self.world.navigate_to(msg.pose.position.x, msg.pose.position.y)
        except ValueError as exc:
            self.rejected.warn(f"goal_pose: {exc}")

    def _on_env_step(self, msg: Float64MultiArray) -> None:
        try:
            row = wire.read_steps(msg)[0]
        except wire.ProtocolError as exc:
            return self.rejected.warn(f"env_step: {exc}")
        key = int(row["key"])
        if self.step_key is not None and key <= self.step_key:
            return  # a re-published step
        self.step_key, self.step_done, self.held_since = key, done(row), None
        if self.step_done:
            self._new_layout()

    def _on_action(self, msg: Int64MultiArray) -> None:
        try:
            key, _ = wire.read_actions(msg, 1 << 30, 1)
        except wire.ProtocolError:
            return
        self.action_key = max(self.action_key, key)

    # -- simulation ----------------------------------------------------------------------------------
    def _holding(self) -> str:
        """What the lockstep clock waits for ('' when it may run)."""
        if self.params["lockstep"] == "off" or self.released_key == self.step_key:
            return ""
        if self.step_key is None:  # the first step comes at time 0: every agent step gets its whole period
            return "the robot environment's first step"
        if not self.step_done and not self._answered():
            return f"the agent's {self.params['lockstep']} for step key {self.step_key}"
        if self.step_done or self.now_ns >= self.step_key + self.params["step_period"] * 1e9:
            return f"the robot environment's step after key {self.step_key}"
        if self.params["lockstep"] == "control" and self.driving and self.world.moving and not self.commanded:
            return "the controller's velocity command for this tick"  # lockstep control
        return ""

    def _answered(self) -> bool:
        """The agent answered the latest step: its action came (the key says which step), and
        with lockstep ``cmd_vel`` a new velocity command too (which carries no key, and may
        arrive before the step itself: counted). Once true for a step, it stays true."""
        if self.answered_key == self.step_key:
            return True
        waiting = self.moves <= self.moves_used if self.params["lockstep"] == "cmd_vel" else \
            self.params["lockstep"] == "control" and not self.driving  # lockstep control: the primitive's first command
        if self.action_key < self.step_key or waiting:
            return False
        self.answered_key, self.moves_used = self.step_key, self.moves
        return True

    def _tick(self) -> None:
        """One integration step of simulated time, unless lockstep holds the clock."""
        if waiting := self._holding():
            return self._hold(waiting)
        self.held_since = None
        self.navigator.control(self.now_ns)  # the navigate_to_pose goal's velocity for this tick
        self.world.advance(self.params["tick"])
        self.now_ns += self.tick_ns
        self.commanded = False
        self._publish_state()
        if self.amcl.due(self.world.odom_pose):
            self._publish_amcl()

    def _hold(self, waiting: str) -> None:
        """Keep the clock still, sending the state again every :data:`RESEND_S` (a node that joins
        during a hold learns where the robot is), until ``lockstep_timeout`` releases the hold."""
        now = time.monotonic()
        if self.held_since is None:
            self.held_since = self.sent_at = now
        elif now - self.held_since > self.params["lockstep_timeout"]:
            self.get_logger().warning(f"lockstep: waited {now - self.held_since:.1f} s for {waiting}; the clock "
                                      f"runs free until the next step")
            self.released_key, self.held_since = self.step_key, None
        elif now - self.sent_at >= RESEND_S:
            self.sent_at = now
            self._publish_state()

    # -- outputs -------------------------------------------------------------------------------------
    def _header(self, frame: str) -> Header:
        return Header(stamp=Time(nanoseconds=self.now_ns).to_msg(), frame_id=frame)

    def _new_layout(self) -> None:
        """The next episode's layout: the robot at its start (an initial pose: ``amcl_pose``),
        the whole map and the places out."""
        params = self.params
        self.world.new_episode()
        self.next_costmap_ns = self.now_ns  # a costmap of the new place now
        self._publish_state()
        self.amcl.initial_pose(self.world.odom_pose)
        self._publish_amcl()
        self.pub_global.publish(self._costmap_msg(self.world.global_costmap(), params["map_frame"]))
        self.pub_places.publish(PoseArray(header=self._header(params["map_frame"]), poses=[
            _pose(x, y) for x, y in self.world.layout.goal_xy]))

    def _publish_state(self) -> None:
        """``/clock``, tf, the odometry, and the local costmap when one is due."""
        params = self.params
        self.pub_clock.publish(ClockMsg(clock=Time(nanoseconds=self.now_ns).to_msg()))
        odom = self.world.odom_pose if self.has_odom_frame else self.world.pose
        if self.pub_tf is not None:
            links = [(params["map_frame"], params["odom_frame"], self.world.map_to_odom)] if self.has_odom_frame else []
            links.append((params["odom_frame"], params["base_frame"], odom))
            self.pub_tf.publish(self.pub_tf.msg_type(transforms=[TransformStamped(
                header=self._header(parent), child_frame_id=child,
                transform=Transform(translation=Vector3(x=float(x), y=float(y)), rotation=_quaternion(yaw)))
                for parent, child, (x, y, yaw) in links]))
        vx, vy, wz = self.world.velocity
        twist = Twist(linear=Vector3(x=float(vx), y=float(vy)), angular=Vector3(z=float(wz)))
        self.pub_odom.publish(Odometry(header=self._header(params["odom_frame"]), child_frame_id=params["base_frame"],
                                       pose=PoseWithCovariance(pose=_pose(*odom)),
                                       twist=TwistWithCovariance(twist=twist)))
        if self.now_ns >= self.next_costmap_ns:
            self.next_costmap_ns = self.now_ns + int(round(params["costmap_period"] * 1e9))
            self._publish_local_costmap()

    def _publish_local_costmap(self) -> None:
        """The rolling window in the odometry frame: a full grid, or (updates only, the window
        where it was) an update of the whole window."""
        costmap = self.world.local_costmap(self.params["costmap_size"], in_odom=self.has_odom_frame)
        window = (costmap.origin_xy, costmap.width, costmap.height)
        frame = self.params["odom_frame"]
        if self.pub_updates is None or window != self.grid_window:
            self.grid_window = window
            return self.pub_costmap.publish(self._costmap_msg(costmap, frame))
        self.pub_updates.publish(self.pub_updates.msg_type(
            header=self._header(frame), x=0, y=0, width=costmap.width, height=costmap.height,
            data=pack(np.asarray(costmap.data, np.int8).reshape(-1))))

    def _publish_amcl(self) -> None:
        if self.pub_amcl is not None:
            self.pub_amcl.publish(PoseWithCovarianceStamped(
                header=self._header(self.params["map_frame"]),
                pose=PoseWithCovariance(pose=_pose(*self.world.pose), covariance=AMCL_COVARIANCE)))

    def _costmap_msg(self, costmap: Costmap, frame: str) -> OccupancyGrid:
        info = MapMetaData(map_load_time=Time(nanoseconds=self.now_ns).to_msg(),
                           resolution=float(costmap.resolution_m), width=int(costmap.width),
                           height=int(costmap.height), origin=_pose(*costmap.origin_xy))
        return OccupancyGrid(header=self._header(frame), info=info,
                             data=pack(np.asarray(costmap.data, np.int8).reshape(-1)))


def main(argv: list[str] | None = None) -> int:
    return run_node(LoopbackRobotNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
