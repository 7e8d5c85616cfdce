"""The meta-controller's options as Nav2 goals with outcomes: one ``navigate_to_pose`` goal
(``nav2_msgs/action/NavigateToPose``, Jazzy's) per option, through rclpy's ``ActionClient``.

- No goal goes out before the action server is there (nor before the places are known):
  an option that starts then waits (the meta-controller does not answer the step), and
  after 2 s the wait is logged (again every 10 s) and ``/diagnostics`` says WARN, naming
  the action and that Nav2's ``bt_navigator`` serves it.
- The goal's result ends its option: the outcome goes out on ``navigation_outcome``
  (:mod:`hdrqn_ros.nodes.navigation_outcomes`) and the critic (``navigation_outcome`` on)
  ends the option at its next step. SUCCEEDED: the navigator stands at the place (the robot environment still decides
  from the robot's pose whether it is a visit); ABORTED, CANCELED or a rejected goal: the
  option failed, at once, without waiting for ``option_timeout``.
- An option that ends while its goal is still active (the critic's ``option_timeout``,
  the place reached first, the episode's end) cancels that goal; so do deactivating the
  node and stopping it (a stopping process waits up to 2 s for the server's answer).
- The feedback (distance remaining, recoveries, navigation time) and the counts of each
  outcome are values of the node's ``/diagnostics`` status.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

from rclpy.action import ActionClient
from rclpy.clock import Clock, ClockType
from std_msgs.msg import Int64MultiArray

from hdrqn_ros.nodes.controller_node import ControllerNode
from hdrqn_ros.nodes.nav_adapters import SubgoalPlaces
from hdrqn_ros.nodes.navigation_outcomes import ENDED, NAVIGATION_OUTCOME, STATUS_ABORTED, outcome_message
from hdrqn_ros.nodes.qos import STEP_QOS
from hdrqn_ros.nodes.ros_messages import interface_class

NAVIGATE_TO_POSE = "nav2_msgs/action/NavigateToPose"
WAIT_REPORTED_S, WAIT_REPEATED_S = 2.0, 10.0
"""A wait for the action server is reported once it lasts this long, and logged again this often."""
WATCH_S = 0.5
"""Wall seconds between looks at whether the action server is there."""
CANCEL_LIMIT_S = 2.0
"""How long a stopping node waits for the server to answer its cancel."""
REJECTED = "rejected"


@dataclass
class _Goal:
    """One option's goal: the option's step key and subgoal, and its handle once accepted."""

    key: int
    subgoal: int
    sent_at: float  # monotonic s
    handle: object = None  # rclpy ClientGoalHandle


class NavigateGoals:
    """Sends each new option's place (``places``) as a ``navigate_to_pose`` goal
    (``navigate_action``) and publishes its outcome; ``on_ready()`` is called while goals
    can go out (the meta-controller then takes a step that waited for them)."""

    def __init__(self, node: ControllerNode, places: SubgoalPlaces, on_ready: Callable[[], None]):
        self.node, self.places, self.on_ready = node, places, on_ready
        self.created_at = time.monotonic()
        self.action_type = interface_class(NAVIGATE_TO_POSE)
        self.name = node.resolve_topic_name(node.params["navigate_action"])
        self.client = ActionClient(node, self.action_type, node.params["navigate_action"])
        self.pub_outcome = node.create_publisher(Int64MultiArray, NAVIGATION_OUTCOME, STEP_QOS)
        self.goal: _Goal | None = None  # the current option's goal, until its result comes
        self.feedback = None  # the current goal's latest NavigateToPose.Feedback
        self.cancels: list = []  # futures of the cancel requests not yet answered
        self.counts = {name: 0 for name in (*ENDED.values(), REJECTED)}
        self.sent = 0
        self.last_outcome = "none yet"
        self.waiting_since: float | None = time.monotonic()  # since when no server is seen (None: one is)
        self.wait_logged = -math.inf
        node.create_timer(WATCH_S, self._watch_server, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # -- the meta-controller's side --------------------------------------------------------------
    def ready(self) -> bool:
        """A goal can go out now: the places are known and the action server is there."""
        return self.places.table is not None and self.client is not None and self.client.server_is_ready()

    def replies(self, subgoal: int, key: int) -> list[tuple]:
        """Send the goal of the option that starts at step ``key`` (the previous option's goal,
        if still active, is cancelled); nothing to publish on the step itself."""
        self._cancel("its option ended")
        pose = self.places.pose_msg(subgoal, self.node.get_clock().now().nanoseconds)
        goal = self.goal = _Goal(key, subgoal, time.monotonic())
        self.feedback = None
        self.sent += 1
        future = self.client.send_goal_async(self.action_type.Goal(pose=pose),
                                             feedback_callback=lambda msg: self._on_feedback(goal, msg))
        future.add_done_callback(lambda done: self._on_response(goal, done))
        return []

    def end_episode(self) -> None:
        self._cancel("the episode ended")

    def stop(self) -> None:
        self._cancel("the node stopped acting")

    def problems(self) -> list[str]:
        """The waits for the action server and for the places (after 2 s); an outcome nobody
        reads (the critic's ``navigation_outcome`` off: options end only at the place or at
        ``option_timeout``)."""
        now = time.monotonic()
        waited = 0.0 if self.waiting_since is None else now - self.waiting_since
        found = [self._waiting(waited)] if waited > WAIT_REPORTED_S else []
        if self.places.table is None and now - self.created_at > WAIT_REPORTED_S:
            found.append(f"no places yet on {self.node.resolve_topic_name(self.node.params['subgoal_poses_topic'])}: "
                         f"no goal can be sent")
        if self.sent and self.pub_outcome.get_subscription_count() == 0:
            found.append(f"nothing subscribes to {self.pub_outcome.topic_name} (is the critic's navigation_outcome "
                         f"off?): an option ends only at its place or at the critic's option_timeout")
        return found

    def values(self) -> dict[str, str]:
        """The diagnostics' values: the current goal and its feedback, the outcomes so far."""
        values = {"navigation": f"action {self.name}", "goals_sent": str(self.sent),
                  **{f"goals_{name.lower()}": str(n) for name, n in self.counts.items()},
                  "last_outcome": self.last_outcome}
        if self.goal is not None:
            values["goal"] = f"subgoal {self.goal.subgoal}, sent {time.monotonic() - self.goal.sent_at:.1f} s ago"
        if self.goal is not None and self.feedback is not None:
            fb = self.feedback
            values.update(distance_remaining_m=f"{fb.distance_remaining:.2f}",
                          number_of_recoveries=str(fb.number_of_recoveries),
                          navigation_time_s=f"{fb.navigation_time.sec + fb.navigation_time.nanosec * 1e-9:.1f}")
        return values

    def release(self) -> None:
        """The node is cleaned up: the action client goes, unless a cancel still waits for its
        answer (then :meth:`settle` releases it)."""
        self.cancels = [f for f in self.cancels if not f.done()]
        if not self.cancels and self.client is not None:
            self.client.destroy()
            self.client = None

    def settle(self, executor) -> None:
        """The process stops: let the cancels sent be answered (spinning ``executor``, at most
        :data:`CANCEL_LIMIT_S`), then release the action client."""
        deadline = time.monotonic() + CANCEL_LIMIT_S
        while executor is not None and self.client is not None and time.monotonic() < deadline and \
                not all(f.done() for f in self.cancels):
            executor.spin_once(timeout_sec=0.05)
        if not all(f.done() for f in self.cancels):
            self.node.get_logger().warning(f"the cancel sent to {self.name} was not answered within "
                                           f"{CANCEL_LIMIT_S:g} s")
        self.cancels = []
        self.release()

    # -- the action ------------------------------------------------------------------------------------
    def _cancel(self, why: str) -> None:
        """Cancel the current goal, if any (one not yet accepted is cancelled when it is)."""
        goal, self.goal = self.goal, None
        if goal is None or goal.handle is None:
            return
        self.node.get_logger().info(f"cancelling the {self.name} goal of subgoal {goal.subgoal}: {why}")
        self.cancels = [f for f in self.cancels if not f.done()] + [goal.handle.cancel_goal_async()]

    def _on_response(self, goal: _Goal, future) -> None:
        handle = future.result()
        if handle is None or not handle.accepted:
            self._ended(goal, REJECTED, STATUS_ABORTED, "the action server rejected the goal")
            return
        goal.handle = handle
        if goal is not self.goal:  # its option ended before the server accepted it
            self.cancels.append(handle.cancel_goal_async())
            return
        handle.get_result_async().add_done_callback(lambda done: self._on_result(goal, done))

    def _on_result(self, goal: _Goal, future) -> None:
        response = future.result()
        name = ENDED.get(response.status, f"status {response.status}")
        result = response.result
        why = ": ".join(part for part in (f"error_code {result.error_code}" if result.error_code else "",
                                           result.error_msg) if part)
        self._ended(goal, name, response.status, why)

    def _ended(self, goal: _Goal, name: str, status: int, why: str) -> None:
        """``goal`` ended (``name``, GoalStatus ``status``): counted, logged (a warning when the
        current option's goal failed), and, when it is the current option's, its outcome
        published (the option ends)."""
        self.counts[name] = self.counts.get(name, 0) + 1
        took = time.monotonic() - goal.sent_at
        self.last_outcome = f"{name} after {took:.1f} s" + (f" ({why})" if why else "")
        text = f"{self.name} goal of subgoal {goal.subgoal}: {self.last_outcome}"
        if name == "SUCCEEDED" or goal is not self.goal:  # arrived, or cancelled here when its option ended
            self.node.get_logger().info(text)
        else:
            self.node.get_logger().warning(text)
        if goal is self.goal:
            self.goal = None
            self.pub_outcome.publish(outcome_message(goal.key, status))

    def _on_feedback(self, goal: _Goal, msg) -> None:
        if goal is self.goal:
            self.feedback = msg.feedback

    # -- the server's presence -------------------------------------------------------------------------
    def _waiting(self, waited: float) -> str:
        return (f"waiting {waited:.0f} s for the {self.name} action server (nav2_msgs/NavigateToPose; Nav2's "
                f"bt_navigator serves it): no goal is sent before it is up")

    def _watch_server(self) -> None:
        """Look whether the server is there: log a wait that lasts, and its end; let a step
        that waited go on."""
        if self.client is None:
            return
        now = time.monotonic()
        if self.client.server_is_ready():
            if self.waiting_since is not None and now - self.waiting_since > WAIT_REPORTED_S:
                self.node.get_logger().info(f"the {self.name} action server is up after "
                                            f"{now - self.waiting_since:.0f} s")
            self.waiting_since, self.wait_logged = None, -math.inf
            if self.ready():
                self.on_ready()
            return
        if self.waiting_since is None:
            self.waiting_since = now
        waited = now - self.waiting_since
        if waited >= WAIT_REPORTED_S and now - self.wait_logged >= WAIT_REPEATED_S:
            self.wait_logged = now
            self.node.get_logger().warning(self._waiting(waited))
