"""``robot_environment`` node: the environment node's place on a robot.

On a robot nothing simulates the task, so this node builds, every ``step_period`` seconds
of ROS time (simulated with ``use_sim_time``; from a pose stamped at or after the step's
time), what the environment node publishes (``docs/topics.md``): ``observation`` (the
local costmap around the robot, drawn as the simulator draws its view, the places still
to visit in their colours), ``subgoal_images`` (the costmap around each place),
``env_step`` (``at_subgoal`` from the robot's distance to each place, visits paid by the
gridworld's ordered-goal rules: :class:`~hdrqn_ros.robot.ordered_visits.OrderedVisits`,
episode boundaries) and ``pose``. The critic, meta-controller, sub-controller and learner
run unchanged, lock-step as in training: a step waits for the sub-controller's ``action``
on the previous one. What moves the robot is the controllers' business (``goal_pose`` to
Nav2, or ``cmd_vel``).

Inputs: the robot pose (``pose_topic``: Odometry, PoseStamped or PoseWithCovarianceStamped),
the local costmap (``costmap_topic``), optionally a global costmap for the places' images,
and the places: a ``subgoal_table`` YAML or a latched ``geometry_msgs/PoseArray`` on
``subgoal_poses_topic`` (a loopback robot publishes each episode's layout there). Every
input must be in the places' frame (there is no tf2 here). Episodes start and stop with
``~/start_episode`` and ``~/stop_episode`` (``std_srvs/Trigger``) or one after the other
with ``autostart``; each ends when every place was visited in order or at ``max_steps``.
Each finished episode is logged, and appended to ``episode_log``
(:class:`~hdrqn_ros.robot.episode_log.EpisodeLog`). A managed node
(:mod:`hdrqn_ros.nodes.lifecycle`): it steps only while active.
"""
from __future__ import annotations

import time

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.clock import Clock, ClockType
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Int64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from hdrqn_ros.envs.gridworld import GOAL_NAMES
from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.diagnostics import OK, WARN, Diagnostics
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, domain_sizes, odd_cells
from hdrqn_ros.nodes.lifecycle import ManagedNode
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import NodeConfigError, Param
from hdrqn_ros.nodes.place_markers import MARKERS, place_markers
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS, STEP_QOS
from hdrqn_ros.nodes.robot_inputs import RobotInputs
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription, interface_class
from hdrqn_ros.protocol import wire
from hdrqn_ros.robot.episode_log import EpisodeLog
from hdrqn_ros.robot.ordered_visits import OrderedVisits

DEFAULT_MAX_STEPS = 50
"""The domain's step limit (``max_steps`` 0)."""
POLL_S, WATCHDOG_S = 0.02, 0.5
"""Wall seconds between looks at whether a step can be taken (a pose or an action arriving
looks at once), and between looks for a missing action."""
WAIT_REPORTED_S, WAIT_REPEATED_S = 2.0, 10.0
"""A wait is reported once it lasts this long (diagnostics WARN, log), and logged again this often."""


def _odd_cells(view: str) -> str | None:
    return None if odd_cells(view) else \
        f"the robot's observation needs an odd number of cells (no 'full' view), got {view!r}"


