"""``robot_environment`` node: the environment node's place on a robot.

On a robot nothing simulates the task, so every ``step_period`` seconds of ROS time
(simulated with ``use_sim_time``) this node builds what the environment node publishes
(``docs/topics.md``; :mod:`~hdrqn_ros.nodes.robot_step_topics`) from the robot's pose at
the step's time and the costmaps (:mod:`~hdrqn_ros.nodes.robot_input_topics`):
``observation`` and ``subgoal_images`` (drawn as the simulator draws its view:
:mod:`~hdrqn_ros.nodes.robot_scene`), ``env_step`` (``at_subgoal``, visits paid by the
gridworld's ordered-goal rules, episode boundaries:
:mod:`~hdrqn_ros.nodes.robot_episodes`) and ``pose``. The critic, meta-controller,
sub-controller and learner run unchanged, lock-step as in training: a step waits for the
sub-controller's ``action`` on the previous one. What moves the robot is the controllers'
business (Nav2 goals, or ``cmd_vel``).

Frames as REP 105 has them: the pose is tf's ``global_frame`` <- ``robot_base_frame``
(``map <- base_link``) at the step's time (the latest after ``pose_timeout_s``), or a
``pose_topic``'s (Odometry, PoseStamped or PoseWithCovarianceStamped, in its own frame);
each costmap (full grids on ``costmap_topic``, Nav2's ``<costmap_topic>_updates``) is used
in its own frame at its own stamp; the places (``subgoal_table`` or a latched
``subgoal_poses_topic``) may be in any frame of the tree.

Where the robot is (``visit_rule``, :mod:`~hdrqn_ros.robot.ordered_visits`): ``tolerance``:
at the place of the option in force (the meta-controller's latest ``subgoal`` this episode)
when within ``goal_tolerance`` of it (Nav2's ``xy_goal_tolerance``: a navigator's arrival
is a visit of the place it was sent to, even beside a nearer place), otherwise at the
nearest place within ``goal_tolerance``; ``cell``: in the place's cell (the simulator's
rule, for sub-drives). Episodes start with ``~/start_episode`` (one each call), stop with
``~/stop_episode`` (``std_srvs/Trigger``) or run back to back with ``autostart``
(:mod:`~hdrqn_ros.robot.episode_requests`); each ends when every place was visited in order
or at ``max_steps``, is logged and appended to ``episode_log``. Every wait (pose,
transforms, costmap, places, the learner, the controllers' action) is a WARN on
``/diagnostics`` naming what is missing and who would publish it. A managed node
(:mod:`hdrqn_ros.nodes.lifecycle`): it steps only while active.
"""
from __future__ import annotations

import time

from rclpy.clock import Clock, ClockType
from std_msgs.msg import Float64MultiArray, Int64MultiArray
from std_srvs.srv import Trigger

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.diagnostics import OK, WARN, Diagnostics
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, domain_sizes, odd_cells
from hdrqn_ros.nodes.lifecycle import ManagedNode
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import NodeConfigError, Param
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import LATCHED_QOS, STEP_QOS
from hdrqn_ros.nodes.robot_episodes import RobotEpisodes
from hdrqn_ros.nodes.robot_input_topics import subscribe_robot_inputs
from hdrqn_ros.nodes.robot_inputs import Waiting
from hdrqn_ros.nodes.robot_scene import Scene, scene_at, step_images
from hdrqn_ros.nodes.robot_step_topics import StepPublishers
from hdrqn_ros.nodes.ros_messages import bounded_subscription
from hdrqn_ros.nodes.step_waits import WAIT_REPORTED_S, StepWaits
from hdrqn_ros.protocol import wire
from hdrqn_ros.robot.episode_log import EpisodeLog
from hdrqn_ros.robot.episode_requests import EpisodeRequests
from hdrqn_ros.robot.ordered_visits import CellVisits, OrderedVisits

DEFAULT_MAX_STEPS = 50
"""The domain's step limit (``max_steps`` 0)."""
POLL_S, WATCHDOG_S = 0.02, 0.5
"""Wall seconds between looks at whether a step can be taken (a pose or an action arriving
looks at once), and between looks for a missing action."""


def _odd_cells(view: str) -> str | None:
    return None if odd_cells(view) else \
        f"the robot's observation needs an odd number of cells (no 'full' view), got {view!r}"


