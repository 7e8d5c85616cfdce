"""The loopback robot's ``navigate_to_pose`` action server: Nav2's navigator in miniature
(an rclpy ``ActionServer`` of Jazzy's ``nav2_msgs/action/NavigateToPose``, hosted by the
``loopback_robot`` process on its simulated time).

Each goal, a pose in the map frame, is planned over the map's free cells
(:func:`hdrqn_ros.robot.grid_planner.plan`) from the robot's cell, and the robot is driven
along the plan (through the cells' centres, then to the goal) at ``nav_speed``, one
velocity command per simulated tick: straight at the next point on a holonomic robot; on a
differential drive turning on the spot at :data:`TURN_SPEED`, then driving. Outcomes as
Nav2 gives them:

- SUCCEEDED once the robot is within :data:`XY_GOAL_TOLERANCE` (Nav2's default
  ``xy_goal_tolerance``, 0.25 m) of the goal: it stops there, not at the goal itself (the
  goal's yaw is not turned to);
- ABORTED at once when there is no plan, with the planner's error code as Jazzy's
  ``bt_navigator`` passes it on (``ComputePathToPose``: 202 TF_ERROR for a goal in another
  frame, 204 GOAL_OUTSIDE_MAP, 206 GOAL_OCCUPIED, 208 NO_VALID_PATH) and
  ``error_msg`` saying why; ABORTED too when a newer goal preempts it (the newer one goes
  on) and when the robot is put back at an episode's start;
- CANCELED on a cancel request: the robot stops at once.

Feedback every :data:`FEEDBACK_PERIOD_S` simulated seconds: ``current_pose``,
``navigation_time``, ``estimated_time_remaining``, ``number_of_recoveries`` (0: there are
no recoveries here) and ``distance_remaining`` along the plan (m).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.node import Node
from rclpy.task import Future
from rclpy.time import Time
from std_msgs.msg import Header

from hdrqn_ros.nodes.ros_messages import interface_class
from hdrqn_ros.robot.grid_planner import PlanError, path_length, plan
from hdrqn_ros.robot.loopback_world import LoopbackWorld

NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
XY_GOAL_TOLERANCE = 0.25
"""m: the goal is reached within this distance (Nav2's ``xy_goal_tolerance`` default)."""
TURN_SPEED = 1.0
"""rad/s: a differential drive's turn on the spot."""
FEEDBACK_PERIOD_S = 0.5
PLAN_ERROR_CODES = {"outside": 204, "occupied": 206, "no_path": 208}
"""Jazzy's ``ComputePathToPose`` result codes (GOAL_OUTSIDE_MAP, GOAL_OCCUPIED, NO_VALID_PATH)
by :class:`~hdrqn_ros.robot.grid_planner.PlanError` reason."""
TF_ERROR = 202
"""Jazzy's ``ComputePathToPose`` TF_ERROR (the goal's frame is not the map's)."""
SUCCEEDED, ABORTED, CANCELED = "succeed", "abort", "canceled"
"""How a navigation ends: the goal handle's method that says so."""
STATUS_NAMES = {SUCCEEDED: "SUCCEEDED", ABORTED: "ABORTED", CANCELED: "CANCELED"}


@dataclass
class _Navigation:
    """One goal being driven to."""

    handle: object  # rclpy ServerGoalHandle
    goal_xy: tuple[float, float]  # m, map frame
    started_ns: int  # simulated time the goal was accepted
    episode: int  # the world's layout episode it was planned in
    points: deque = field(default_factory=deque)  # the plan's points still ahead, (x, y) m
    done: Future = field(default_factory=Future)  # result: (how it ended, error code, error message)
    feedback_ns: int = -1  # when feedback last went out


class LoopbackNavigator:
    """Serves ``action_name`` for ``node`` (the loopback robot) and drives ``world`` when
    :meth:`control` is called before each simulated tick of ``tick_s`` seconds."""

    def __init__(self, node: Node, world: LoopbackWorld, frame_id: str, tick_s: float,
                 action_name: str = "navigate_to_pose"):
        self.node, self.world, self.frame_id, self.tick_s = node, world, frame_id, tick_s
        self.action_type = interface_class(NAVIGATE_TO_POSE)
        self.now_ns = 0
        self.active: _Navigation | None = None
        self.accepted: dict[bytes, _Navigation] = {}  # goal id -> its navigation, until it executes
        self.server = ActionServer(node, self.action_type, action_name, self._execute,
                                   goal_callback=lambda _request: GoalResponse.ACCEPT,
                                   handle_accepted_callback=self._on_accepted,
                                   cancel_callback=self._on_cancel)

    # -- the action ------------------------------------------------------------------------------
    def _on_accepted(self, goal_handle) -> None:
        """Plan the new goal (the active one, preempted, is aborted) and start executing it."""
        if self.active is not None:
            self._finish(self.active, ABORTED, 0, "preempted by a newer goal")
        pose = goal_handle.request.pose
        nav = _Navigation(goal_handle, (pose.pose.position.x, pose.pose.position.y), self.now_ns,
                          self.world.layout.episode)
        self.accepted[bytes(goal_handle.goal_id.uuid)] = nav
        if pose.header.frame_id != self.frame_id:
            self._finish(nav, ABORTED, TF_ERROR, f"the goal is in frame {pose.header.frame_id!r}, the navigator "
                                                 f"plans in {self.frame_id!r}")
        elif not all(math.isfinite(v) for v in nav.goal_xy):
            self._finish(nav, ABORTED, PLAN_ERROR_CODES["outside"], f"the goal {nav.goal_xy} is not finite")
        else:
            try:
                cells = plan(~self.world.walls, self.world.cell_of(*self.world.pose[:2]),
                             self.world.cell_of(*nav.goal_xy))
            except PlanError as exc:
                self._finish(nav, ABORTED, PLAN_ERROR_CODES[exc.reason], f"no plan to {nav.goal_xy}: {exc}")
            else:
                nav.points.extend(self.world.cell_centre(*cell) for cell in cells)
                nav.points.append(nav.goal_xy)
                self.world.stop()
                self.active = nav
        goal_handle.execute()

    def _on_cancel(self, goal_handle) -> CancelResponse:
        """A cancel is accepted: the robot stops now, and the goal ends CANCELED."""
        if self.active is not None and self.active.handle == goal_handle:
            self._finish(self.active, CANCELED, 0, "")
        return CancelResponse.ACCEPT

    async def _execute(self, goal_handle):
        """Wait for the navigation to end, then say how (the goal handle's terminal state) and
        return the result."""
        nav = self.accepted.pop(bytes(goal_handle.goal_id.uuid))
        how, code, message = await nav.done
        getattr(goal_handle, how)()
        return self.action_type.Result(error_code=code, error_msg=message)

    def _finish(self, nav: _Navigation, how: str, code: int, message: str) -> None:
        """``nav`` ends (``how``: :data:`SUCCEEDED`, :data:`ABORTED` or :data:`CANCELED`); the robot
        stops if it was the active one."""
        if nav.done.done():
            return
        if nav is self.active:
            self.active = None
            self.world.stop()
        if how != SUCCEEDED:
            self.node.get_logger().info(f"navigate_to_pose goal {nav.goal_xy}: {STATUS_NAMES[how]}"
                                        + (f", error_code {code}: {message}" if code or message else ""))
        nav.done.set_result((how, code, message))

    # -- driving -----------------------------------------------------------------------------------
    def control(self, now_ns: int) -> None:
        """Before the simulated tick that starts at ``now_ns``: end the navigation at the goal,
        or command the robot's velocity for the tick along the plan."""
        self.now_ns = now_ns
        nav = self.active
        if nav is None:
            return
        if nav.episode != self.world.layout.episode:
            return self._finish(nav, ABORTED, 0, "the robot was put back at an episode's start")
        x, y, yaw = self.world.pose
        if math.hypot(nav.goal_xy[0] - x, nav.goal_xy[1] - y) <= XY_GOAL_TOLERANCE:
            self._feedback(nav, force=True)
            return self._finish(nav, SUCCEEDED, 0, "")
        while len(nav.points) > 1 and math.hypot(nav.points[0][0] - x, nav.points[0][1] - y) < 1e-9:
            nav.points.popleft()
        tx, ty = nav.points[0]
        dx, dy = tx - x, ty - y
        step = min(self.world.nav_speed * self.tick_s, math.hypot(dx, dy))
        if self.world.holonomic:  # straight at the point: its direction in the robot's frame
            along = step / max(math.hypot(dx, dy), 1e-12) / self.tick_s
            c, s = math.cos(yaw), math.sin(yaw)
            self.world.command((dx * c + dy * s) * along, (-dx * s + dy * c) * along, 0.0, self.tick_s)
        else:  # turn on the spot to face the point, then drive to it
            turn = math.remainder(math.atan2(dy, dx) - yaw, 2 * math.pi)
            if abs(turn) > 1e-6:
                self.world.command(0.0, 0.0, math.copysign(min(abs(turn) / self.tick_s, TURN_SPEED), turn),
                                   self.tick_s)
            else:
                self.world.command(step / self.tick_s, 0.0, 0.0, self.tick_s)
        self._feedback(nav)

    def _feedback(self, nav: _Navigation, force: bool = False) -> None:
        if not force and 0 <= nav.feedback_ns and self.now_ns - nav.feedback_ns < FEEDBACK_PERIOD_S * 1e9:
            return
        nav.feedback_ns = self.now_ns
        x, y, yaw = self.world.pose
        remaining = path_length([(x, y), *nav.points])
        feedback = self.action_type.Feedback(
            current_pose=PoseStamped(header=Header(stamp=Time(nanoseconds=self.now_ns).to_msg(),
                                                   frame_id=self.frame_id),
                                     pose=Pose(position=Point(x=float(x), y=float(y)),
                                               orientation=Quaternion(z=math.sin(yaw / 2), w=math.cos(yaw / 2)))),
            navigation_time=_duration(self.now_ns - nav.started_ns),
            estimated_time_remaining=_duration(int(remaining / self.world.nav_speed * 1e9)),
            number_of_recoveries=0, distance_remaining=float(remaining))
        nav.handle.publish_feedback(feedback)


def _duration(ns: int) -> Duration:
    return Duration(sec=int(ns // 10**9), nanosec=int(ns % 10**9))