PARAMETERS = {
    **ENV_PARAMETERS, **MAX_MESSAGE_BYTES,
    "view": Param("5", "the observation's view: an odd number of cells (a string)", check=_odd_cells),
    "step_period": Param(2.5, "seconds (ROS time) per agent step", live=True, positive=True),
    "pose_topic": Param("/odom", "the robot's pose (e.g. /odom, /amcl_pose)"),
    "pose_type": Param("odometry", "the pose topic's type", choices=tuple(nav.POSE_TYPES)),
    "costmap_topic": Param("/local_costmap/costmap", "the observation's costmap (nav_msgs/OccupancyGrid)"),
    "global_costmap_topic": Param("", "the places' images' costmap ('': the local one)"),
    "subgoal_table": Param("", "the places as a YAML table (this or subgoal_poses_topic)"),
    "subgoal_poses_topic": Param("", "the places as a latched geometry_msgs/PoseArray"),
    "new_layout_each_episode": Param(False, "start an episode only on places published since the last one ended"),
    "goal_tolerance": Param(0.125, "metres within which the robot is at a place", live=True, positive=True),
    "max_steps": Param(0, "an episode's step limit (0: the domain's, 50)", live=True, low=0, high=100000),
    "cell_size_m": Param(0.25, "metres per simulator cell in the observation", positive=True),
    "heading_up": Param(False, "observation turned with the robot's yaw (forward/turn action tables) instead of "
                               "north-up"),
    "lethal": Param(nav.LETHAL, "costmap cost drawn as wall (and reported as hit_obstacle under the robot)",
                    live=True, low=1, high=100),
    "unknown_cells": Param("outside", "unknown costmap cells drawn black (outside, as beyond the simulator's map) "
                                      "or as wall", choices=("outside", "wall")),
    "stale_after_s": Param(5.0, "a pose or costmap older than this (ROS time since it arrived) holds the next step",
                           live=True, positive=True),
    "action_timeout": Param(5.0, "wall seconds without an action before a warning and a re-published step",
                            live=True, positive=True),
    "autostart": Param(True, "start the next episode as soon as one ends (false: on ~/start_episode)", live=True),
    "max_episodes": Param(0, "exit after this many episodes (0: never)", live=True, low=0, high=2**31),
    "episode_log": Param("", "append each finished episode to this JSON-lines file ('': off)"),
    "wait_for_learner": Param(False, "start the first episode once a learner is heard on learner_credit (a learner "
                                     "that records the episodes gets all of them)"),
}
"""The robot environment's parameters; the live ones take effect at the next step."""