PARAMETERS = {
    **ENV_PARAMETERS, **MAX_MESSAGE_BYTES,
    "view": Param("5", "the observation's view: an odd number of cells (a string)", check=_odd_cells),
    "step_period": Param(2.5, "seconds (ROS time) per agent step", live=True, positive=True),
    "global_frame": Param("map", "the frame of the robot's pose from tf (Nav2's global_frame)"),
    "robot_base_frame": Param("base_link", "the robot's frame in tf (Nav2's robot_base_frame)"),
    "pose_timeout_s": Param(1.0, "wall seconds a due step waits for the pose at its time before it takes the latest",
                            live=True, positive=True),
    "pose_topic": Param("", "the robot's pose from a topic instead of tf (e.g. /odom, /amcl_pose; '': from tf)"),
    "pose_type": Param("odometry", "the pose topic's type", choices=tuple(nav.POSE_TYPES)),
    "costmap_topic": Param("/local_costmap/costmap", "the observation's costmap (nav_msgs/OccupancyGrid; its "
                                                     "map_msgs/OccupancyGridUpdate on <costmap_topic>_updates)"),
    "global_costmap_topic": Param("", "the places' images' costmap ('': the local one)"),
    "subgoal_table": Param("", "the places as a YAML table (this or subgoal_poses_topic)"),
    "subgoal_poses_topic": Param("", "the places as a latched geometry_msgs/PoseArray"),
    "new_layout_each_episode": Param(False, "start an episode only on places published since the last one ended"),
    "visit_rule": Param("tolerance", "the robot is at a place within goal_tolerance (the current option's place "
                                     "first, else the nearest), or in the place's cell (cell_size_m square: the "
                                     "simulator's rule)", choices=("tolerance", "cell")),
    "goal_tolerance": Param(0.25, "metres within which the robot is at a place (visit_rule tolerance; Nav2's "
                                  "xy_goal_tolerance)", live=True, positive=True),
    "max_steps": Param(0, "an episode's step limit (0: the domain's, 50)", live=True, low=0, high=100000),
    "cell_size_m": Param(0.25, "metres per simulator cell in the observation", positive=True),
    "heading_up": Param(False, "observation turned with the robot's yaw (forward/turn action tables) instead of "
                               "north-up"),
    "lethal": Param(nav.LETHAL, "costmap cost drawn as wall (and reported as hit_obstacle under the robot)",
                    live=True, low=1, high=100),
    "unknown_cells": Param("outside", "unknown costmap cells drawn black (outside, as beyond the simulator's map) "
                                      "or as wall", choices=("outside", "wall")),
    "stale_after_s": Param(5.0, "a pose, transform or costmap older than this (ROS time) holds the next step",
                           live=True, positive=True),
    "action_timeout": Param(5.0, "wall seconds without an action before a warning and a re-published step",
                            live=True, positive=True),
    "autostart": Param(True, "run episodes back to back (false: one per ~/start_episode)", live=True),
    "max_episodes": Param(0, "exit after this many episodes (0: never)", live=True, low=0, high=2**31),
    "episode_log": Param("", "append each finished episode to this JSON-lines file ('': off)"),
    "wait_for_learner": Param(False, "step only while the learner's learner_credit allows, as the training graph's "
                                     "environment does (a learner that records the episodes gets all of them)"),
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
        max_steps = params["max_steps"] or DEFAULT_MAX_STEPS
        self.task = CellVisits(self.num_subgoals, params["cell_size_m"], max_steps) \
            if params["visit_rule"] == "cell" else OrderedVisits(self.num_subgoals, params["goal_tolerance"], max_steps)
        self.episodes = RobotEpisodes(self.task, EpisodeLog(params["episode_log"]), self.get_logger())
        self.inputs = subscribe_robot_inputs(self, self.logger, params, self.num_subgoals, self.view, self._on_pose,
                                             (wire.ACTION, wire.SUBGOAL, wire.CREDIT))
        # step keys are ROS time: simulated as it is, wall time since the node started (below 2^53)
        self.key_origin = 0 if self.get_parameter("use_sim_time").value else time.time_ns() - 10**9
        self._reset()
        self._subscribe()
        self.outputs = StepPublishers(self)
        self.create_service(Trigger, "~/start_episode", self._on_start)
        self.create_service(Trigger, "~/stop_episode", self._on_stop)
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # also while a simulated clock stands still
        self.create_timer(POLL_S, self._tick, clock=steady)
        self.create_timer(WATCHDOG_S, self._watchdog, clock=steady)
        self.diagnostics = Diagnostics(self, self._health)

    def _reset(self) -> None:
        """No episode yet (the first starts as ``autostart`` says), nothing heard from the learner."""
        self.credit: int | None = None  # the learner's credit: env steps it lets this node take (None: not heard)
        self.requests = EpisodeRequests(self.params["autostart"])
        self.running = False
        self.scene: Scene | None = None  # the latest step's
        self.key = self.step_ns = 0
        self.ended_ns = -1  # ROS time the last episode ended
        self.pending_action: int | None = None
        self.published_at = self.stepped_at = time.monotonic()
        self.option_subgoal = NO_SUBGOAL  # the place of the option in force (the meta-controller's subgoal)
        self.waits = StepWaits(self.get_logger())
        self.latest_poses = 0  # steps that took the latest pose after pose_timeout_s

    def _subscribe(self) -> None:
        """The protocol's inputs (the robot's: :func:`subscribe_robot_inputs`)."""
        def subscribe(msg_type, topic: str, callback, qos) -> None:
            bounded_subscription(self, msg_type, topic, callback, qos, self.params["max_message_bytes"], self.logger)

        # the subgoal first: where a step's subgoal and its action wait together, the executor takes them in this order
        subscribe(Int64MultiArray, wire.SUBGOAL, self._on_subgoal, STEP_QOS)
        subscribe(Int64MultiArray, wire.ACTION, self._on_action, STEP_QOS)
        if self.params["wait_for_learner"]:
            subscribe(Float64MultiArray, wire.CREDIT, self._on_credit, LATCHED_QOS)

    def start(self) -> None:
        self.waits.clear()

    def stop(self) -> None:
        """A running episode is abandoned (no further step of it is published)."""
        if self.running:
            self.running = False
            self.requests.ended()
            self.get_logger().info(f"episode {self.episodes.episode} abandoned at step t={self.episodes.t}: the node "
                                   f"stopped stepping (deactivated or shut down)")

    def teardown(self) -> None:
        self.episodes.log.close()

    def on_live_parameter(self, name: str, value) -> None:
        if not self.configured:
            return  # read at the next configure
        if name == "goal_tolerance" and not isinstance(self.task, CellVisits):
            self.task.tolerance_m = float(value)
        elif name == "max_steps":
            self.task.max_steps = int(value) or DEFAULT_MAX_STEPS
        elif name == "autostart":
            self.requests.auto = bool(value)

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

    def _on_action(self, msg: Int64MultiArray) -> None:
        try:
            key, actions = wire.read_actions(msg, self.num_actions, 1)
        except wire.ProtocolError as exc:
            self.inputs.reject(wire.ACTION, exc)
            return
        if self.running and key == self.key and self.pending_action is None and actions[0] >= 0:
            self.pending_action = int(actions[0])
            self.episodes.decision_s.append(time.monotonic() - self.stepped_at)
            self.diagnostics.decision(self.episodes.decision_s[-1])
            self._tick()

    def _on_subgoal(self, msg: Int64MultiArray) -> None:
        """A new option's place, chosen at a step of the running episode (published before
        that step's action): the option in force from that step on."""
        try:
            key, chosen = wire.read_subgoals(msg, self.num_subgoals, 1)
        except wire.ProtocolError as exc:
            self.inputs.reject(wire.SUBGOAL, exc)
            return
        if chosen[0] >= 0 and self.running and self.episodes.first_key <= key <= self.key:
            self.option_subgoal = int(chosen[0])
            self._publish_markers()

    def _on_credit(self, msg: Float64MultiArray) -> None:
        try:
            self.credit = int(wire.read_record(msg, wire.CREDIT_FIELDS)["credit_steps"])
        except wire.ProtocolError as exc:
            self.inputs.reject(wire.CREDIT, exc)
            return
        self._tick()

    def _credit_short(self) -> bool:
        """With ``wait_for_learner``: the learner's credit does not cover the next step."""
        return self.params["wait_for_learner"] and self.episodes.env_steps >= (self.credit or 0)

    def _on_start(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """One episode: the next, once the inputs are fresh (with ``autostart``: they run back to back again)."""
        response.success, response.message = self.requests.start(self.params["autostart"], self.running,
                                                                 self.finished, self.episodes.episode)
        return response

    def _on_stop(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """The running episode ends at its next step (truncated); none starts until ``~/start_episode``."""
        response.success, response.message = self.requests.stop(self.running, self.episodes.episode)
        return response

    # -- health ----------------------------------------------------------------------------------------
    def _health(self) -> tuple[int, str, dict[str, str]]:
        """The diagnostics: WARN while a step has waited over 2 s (saying for what), or messages were rejected."""
        places, params = self.inputs.places, self.params
        pose_source = f"tf {params['global_frame']} <- {params['robot_base_frame']}" if self.inputs.pose_frames \
            else f"topic {self.inputs.topics['pose']}"
        values = {"episodes": str(self.episodes.log.done), "successes": str(self.episodes.log.successes),
                  "step_period_s": f"{params['step_period']:g}", "messages_rejected": str(self.inputs.rejections),
                  "places": places.source if places is not None else "none yet", "pose_source": pose_source,
                  "steps_on_the_latest_pose": str(self.latest_poses),
                  "transforms_at_the_latest_time": str(self.inputs.frames.fell_back),
                  "visit_rule": "in the place's cell" if isinstance(self.task, CellVisits) else
                  f"within {self.task.tolerance_m:g} m"}
        if self.finished:
            return OK, f"finished {self.episodes.log.done} episodes", values
        if not self.active:
            return OK, "inactive (managed node: activate to step)", values
        if lasting := self.waits.lasting():
            return WARN, lasting, values
        if self.running and self.pending_action is None and time.monotonic() - self.stepped_at > WAIT_REPORTED_S:
            return WARN, f"waiting for the action of step t={self.episodes.t} on " \
                         f"{self.resolve_topic_name(wire.ACTION)} (is the sub_controller running?)", values
        state = f"episode {self.episodes.episode} step t={self.episodes.t}" if self.running else "between episodes"
        return OK, state, values

    def _watchdog(self) -> None:
        """Re-publish a step whose action, or the learner's credit for the next, has not come
        within ``action_timeout`` (a subscription matched late gets the step and its answers)."""
        if not self.running or not self.active or (self.pending_action is not None and not self._credit_short()):
            return
        waited = time.monotonic() - self.published_at
        if waited >= self.params["action_timeout"]:
            missing = f"credit from the learner on {self.resolve_topic_name(wire.CREDIT)}" \
                if self.pending_action is not None else \
                f"action on {self.resolve_topic_name(wire.ACTION)} (is the sub_controller running?)"
            self.get_logger().warning(f"no {missing} for step t={self.episodes.t} of episode {self.episodes.episode} "
                                      f"after {waited:.1f} s; re-publishing the step")
            self._publish()
            self.published_at = time.monotonic()

    # -- stepping ------------------------------------------------------------------------------------
    def _tick(self) -> None:
        """Start an episode, or take the next step, as soon as what it needs is there."""
        if not self.active or self.finished:
            return
        if self.running:
            self._step_when_due(self._now())
        elif self.requests.wanted:
            self._start_when_ready(self._now())

    def _scene(self, at_ns: int, now: int) -> Scene:
        """The step's :class:`~hdrqn_ros.nodes.robot_scene.Scene` at ``at_ns``; :class:`Waiting` if not yet."""
        scene = scene_at(self.inputs, at_ns, now, self._ns("stale_after_s"), self.waits.pose_waited_s(),
                         self.params["pose_timeout_s"])
        if scene.pose.latest and not (self.scene is not None and self.scene.pose.latest):
            source = "tf" if self.inputs.pose_frames else self.inputs.topics["pose"]
            self.get_logger().info(f"no pose from {source} at the step's time within pose_timeout_s "
                                   f"({self.params['pose_timeout_s']:g} s): stepping on the latest")
        return scene

    def _start_when_ready(self, now: int) -> None:
        if self.params["wait_for_learner"] and self.credit is None:
            return self.waits.wait(f"for a learner on {self.resolve_topic_name(wire.CREDIT)}")
        if self.inputs.places is None:
            why = self.inputs.refused.get("places")
            why = f": the last were refused: {why}" if why else " (a latched geometry_msgs/PoseArray)"
            return self.waits.wait(f"no places yet on {self.inputs.topics['places']}{why}")
        new_layout = self.params["new_layout_each_episode"]
        if new_layout and self.inputs.places_stamp < self.ended_ns:
            return self.waits.wait(f"for the next episode's places on {self.inputs.topics['places']} "
                                   f"(new_layout_each_episode: published after the last episode ended)")
        scene = self._ready_scene(now, now, "to start an episode", self.inputs.places_stamp if new_layout else 0)
        if scene is not None:
            self._start_episode(now, scene)

    def _step_when_due(self, now: int) -> None:
        due = self.step_ns + self._ns("step_period")
        if self.pending_action is None or now < due:
            return  # the action, and the step's time
        if self._credit_short():
            return self.waits.wait(f"for step t={self.episodes.t + 1}: the learner's credit on "
                                   f"{self.resolve_topic_name(wire.CREDIT)} ({self.credit} steps, "
                                   f"{self.episodes.env_steps} taken; none ahead before it hears every topic it records)")
        scene = self._ready_scene(due, now, f"for step t={self.episodes.t + 1}")
        if scene is not None:
            self._advance(now, scene)

    def _ready_scene(self, at_ns: int, now: int, what: str, since_stamp: int = 0) -> Scene | None:
        """The scene at ``at_ns`` once every input is fresh (since ``since_stamp``); else
        ``None``, the wait reported as ``what`` waits for."""
        why = self.inputs.missing(now, self._ns("stale_after_s"), since_stamp)
        if not why:
            try:
                return self._scene(at_ns, now)
            except Waiting as waiting:
                why = str(waiting)
        self.waits.wait(f"{what}: {why}")
        return None

    def _new_key(self, now: int, scene: Scene) -> None:
        self.key = max(now - self.key_origin, self.key + 1)
        # timed from the key: a first step at the previous step's time (keys grow) is 1 ns later
        # than now, and the critic and a lockstep robot time the step from its key
        self.step_ns, self.pending_action, self.scene = self.key + self.key_origin, None, scene
        self.published_at = self.stepped_at = time.monotonic()
        self.waits.new_step()
        self.latest_poses += scene.pose.latest

    def _start_episode(self, now: int, scene: Scene) -> None:
        self.running, self.option_subgoal = True, NO_SUBGOAL
        self.requests.started()
        self._new_key(now, scene)
        self.episodes.start(self.key, scene.goal_xy, (scene.pose.x, scene.pose.y))
        self._publish()

    def _advance(self, now: int, scene: Scene) -> None:
        """The step the pending action led to, judged under the option in force during it."""
        action = self.pending_action
        robot = scene.robot_in(scene.to_costmap)
        on_lethal = self.inputs.on_lethal(self.inputs.costmap.value, robot[:2], self.params["lethal"])
        self._new_key(now, scene)
        outcome = self.episodes.step(self.key, action, scene.goal_xy, (scene.pose.x, scene.pose.y), on_lethal,
                                     self.option_subgoal, self.requests.stop_requested)
        self._publish()
        if outcome["terminated"] or outcome["truncated"]:
            self.running, self.ended_ns = False, now
            self.requests.ended()
            self.episodes.end(outcome["success"])
            if self.params["max_episodes"] and self.episodes.log.done >= self.params["max_episodes"]:
                self.finished = True

    def _publish(self) -> None:
        """The current step's topics, each image drawn from its costmap in the costmap's frame."""
        obs, images = step_images(self.scene, self.task.goal_xy, self.task.uncollected_xy(), self.inputs.costmap.value,
                                  self.inputs.places_costmap, self.view, self.params)
        self.outputs.publish(self.key, self.episodes.record, self.scene, obs, images)
        self._publish_markers()

    def _publish_markers(self) -> None:
        self.outputs.publish_markers(self.key, self.scene, self.task, self.option_subgoal)


def main(argv: list[str] | None = None) -> int:
    return run_node(RobotEnvironmentNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
