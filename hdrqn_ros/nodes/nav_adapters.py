"""The Nav2 adapters the controllers hand their decisions to: the sub-controller's actions as
velocity commands (``cmd_vel``), the meta-controller's subgoals as goal poses (``goal_pose``;
as ``navigate_to_pose`` goals: :mod:`hdrqn_ros.nodes.navigate_goals`). The tables are
:mod:`hdrqn_ros.nodes.nav`'s; see ``docs/nav2.md``."""
from __future__ import annotations

import time

from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.duration import Duration

from hdrqn_ros.nodes.controller_node import ControllerNode
from hdrqn_ros.nodes.nav import ActionTable, SubgoalTable
from hdrqn_ros.nodes.parameters import Param
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS
from hdrqn_ros.nodes.ros_messages import bounded_subscription

SUBGOAL_TABLE = {"subgoal_table": Param("", "YAML table of the places, subgoal index -> pose ('': off)")}
VELOCITY_PARAMETERS = {
    "action_table": Param("", "YAML table, action index -> velocity command ('': drive nothing)"),
    "cmd_vel_topic": Param("cmd_vel", "where velocity commands go"),
    "stale_after_s": Param(5.0, "wall seconds without an observation after which the robot is stopped (zero "
                                "command)", live=True, positive=True),
}
"""The sub-controller's driving parameters (:class:`VelocityDriver`); ``stale_after_s`` is live."""
GOAL_PARAMETERS = {
    **SUBGOAL_TABLE,
    "subgoal_poses_topic": Param("", "instead of subgoal_table: a latched geometry_msgs/PoseArray of the places"),
    "navigation": Param("action", "how each new option's place goes to the navigator: a navigate_to_pose goal whose "
                                  "result ends the option (action), or a goal_pose message (topic)",
                        choices=("action", "topic")),
    "navigate_action": Param("navigate_to_pose", "navigation action: the nav2_msgs/NavigateToPose action (Nav2's "
                                                 "bt_navigator serves it)"),
    "goal_pose_topic": Param("goal_pose", "navigation topic: where each new option's place goes "
                                          "(geometry_msgs/PoseStamped)"),
}
"""The meta-controller's navigation parameters (:class:`GoalPoses`,
:class:`~hdrqn_ros.nodes.navigate_goals.NavigateGoals`)."""
DELIVERY_LIMIT_S = 2.0
"""How long a stopping node waits for every subscriber to acknowledge its zero command."""
STALE_CHECK_S = 0.05
"""How often (wall seconds) the driver checks whether its observation went stale."""


