"""``loopback_robot`` node: a kinematic robot on the gridworld / four-rooms map, for tests and demos.

In the spirit of Nav2's ``nav2_loopback_sim`` (which stands in for Gazebo in Nav2's own
tests): no physics, only kinematics (:class:`~hdrqn_ros.robot.loopback_world.LoopbackWorld`).
It integrates ``cmd_vel`` (Twist or TwistStamped; each command is held for
``cmd_vel_timeout`` simulated seconds, like Nav2's velocity smoother deadman; walls stop
the robot), drives to each ``goal_pose`` along a shortest free path at ``nav_speed`` (a
navigator stand-in, not Nav2's planners), and publishes what a Nav2 robot offers:
``odom`` (nav_msgs/Odometry), a rolling ``local_costmap/costmap`` and a
``global_costmap/costmap`` (OccupancyGrid with Nav2's cost values 0 / 100 / -1 and QoS:
reliable, transient local), and ``/clock``. Each episode's layout is the simulator's for
the same ``seed`` (fires left out); its places go out as a latched
``geometry_msgs/PoseArray`` on ``subgoal_poses``, and a new one is drawn when the
robot-side environment's ``env_step`` says the episode ended.

Simulated time runs ``real_time_factor`` times faster than the wall clock (0: as fast as it
can). With ``lockstep`` (``action`` or ``cmd_vel``) the clock stands at 0 until the
robot-side environment's first step, stops at each agent step until the agent answered
it, and at the next step's time until the robot-side environment published it (as PX4's lockstep simulation does), so a loaded machine never changes what
happens; a hold longer than ``lockstep_timeout`` wall seconds is logged and released.
It is not a robot simulator: no dynamics, no sensors, no localisation error, one frame.
"""
from __future__ import annotations

import math
import time

import numpy as np

from hdrqn_ros.envs.registration import GRID_IDS
from hdrqn_ros.middleware import LATCHED_QOS, Middleware, ParameterRule
from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.common import NodeConfigError, live_parameters, run_node
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import done
from hdrqn_ros.robot.loopback_world import LoopbackWorld
from hdrqn_ros.throttle import Throttle

PARAMETERS = {"env": "hdrqn/GridWorld-2Goals-v0", "seed": 0, "frame_id": "map", "tick": 0.1,
              "real_time_factor": 20.0, "holonomic": True, "cmd_vel_topic": "cmd_vel", "cmd_vel_stamped": False,
              "cmd_vel_timeout": 2.0, "goal_pose_topic": "goal_pose", "nav_speed": 0.25, "odom_topic": "odom",
              "costmap_topic": "local_costmap/costmap", "costmap_size": 3.0, "costmap_period": 0.5,
              "global_costmap_topic": "global_costmap/costmap", "subgoal_poses_topic": "subgoal_poses",
              "lockstep": "off", "step_period": 2.5, "lockstep_timeout": 10.0}
"""``tick``: simulated seconds per integration step; ``cmd_vel_timeout``: simulated seconds
a command is held; ``nav_speed``: m/s toward a goal pose; ``costmap_size``: side of the
rolling local costmap (m); ``costmap_period``: simulated seconds between local costmaps;
``lockstep``: ``off``, ``action`` (hold until the sub-controller's action for the step) or
``cmd_vel`` (until a velocity command after the step); ``step_period``: the robot-side
environment's step period (the time at which lockstep waits for its next step)."""
LOCKSTEP_MODES = ("off", "action", "cmd_vel")
RULES = {
    "env": ParameterRule("the map: a gridworld or four-rooms environment id"),
    "seed": ParameterRule("the layouts: the simulator's for this seed, without fire"),
    "frame_id": ParameterRule("the one frame of everything published"),
    "tick": ParameterRule("simulated seconds per integration step", positive=True),
    "real_time_factor": ParameterRule("simulated seconds per wall second (0: as fast as possible)", low=0.0, high=1e6),
    "holonomic": ParameterRule("false: differential drive (linear.y ignored)"),
    "cmd_vel_topic": ParameterRule("velocity commands in"),
    "cmd_vel_stamped": ParameterRule("commands are TwistStamped (else Twist)"),
    "cmd_vel_timeout": ParameterRule("simulated seconds a command is held, then the robot stops", live=True,
                                     positive=True),
    "goal_pose_topic": ParameterRule("goal poses the navigator stand-in drives to"),
    "nav_speed": ParameterRule("m/s toward a goal pose", live=True, positive=True),
    "odom_topic": ParameterRule("nav_msgs/Odometry out, every tick"),
    "costmap_topic": ParameterRule("the rolling local costmap out"),
    "costmap_size": ParameterRule("side of the local costmap (m)", live=True, positive=True),
    "costmap_period": ParameterRule("simulated seconds between local costmaps", live=True, positive=True),
    "global_costmap_topic": ParameterRule("the whole map out, once per layout"),
    "subgoal_poses_topic": ParameterRule("each episode's places out (latched PoseArray)"),
    "lockstep": ParameterRule("stop the clock at each agent step until it is answered", choices=LOCKSTEP_MODES),
    "step_period": ParameterRule("the robot environment's step period (when lockstep waits for its next step)",
                                 live=True, positive=True),
    "lockstep_timeout": ParameterRule("wall seconds a lockstep hold may last before it is released", live=True,
                                      positive=True),
}
"""Descriptions and rules of :data:`PARAMETERS`."""