class RobotEnvironmentNode(ManagedNode):
    """One robot's task as an environment node."""

    def __init__(self, **kwargs):
        super().__init__("robot_environment", PARAMETERS, **kwargs)
        self.logger = python_logger(self)

    # -- the lifecycle ---------------------------------------------------------------------------
    def build(self) -> None:
        params = self.params
        if bool(params["subgoal_table"]) == bool(params["subgoal_poses_topic"]):
            raise NodeConfigError("give the places either as subgoal_table (a YAML file) or as subgoal_poses_topic "
                                  "(a latched geometry_msgs/PoseArray), exactly one")
        self.num_actions, self.num_subgoals = domain_sizes(params["env"], params["view"])
        self.view = int(params["view"])
        self.task = OrderedVisits(self.num_subgoals, params["goal_tolerance"], params["max_steps"] or DEFAULT_MAX_STEPS)
        places = nav.SubgoalTable.load(params["subgoal_table"], self.num_subgoals) if params["subgoal_table"] else None
        topics = {"pose": params["pose_topic"], "costmap": params["costmap_topic"],
                  "global": params["global_costmap_topic"], "places": params["subgoal_poses_topic"],
                  wire.ACTION: wire.ACTION, wire.SUBGOAL: wire.SUBGOAL}
        self.inputs = RobotInputs(self.logger, {kind: self.resolve_topic_name(topic) for kind, topic in topics.items()
                                                if topic}, places, self.num_subgoals, self.view, params["cell_size_m"])
        # step keys are ROS time: simulated as it is, wall time since the node started (below 2^53)
        self.key_origin = 0 if self.get_parameter("use_sim_time").value else time.time_ns() - 10**9
        self._reset()
        self._subscribe()
        self.pub_obs = self.create_publisher(Image, wire.OBSERVATION, STEP_QOS)
        self.pub_images = self.create_publisher(Image, wire.SUBGOAL_IMAGES, STEP_QOS)
        self.pub_step = self.create_publisher(Float64MultiArray, wire.ENV_STEP, STEP_QOS)
        self.pub_pose = self.create_publisher(PoseStamped, wire.POSE, DEFAULT_QOS)
        self.pub_markers = self.create_publisher(MarkerArray, MARKERS, DEFAULT_QOS)
        self.create_service(Trigger, "~/start_episode", self._on_start)
        self.create_service(Trigger, "~/stop_episode", self._on_stop)
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # also while a simulated clock stands still
        self.create_timer(POLL_S, self._tick, clock=steady)
        self.create_timer(WATCHDOG_S, self._watchdog, clock=steady)
        self.diagnostics = Diagnostics(self, self._health)
        self.episodes = EpisodeLog(params["episode_log"])

    def _reset(self) -> None:
        """No episode yet (the first starts as ``autostart`` says), nothing heard from the learner."""
        self.learner_heard = False
        self.start_requested, self.stop_requested = self.params["autostart"], False
        self.running = False
        self.record: dict = {}  # the latest step's env_step fields
        self.key = self.step_ns = 0
        self.ended_ns = -1  # ROS time the last episode ended
        self.episode, self.env_steps, self.episode_return = -1, 0, 0.0
        self.pending_action: int | None = None
        self.published_at = self.stepped_at = time.monotonic()
        self.decision_s: list[float] = []  # this episode's wall seconds from a step to its action
        self.option_subgoal = -1  # the current option's place (the meta-controller's subgoal), for the markers
        self.wait_since: float | None = None  # wall time the current wait began
        self.wait_logged, self.wait_reason = 0.0, ""

    def _subscribe(self) -> None:
        params = self.params

        def subscribe(msg_type, topic: str, callback, qos) -> None:
            bounded_subscription(self, msg_type, topic, callback, qos, params["max_message_bytes"], self.logger)

        subscribe(interface_class(nav.POSE_TYPES[params["pose_type"]]), params["pose_topic"], self._on_pose,
                  DEFAULT_QOS)
        subscribe(OccupancyGrid, params["costmap_topic"], self._on_costmap, LATCHED_QOS)
        if params["global_costmap_topic"]:
            subscribe(OccupancyGrid, params["global_costmap_topic"], self._on_global_costmap, LATCHED_QOS)
        if params["subgoal_poses_topic"]:
            subscribe(PoseArray, params["subgoal_poses_topic"], self.inputs.take_places, LATCHED_QOS)
        subscribe(Int64MultiArray, wire.ACTION, self._on_action, STEP_QOS)
        subscribe(Int64MultiArray, wire.SUBGOAL, self._on_subgoal, STEP_QOS)
        if params["wait_for_learner"]:
            subscribe(Float64MultiArray, wire.CREDIT, self._on_credit, LATCHED_QOS)

    def start(self) -> None:
        self.wait_since = None

    def stop(self) -> None:
        """A running episode is abandoned (no further step of it is published)."""
        if self.running:
            self.running, self.stop_requested = False, False
            self.get_logger().info(f"episode {self.episode} abandoned at step t={int(self.record['t'])}: the node "
                                   f"stopped stepping (deactivated or shut down)")

    def teardown(self) -> None:
        self.episodes.close()

    def on_live_parameter(self, name: str, value) -> None:
        if not self.configured:
            return  # read at the next configure
        if name == "goal_tolerance":
            self.task.tolerance_m = float(value)
        elif name == "max_steps":
            self.task.max_steps = int(value) or DEFAULT_MAX_STEPS
        elif name == "autostart" and value:
            self.start_requested = True

    def _ns(self, name: str) -> int:
        """Parameter ``name`` (seconds) in nanoseconds."""
        return int(round(self.params[name] * 1e9))

    # -- inputs ------------------------------------------------------------------------------------
    def _now(self) -> int:
        """ROS time (ns): ``/clock``'s with ``use_sim_time``."""
        return self.get_clock().now().nanoseconds

    def _on_pose(self, msg) -> None:
        if self.inputs.take_pose(msg, self._now()):
            self._tick()

    def _on_costmap(self, msg: OccupancyGrid) -> None:
        self.inputs.take_costmap(msg, self._now())

    def _on_global_costmap(self, msg: OccupancyGrid) -> None:
        self.inputs.take_costmap(msg, self._now(), "global")

    def _on_action(self, msg: Int64MultiArray) -> None:
        try:
            key, actions = wire.read_actions(msg, self.num_actions, 1)
        except wire.ProtocolError as exc:
            self.inputs.reject(wire.ACTION, exc)
            return
        if self.running and key == self.key and self.pending_action is None and actions[0] >= 0:
            self.pending_action = int(actions[0])
            self.decision_s.append(time.monotonic() - self.stepped_at)
            self.diagnostics.decision(self.decision_s[-1])
            self._tick()

    def _on_subgoal(self, msg: Int64MultiArray) -> None:
        try:
            _, chosen = wire.read_subgoals(msg, self.num_subgoals, 1)
        except wire.ProtocolError as exc:
            self.inputs.reject(wire.SUBGOAL, exc)
            return
        if chosen[0] >= 0:
            self.option_subgoal = int(chosen[0])
            if self.running:
                self._publish_markers()

    def _on_credit(self, _msg: Float64MultiArray) -> None:
        self.learner_heard = True

    def _on_start(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = not self.finished
        response.message = "finished: max_episodes reached" if self.finished else \
            ("an episode is running" if self.running else "the next episode starts when the inputs are fresh")
        self.start_requested, self.stop_requested = not self.finished, False
        return response

    def _on_stop(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success = True
        response.message = f"episode {self.episode} ends at the next step" if self.running else "no episode running"
        self.start_requested, self.stop_requested = False, self.running
        return response

    # -- health ----------------------------------------------------------------------------------------
    def _health(self) -> tuple[int, str, dict[str, str]]:
        """The diagnostics: WARN while a step has waited over 2 s (saying for what), or messages were rejected."""
        places = self.inputs.places
        values = {"episodes": str(self.episodes.done), "successes": str(self.episodes.successes),
                  "step_period_s": f"{self.params['step_period']:g}", "messages_rejected": str(self.inputs.rejections),
                  "places": places.source if places is not None else "none yet"}
        if self.finished:
            return OK, f"finished {self.episodes.done} episodes", values
        if not self.active:
            return OK, "inactive (managed node: activate to step)", values
        waited = 0.0 if self.wait_since is None else time.monotonic() - self.wait_since
        if waited > WAIT_REPORTED_S:
            return WARN, f"waiting {waited:.0f} s {self.wait_reason}", values
        if self.running and self.pending_action is None and time.monotonic() - self.stepped_at > WAIT_REPORTED_S:
            return WARN, f"waiting for the action of step t={int(self.record['t'])} on " \
                         f"{self.resolve_topic_name(wire.ACTION)} (is the sub_controller running?)", values
        state = f"episode {self.episode} step t={int(self.record['t'])}" if self.running else "between episodes"
        return OK, state, values

    def _wait(self, why: str) -> None:
        """Report a wait that lasts (after 2 s, then every 10 s), not a momentary one."""
        now = time.monotonic()
        self.wait_reason = why
        if self.wait_since is None:
            self.wait_since = now
        elif now - self.wait_since >= WAIT_REPORTED_S and now - self.wait_logged >= WAIT_REPEATED_S:
            self.wait_logged = now
            self.get_logger().warning(f"waiting {now - self.wait_since:.0f} s {why}")

    def _watchdog(self) -> None:
        """Re-publish a step whose action has not come within ``action_timeout``."""
        if not self.running or self.pending_action is not None or not self.active:
            return
        waited = time.monotonic() - self.published_at
        if waited >= self.params["action_timeout"]:
            self.get_logger().warning(
                f"no action for step t={int(self.record['t'])} of episode {self.episode} after {waited:.1f} s on "
                f"{self.resolve_topic_name(wire.ACTION)} (is the sub_controller running?); re-publishing the step")
            self._publish()
            self.published_at = time.monotonic()

    # -- stepping ------------------------------------------------------------------------------------
    def _tick(self) -> None:
        """Start an episode, or take the next step, as soon as what it needs is there."""
        if not self.active or self.finished:
            return
        if self.running:
            self._step_when_due(self._now())
        elif self.start_requested:
            self._start_when_ready(self._now())

    def _start_when_ready(self, now: int) -> None:
        if self.params["wait_for_learner"] and not self.learner_heard:
            return self._wait(f"for a learner on {self.resolve_topic_name(wire.CREDIT)}")
        if self.inputs.places is None:
            return self._wait(f"no places yet on {self.inputs.topics['places']}")
        new_layout = self.params["new_layout_each_episode"]
        if new_layout and self.inputs.places_stamp < self.ended_ns:
            return
        if why := self.inputs.missing(now, self._ns("stale_after_s"), self.inputs.places_stamp if new_layout else 0):
            return self._wait(f"to start an episode: {why}")
        self._start_episode(now)

    def _step_when_due(self, now: int) -> None:
        due = self.step_ns + self._ns("step_period")
        if self.pending_action is None or now < due or self.inputs.pose.stamp_ns < due:
            return  # the action, the step's time, and a pose measured at or after it
        if why := self.inputs.missing(now, self._ns("stale_after_s")):
            return self._wait(f"for step t={int(self.record['t']) + 1}: {why}")
        self._advance(now)

    def _new_key(self, now: int) -> None:
        self.key = max(now - self.key_origin, self.key + 1)
        self.step_ns, self.pending_action = now, None
        self.published_at = self.stepped_at = time.monotonic()
        self.wait_since = None

    def _start_episode(self, now: int) -> None:
        self.episode += 1
        self.task.start(np.array([pose[:2] for pose in self.inputs.places.poses]))
        self.running, self.episode_return, self.decision_s, self.option_subgoal = True, 0.0, [], -1
        self._new_key(now)
        self.record = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        self.record.update(key=self.key, prev_key=0, env_steps=self.env_steps, episode=self.episode,
                           at_subgoal=self.task.where(self.inputs.pose.value[:2]), decision_point=1)
        self._publish()

    def _advance(self, now: int) -> None:
        prev_key, action = self.key, self.pending_action
        outcome = self.task.step(self.inputs.pose.value[:2], self.inputs.on_lethal(self.params["lethal"]))
        if self.stop_requested and not outcome["terminated"]:
            outcome.update(truncated=True, decision_point=False)
        self.env_steps += 1
        self._new_key(now)
        self.record = {"key": self.key, "prev_key": prev_key, "env_steps": self.env_steps, "episode": self.episode,
                       "t": self.task.t, "action": action, **outcome}
        self.episode_return += outcome["extrinsic"]
        self._publish()
        if outcome["terminated"] or outcome["truncated"]:
            self._end_episode(now, outcome["success"])

    def _end_episode(self, now: int, success: bool) -> None:
        self.running, self.stop_requested, self.ended_ns = False, False, now
        visits = self.task.visits
        self.episodes.add(self.episode, success, self.task.t, visits, self.episode_return, self.decision_s)
        names = ", ".join(GOAL_NAMES[g] if g < len(GOAL_NAMES) else str(g) for g in visits) or "nothing"
        self.get_logger().info(f"episode {self.episode}: visited {names} in {self.task.t} steps, "
                               f"{'in order' if success else 'not in order'} "
                               f"(success {self.episodes.successes} of {self.episodes.done})")
        if self.params["max_episodes"] and self.episodes.done >= self.params["max_episodes"]:
            self.finished = True

    def _publish(self) -> None:
        """The current step: ``env_step``, ``observation``, ``subgoal_images``, ``pose`` and the markers."""
        key, frame, params, inputs = self.key, self.inputs.places.frame_id, self.params, self.inputs
        x, y, yaw = inputs.pose.value
        view = {"view_cells": self.view, "cell_size_m": params["cell_size_m"], "lethal": params["lethal"],
                "robot_yaw": yaw if params["heading_up"] else None, "unknown": params["unknown_cells"],
                "goals_xy": self.task.uncollected_xy()}
        obs = nav.costmap_to_observation(inputs.costmap.value, robot_xy=(x, y), **view)
        images = np.concatenate([nav.costmap_to_observation(inputs.places_costmap, robot_xy=xy, agent_xy=(x, y), **view)
                                 for xy in self.task.goal_xy])
        self.pub_step.publish(wire.make_record(ROS_MESSAGES, wire.FLOATS, wire.STEP_FIELDS,
                                               [self.record[f] for f in wire.STEP_FIELDS]))
        self.pub_obs.publish(wire.make_image(ROS_MESSAGES, key, obs, frame))
        self.pub_images.publish(wire.make_image(ROS_MESSAGES, key, images, frame))
        self.pub_pose.publish(wire.make_pose(ROS_MESSAGES, key, frame, x, y))
        self._publish_markers()

    def _publish_markers(self) -> None:
        header = wire.make_header(ROS_MESSAGES, self.key, self.inputs.places.frame_id)
        self.pub_markers.publish(place_markers(header, self.task.goal_xy, self.task.collected, self.option_subgoal,
                                               self.inputs.pose.value[:2]))


def main(argv: list[str] | None = None) -> int:
    return run_node(RobotEnvironmentNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