class VelocityDriver:
    """Drives the robot with the sub-controller's actions (``drive: commands``): one command per action on
    ``cmd_vel_topic`` (the :class:`~hdrqn_ros.nodes.nav.ActionTable`'s ``Twist`` or
    ``TwistStamped``), the zero command when the episode ends or the node stops, and when no
    observation came for ``stale_after_s`` (wall time) while the robot moves."""

    def __init__(self, node: ControllerNode, table: ActionTable):
        self.node, self.table = node, table
        self.topic = node.resolve_topic_name(node.params["cmd_vel_topic"])
        self.pub = node.create_publisher(table.msg_type, node.params["cmd_vel_topic"], DEFAULT_QOS)
        self.observed_at: float | None = None  # when the last observation arrived (monotonic s)
        self.moving = False  # the last command published was not the zero one
        node.create_timer(STALE_CHECK_S, self._stop_if_stale, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def command(self, action: int | None, stamp=(0, 0)) -> tuple:
        """The (publisher, message) that commands ``action`` (``None``: the zero command),
        stamped ``stamp`` (a step key, ns) if the table is stamped."""
        self.moving = action is not None and self.table.moves(action)
        return self.pub, self.table.stop_msg(stamp) if action is None else self.table.twist_msg(action, stamp)

    def observed(self, frame_id: str = "") -> None:
        """An observation arrived (drawn in ``frame_id``): the commands go on."""
        self.observed_at = time.monotonic()

    def stale(self) -> bool:
        """The observation is older than ``stale_after_s``."""
        return self.observed_at is not None and time.monotonic() - self.observed_at > self.node.params["stale_after_s"]

    def problems(self) -> list[str]:
        if self.stale():
            return [f"the observation is older than stale_after_s ({self.node.params['stale_after_s']} s): the robot "
                    f"is stopped"]
        return []

    def values(self) -> dict[str, str]:
        """How it drives, for the diagnostics."""
        return {"drive": f"one command per action on {self.topic}"}

    def release(self) -> None:
        """Nothing to release beyond the publisher (destroyed with the node's entities)."""

    def halt(self) -> None:
        """The zero command, delivered before the node stops acting (at most :data:`DELIVERY_LIMIT_S`)."""
        pub, msg = self.command(None)
        pub.publish(msg)
        if not pub.wait_for_all_acked(Duration(seconds=DELIVERY_LIMIT_S)):
            self.node.get_logger().warning(f"the zero command on {self.topic} was not acknowledged by every "
                                           f"subscriber within {DELIVERY_LIMIT_S:g} s")

    def _stop_if_stale(self) -> None:
        if self.moving and self.stale():
            pub, msg = self.command(None)
            pub.publish(msg)
            self.node.get_logger().info(
                f"zero command on {self.topic}: the observation is {time.monotonic() - self.observed_at:.1f} s old "
                f"(stale_after_s {self.node.params['stale_after_s']})")


class SubgoalPlaces:
    """The places of the subgoals: from ``subgoal_table``, or the latest ``PoseArray`` on
    ``subgoal_poses_topic`` (``table`` is ``None`` until one arrives)."""

    def __init__(self, node: ControllerNode, num_subgoals: int):
        self.node, self.num_subgoals = node, num_subgoals
        params = node.params
        self.table = SubgoalTable.load(params["subgoal_table"], num_subgoals) if params["subgoal_table"] else None
        if params["subgoal_poses_topic"]:
            bounded_subscription(node, PoseArray, params["subgoal_poses_topic"], self._on_places, LATCHED_QOS,
                                 params["max_message_bytes"], node.logger)

    def pose_msg(self, subgoal: int, stamp) -> PoseStamped | None:
        """The place of ``subgoal`` stamped ``stamp`` (ns, or (sec, nanosec)); ``None`` while unknown."""
        return None if self.table is None else self.table.pose_msg(subgoal, stamp)

    def _on_places(self, msg: PoseArray) -> None:
        topic = self.node.params["subgoal_poses_topic"]
        places = self.node.decode(topic, lambda: SubgoalTable.from_pose_array(
            msg, self.num_subgoals, self.node.resolve_topic_name(topic)))
        if places is not None:
            self.table = places


class GoalPoses:
    """Sends each new option's subgoal to the robot's navigator as a ``PoseStamped`` on
    ``goal_pose_topic`` (Nav2's ``goal_pose``, fire-and-forget: ``navigation: topic``);
    nothing is sent while the places are unknown. The navigator's own topic subscription
    decides what happens to a goal: nothing comes back, and the option ends at the place or
    at the critic's ``option_timeout``."""

    def __init__(self, node: ControllerNode, places: SubgoalPlaces):
        self.places = places
        self.pub = node.create_publisher(PoseStamped, node.params["goal_pose_topic"], DEFAULT_QOS)

    def ready(self) -> bool:
        """A goal can go out now (always: the topic has no server to wait for)."""
        return True

    def replies(self, subgoal: int, key: int) -> list[tuple]:
        """The (publisher, goal pose) of ``subgoal`` stamped ``key``; none while the places are unknown."""
        msg = self.places.pose_msg(subgoal, key)
        return [] if msg is None else [(self.pub, msg)]

    def end_episode(self) -> None:
        """The episode ended (a goal pose cannot be taken back)."""

    def stop(self) -> None:
        """The node stops acting (a goal pose cannot be taken back)."""

    def problems(self) -> list[str]:
        return []

    def values(self) -> dict[str, str]:
        return {"navigation": f"topic {self.pub.topic_name}"}

    def release(self) -> None:
        """Nothing to release beyond the publisher (destroyed with the node's entities)."""

    def settle(self, executor) -> None:
        """Nothing waits for an answer."""