class LoopbackRobotNode:
    def __init__(self, mw: Middleware):
        node = self.node = mw.create_node("loopback_robot")
        params = self.params = node.declare_parameters(PARAMETERS, rules=RULES)
        if params["env"] not in GRID_IDS:
            raise NodeConfigError(f"the loopback robot drives the gridworld maps: env must be one of "
                                  f"{sorted(GRID_IDS)}, got {params['env']!r}")
        for name in ("tick", "cmd_vel_timeout", "nav_speed", "costmap_size", "costmap_period", "step_period",
                     "lockstep_timeout"):
            if not (math.isfinite(params[name]) and params[name] > 0):
                raise NodeConfigError(f"{name} must be a positive number, got {params[name]!r}")
        if not (math.isfinite(params["real_time_factor"]) and params["real_time_factor"] >= 0):
            raise NodeConfigError(f"real_time_factor must be >= 0 (0: as fast as possible), "
                                  f"got {params['real_time_factor']!r}")
        if params["lockstep"] not in LOCKSTEP_MODES:
            raise NodeConfigError(f"lockstep must be one of {LOCKSTEP_MODES}, got {params['lockstep']!r}")
        grid = GRID_IDS[params["env"]]
        self.world = LoopbackWorld(grid["layout"], grid["n_goals"], params["seed"], nav_speed_m_s=params["nav_speed"],
                                   holonomic=params["holonomic"])
        self.tick_ns = int(round(params["tick"] * 1e9))
        live_parameters(node, params, RULES, self._apply)
        self.now_ns = 0
        self.next_costmap_ns = 0
        twist = nav.TWIST_STAMPED if params["cmd_vel_stamped"] else nav.TWIST
        node.create_subscription(twist, params["cmd_vel_topic"], self._on_cmd_vel)
        node.create_subscription(nav.POSE_STAMPED, params["goal_pose_topic"], self._on_goal_pose)
        node.create_subscription(wire.FLOATS, wire.ENV_STEP, self._on_env_step, wire.STEP_QOS)
        node.create_subscription(wire.INTS, wire.ACTION, self._on_action, wire.STEP_QOS)
        self.pub_clock = node.create_publisher(wire.CLOCK_TYPE, wire.CLOCK)
        self.pub_odom = node.create_publisher(nav.POSE_TYPES["odometry"], params["odom_topic"])
        self.pub_costmap = node.create_publisher(nav.OCCUPANCY_GRID, params["costmap_topic"], LATCHED_QOS)
        self.pub_global = node.create_publisher(nav.OCCUPANCY_GRID, params["global_costmap_topic"], LATCHED_QOS)
        self.pub_places = node.create_publisher(nav.POSE_ARRAY, params["subgoal_poses_topic"], LATCHED_QOS)
        self.rejected = Throttle(node.logger, "rejected a message")
        # lockstep: the latest agent step (its key, whether it ended the episode)
        self.step_key: int | None = None
        self.step_done = False
        self.action_key = self.answered_key = -1  # the latest action's key; the latest step answered
        self.moves = self.moves_used = 0  # non-zero commands received; those that answered steps
        self.held_since: float | None = None
        self.released_key: int | None = -1  # the step whose hold timed out (runs free until the next step;
        #                                     None: the wait for the first step)
        self._new_layout()
        period = params["tick"] / params["real_time_factor"] if params["real_time_factor"] > 0 else 0.001
        node.create_timer(period, self._tick)

    def _apply(self, name: str, value) -> None:
        """A live parameter changed (the others are read at their next use)."""
        if name == "nav_speed":
            self.world.nav_speed = float(value)

    # -- inputs ------------------------------------------------------------------------------------
    def _on_cmd_vel(self, msg) -> None:
        twist = msg.twist if self.params["cmd_vel_stamped"] else msg
        values = (twist.linear.x, twist.linear.y, twist.angular.z)
        if not all(math.isfinite(v) for v in values):
            return self.rejected.warn(f"cmd_vel is not finite: {values}")
        if any(values):
            self.world.command(*values, self.params["cmd_vel_timeout"])
            self.moves += 1
        else:
            self.world.stop()

    def _on_goal_pose(self, msg) -> None:
        if msg.header.frame_id != self.params["frame_id"]:
            return self.rejected.warn(f"goal_pose in frame {msg.header.frame_id!r}, the map is "
                                      f"{self.params['frame_id']!r}")
        try:
            self.world.navigate_to(msg.pose.position.x, msg.pose.position.y)
        except ValueError as exc:
            self.rejected.warn(f"goal_pose: {exc}")

    def _on_env_step(self, msg) -> None:
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

    def _on_action(self, msg) -> None:
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
        return ""

    def _answered(self) -> bool:
        """The agent answered the latest step: its action came (the key says which step), and
        with lockstep ``cmd_vel`` a new velocity command too (which carries no key, and may
        arrive before the step itself: counted). Once true for a step, it stays true."""
        if self.answered_key == self.step_key:
            return True
        if self.action_key < self.step_key or (self.params["lockstep"] == "cmd_vel" and self.moves <= self.moves_used):
            return False
        self.answered_key, self.moves_used = self.step_key, self.moves
        return True

    def _tick(self) -> None:
        if waiting := self._holding():
            now = time.monotonic()
            if self.held_since is None:
                self.held_since = now
            elif now - self.held_since > self.params["lockstep_timeout"]:
                self.node.logger.warning("lockstep: waited %.1f s for %s; the clock runs free until the next step",
                                         now - self.held_since, waiting)
                self.released_key, self.held_since = self.step_key, None
            return
        self.world.advance(self.params["tick"])
        self.now_ns += self.tick_ns
        self._publish_state()

    def _new_layout(self) -> None:
        self.world.new_episode()
        self.next_costmap_ns = self.now_ns  # a costmap of the new place now
        self._publish_state()
        self.pub_global.publish(self._costmap_msg(self.world.global_costmap()))
        stamp = wire.make_header(self.node, self.now_ns, self.params["frame_id"])
        self.pub_places.publish(self.node.msg(nav.POSE_ARRAY)(header=stamp, poses=[
            self._pose(x, y, 0.0) for x, y in self.world.layout.goal_xy]))

    def _publish_state(self) -> None:
        node, now = self.node, self.now_ns
        self.pub_clock.publish(node.msg(wire.CLOCK_TYPE)(clock=wire.make_time(node, now)))
        x, y, yaw = self.world.pose
        vx, vy, wz = self.world.velocity
        v3 = node.msg("geometry_msgs/msg/Vector3")
        twist = node.msg("geometry_msgs/msg/Twist")(linear=v3(x=vx, y=vy, z=0.0), angular=v3(x=0.0, y=0.0, z=wz))
        odom = node.msg(nav.POSE_TYPES["odometry"])(
            header=wire.make_header(node, now, self.params["frame_id"]), child_frame_id="base_link",
            pose=node.msg("geometry_msgs/msg/PoseWithCovariance")(pose=self._pose(x, y, yaw)),
            twist=node.msg("geometry_msgs/msg/TwistWithCovariance")(twist=twist))
        self.pub_odom.publish(odom)
        if now >= self.next_costmap_ns:
            self.next_costmap_ns = now + int(round(self.params["costmap_period"] * 1e9))
            self.pub_costmap.publish(self._costmap_msg(self.world.local_costmap(self.params["costmap_size"])))

    def _pose(self, x: float, y: float, yaw: float):
        msg = self.node.msg
        return msg("geometry_msgs/msg/Pose")(
            position=msg("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0),
            orientation=msg("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))

    def _costmap_msg(self, costmap):
        node = self.node
        info = node.msg("nav_msgs/msg/MapMetaData")(
            map_load_time=wire.make_time(node, self.now_ns), resolution=float(costmap.resolution_m),
            width=int(costmap.width), height=int(costmap.height),
            origin=self._pose(costmap.origin_xy[0], costmap.origin_xy[1], 0.0))
        return node.msg(nav.OCCUPANCY_GRID)(header=wire.make_header(node, self.now_ns, self.params["frame_id"]),
                                            info=info, data=node.pack(np.ascontiguousarray(costmap.data, np.int8)
                                                                      .reshape(-1)))


def main(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: LoopbackRobotNode(mw), argv)


if __name__ == "__main__":
    raise SystemExit(main())
