"""``robot_environment`` node: the environment node's place on a robot.

On a robot nothing simulates the task, so this node builds, every ``step_period`` seconds
of ROS time (simulated with ``use_sim_time``; from the robot's pose at the step's time),
what the environment node publishes (``docs/topics.md``): ``observation`` (the local
costmap around the robot, drawn as the simulator draws its view, the places still to visit
in their colours), ``subgoal_images`` (the costmap around each place), ``env_step``
(``at_subgoal`` from where the robot is, visits paid by the gridworld's ordered-goal
rules: :class:`~hdrqn_ros.robot.ordered_visits.OrderedVisits`, episode boundaries) and
``pose``. The critic, meta-controller, sub-controller and learner run unchanged, lock-step
as in training: a step waits for the sub-controller's ``action`` on the previous one. What
moves the robot is the controllers' business (``goal_pose`` to Nav2, or ``cmd_vel``).

Frames as REP 105 has them: the robot's pose is tf's ``global_frame`` <- ``robot_base_frame``
(``map <- base_link``) at the step's time (the latest after ``pose_timeout_s``), or a pose
topic's (``pose_topic``: Odometry, PoseStamped or PoseWithCovarianceStamped, in its own
frame). Each costmap is used in its own frame at its own stamp: the robot and the places are
transformed into it, and a north-up view keeps the pose frame's +y up (the map's grid, as the
simulator's); the places (a ``subgoal_table`` YAML or a latched
``geometry_msgs/PoseArray`` on ``subgoal_poses_topic``) may be in any frame of the tree.
Full grids come on ``costmap_topic``, Nav2's ``map_msgs/OccupancyGridUpdate`` s on
``<costmap_topic>_updates`` (``always_send_full_costmap: false``). A place is visited by the
``visit_rule``: within ``goal_tolerance`` (Nav2's ``xy_goal_tolerance``, so a Nav2 arrival
counts) or in the place's cell (the simulator's rule, for sub-drives). Episodes start with
``~/start_episode`` (one each call) and stop with ``~/stop_episode`` (``std_srvs/Trigger``),
or run back to back with ``autostart``; each ends when every place was visited in order or
at ``max_steps``, is logged, and appended to ``episode_log``
(:class:`~hdrqn_ros.robot.episode_log.EpisodeLog`). Every wait (pose, transforms, costmap,
places, the learner, the controllers' action) is a WARN on ``/diagnostics`` naming what is
missing and who would publish it. A managed node (:mod:`hdrqn_ros.nodes.lifecycle`): it
steps only while active.
"""
from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.clock import Clock, ClockType
from rclpy.time import Time
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Int64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.gridworld import GOAL_NAMES
from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.diagnostics import OK, WARN, Diagnostics
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, domain_sizes, odd_cells
from hdrqn_ros.nodes.lifecycle import ManagedNode
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import NodeConfigError, Param
from hdrqn_ros.nodes.place_markers import MARKERS, place_markers
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS, STEP_QOS, keep_last
from hdrqn_ros.nodes.robot_inputs import Frames, RobotInputs, RobotPose, Waiting
from hdrqn_ros.nodes.tf_listener import TfListener
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription, interface_class
from hdrqn_ros.protocol import wire
from hdrqn_ros.robot.episode_log import EpisodeLog
from hdrqn_ros.robot.ordered_visits import OrderedVisits
from hdrqn_ros.robot.transforms import Transform

DEFAULT_MAX_STEPS = 50
"""The domain's step limit (``max_steps`` 0)."""
POLL_S, WATCHDOG_S = 0.02, 0.5
"""Wall seconds between looks at whether a step can be taken (a pose or an action arriving
looks at once), and between looks for a missing action."""
WAIT_REPORTED_S, WAIT_REPEATED_S = 2.0, 10.0
"""A wait is reported once it lasts this long (diagnostics WARN, log), and logged again this often."""
OCCUPANCY_GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
UPDATES_QOS = keep_last(10, transient_local=True)
"""``<costmap>_updates``: Nav2 offers reliable, transient local; a few deep, so none is lost in a burst."""


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
    "visit_rule": Param("tolerance", "the robot is at a place within goal_tolerance, or in the place's cell "
                                     "(cell_size_m square: the simulator's rule)", choices=("tolerance", "cell")),
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
    "wait_for_learner": Param(False, "start the first episode once a learner is heard on learner_credit (a learner "
                                     "that records the episodes gets all of them)"),
}
"""The robot environment's parameters; the live ones take effect at the next step."""


class CellVisits(OrderedVisits):
    """:class:`OrderedVisits` by the simulator's rule: the robot is at a place when it is in
    the place's cell, the square of ``cell_m`` centred on it (axes of the pose's frame)."""

    def __init__(self, n_goals: int, cell_m: float, max_steps: int):
        super().__init__(n_goals, cell_m / 2, max_steps)

    def where(self, robot_xy) -> int:
        off = np.abs(self.goal_xy - np.asarray(robot_xy, dtype=np.float64)).max(axis=1)
        nearest = int(np.argmin(off))
        return nearest if off[nearest] < self.tolerance_m else NO_SUBGOAL


class Scene:
    """What a step is built from: the robot's ``pose``, the places ``goal_xy`` ``(n, 2)`` in
    its frame, and the transforms from that frame into the costmap's (``to_costmap``) and the
    places' images' costmap's (``to_images``) frames."""

    def __init__(self, pose: RobotPose, goal_xy: np.ndarray, to_costmap: Transform, to_images: Transform):
        self.pose, self.goal_xy, self.to_costmap, self.to_images = pose, goal_xy, to_costmap, to_images

    def robot_in(self, to: Transform) -> tuple[float, float, float]:
        """The robot's ``(x, y, yaw)`` in the frame ``to`` maps into."""
        x, y = to.apply((self.pose.x, self.pose.y))
        return float(x), float(y), self.pose.yaw + to.yaw


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
        places = nav.SubgoalTable.load(params["subgoal_table"], self.num_subgoals) if params["subgoal_table"] else None
        from_tf = not params["pose_topic"]
        try:
            self.tf, no_tf = TfListener(self, max_message_bytes=params["max_message_bytes"]), ""
        except ImportError as exc:  # tf2_msgs is not on PyPI: scripts/install builds it
            self.tf, no_tf = None, str(exc)
        if from_tf and self.tf is None:
            raise NodeConfigError(f"the robot pose from tf ({params['global_frame']} <- {params['robot_base_frame']}) "
                                  f"needs tf2_msgs: {no_tf}; or give a pose topic (pose_topic)")
        topics = {"pose": params["pose_topic"], "costmap": params["costmap_topic"],
                  "costmap_updates": params["costmap_topic"] + "_updates", "global": params["global_costmap_topic"],
                  "global_updates": params["global_costmap_topic"] and params["global_costmap_topic"] + "_updates",
                  "places": params["subgoal_poses_topic"], wire.ACTION: wire.ACTION, wire.SUBGOAL: wire.SUBGOAL}
        frames = Frames(self._lookup if self.tf is not None else None, no_tf)
        self.inputs = RobotInputs(self.logger, {kind: self.resolve_topic_name(topic) for kind, topic in topics.items()
                                                if topic}, places, self.num_subgoals, self.view, params["cell_size_m"],
                                  frames, (params["global_frame"], params["robot_base_frame"]) if from_tf else None,
                                  amcl_like=params["pose_type"] == "pose_with_covariance")
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

    def _lookup(self, target: str, source: str, stamp_ns: int | None) -> Transform:
        return self.tf.lookup(target, source, None if stamp_ns is None else Time(nanoseconds=stamp_ns))

    def _reset(self) -> None:
        """No episode yet (the first starts as ``autostart`` says), nothing heard from the learner."""
        self.learner_heard = False
        self.start_requested, self.stop_requested = False, False  # one episode asked for; the running one to end
        self.auto = self.params["autostart"]  # episodes back to back (paused by ~/stop_episode)
        self.running = False
        self.record: dict = {}  # the latest step's env_step fields
        self.scene: Scene | None = None  # the latest step's
        self.key = self.step_ns = 0
        self.ended_ns = -1  # ROS time the last episode ended
        self.episode, self.env_steps, self.episode_return = -1, 0, 0.0
        self.pending_action: int | None = None
        self.published_at = self.stepped_at = time.monotonic()
        self.decision_s: list[float] = []  # this episode's wall seconds from a step to its action
        self.option_subgoal = -1  # the current option's place (the meta-controller's subgoal), for the markers
        self.wait_since: float | None = None  # wall time the current wait began
        self.wait_logged, self.wait_reason = 0.0, ""
        self.pose_wait_since: float | None = None  # wall time the next step began to wait for its pose
        self.latest_poses = 0  # steps that took the latest pose after pose_timeout_s

    def _subscribe(self) -> None:
        params = self.params

        def subscribe(msg_type, topic: str, callback, qos) -> None:
            bounded_subscription(self, msg_type, topic, callback, qos, params["max_message_bytes"], self.logger)

        if params["pose_topic"]:
            subscribe(interface_class(nav.POSE_TYPES[params["pose_type"]]), params["pose_topic"], self._on_pose,
                      DEFAULT_QOS)
        for kind, topic in (("costmap", params["costmap_topic"]), ("global", params["global_costmap_topic"])):
            if not topic:
                continue
            subscribe(OccupancyGrid, topic, lambda msg, kind=kind: self.inputs.take_costmap(msg, self._now(), kind),
                      LATCHED_QOS)
            try:
                update = interface_class(OCCUPANCY_GRID_UPDATE)
            except ImportError as exc:  # map_msgs is not on PyPI: scripts/install builds it
                self.get_logger().warning(f"not reading {topic}_updates: {exc}; Nav2's costmap must then send full "
                                          f"grids (always_send_full_costmap: true)")
                continue
            subscribe(update, topic + "_updates",
                      lambda msg, kind=kind: self.inputs.take_update(msg, self._now(), kind), UPDATES_QOS)
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
        if name == "goal_tolerance" and not isinstance(self.task, CellVisits):
            self.task.tolerance_m = float(value)
        elif name == "max_steps":
            self.task.max_steps = int(value) or DEFAULT_MAX_STEPS
        elif name == "autostart":
            self.auto = bool(value)

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
        """One episode: the next, once the inputs are fresh (with ``autostart``: they run back to back again)."""
        if self.finished or self.running:
            response.success = False
            response.message = "finished: max_episodes reached" if self.finished else \
                f"episode {self.episode} is running: start_episode starts one when none runs"
            return response
        self.start_requested, self.stop_requested, self.auto = True, False, self.params["autostart"]
        response.success = True
        response.message = f"episode {self.episode + 1} starts when the inputs are fresh" + \
            (" (autostart: then back to back)" if self.auto else "")
        return response

    def _on_stop(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """The running episode ends at its next step (truncated); none starts until ``~/start_episode``."""
        response.success = True
        response.message = f"episode {self.episode} ends at the next step" if self.running else "no episode running"
        self.start_requested, self.auto, self.stop_requested = False, False, self.running
        return response

    # -- health ----------------------------------------------------------------------------------------
    def _health(self) -> tuple[int, str, dict[str, str]]:
        """The diagnostics: WARN while a step has waited over 2 s (saying for what), or messages were rejected."""
        places, params = self.inputs.places, self.params
        pose_source = f"tf {params['global_frame']} <- {params['robot_base_frame']}" if self.inputs.pose_frames \
            else f"topic {self.inputs.topics['pose']}"
        values = {"episodes": str(self.episodes.done), "successes": str(self.episodes.successes),
                  "step_period_s": f"{params['step_period']:g}", "messages_rejected": str(self.inputs.rejections),
                  "places": places.source if places is not None else "none yet", "pose_source": pose_source,
                  "steps_on_the_latest_pose": str(self.latest_poses),
                  "transforms_at_the_latest_time": str(self.inputs.frames.fell_back),
                  "visit_rule": "in the place's cell" if isinstance(self.task, CellVisits) else
                  f"within {self.task.tolerance_m:g} m"}
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
        elif self.start_requested or self.auto:
            self._start_when_ready(self._now())

    def _scene(self, at_ns: int, now: int) -> Scene:
        """The robot at ``at_ns`` and the places and costmaps in its frame; :class:`Waiting` if not yet."""
        inputs, params = self.inputs, self.params
        if self.pose_wait_since is None:
            self.pose_wait_since = time.monotonic()
        pose = inputs.pose_at(at_ns, now, self._ns("stale_after_s"), time.monotonic() - self.pose_wait_since,
                              params["pose_timeout_s"])
        places, frames = inputs.places, inputs.frames
        to_pose = frames.transform(pose.frame, places.frame_id, pose.stamp_ns,
                                   f"the places ({places.source}, frame {places.frame_id!r})")
        goal_xy = to_pose.apply(np.array([p[:2] for p in places.poses]))
        into = {}
        for kind, grid in (("costmap", inputs.costmap.value), ("global", inputs.places_costmap)):
            topic = inputs.topics.get(kind if inputs.global_costmap.value is not None else "costmap")
            into[kind] = frames.transform(grid.frame_id, pose.frame, grid.stamp_ns,
                                          f"the costmap on {topic} (frame {grid.frame_id!r})")
        if pose.latest and not (self.scene is not None and self.scene.pose.latest):
            source = "tf" if inputs.pose_frames else inputs.topics["pose"]
            self.get_logger().info(f"no pose from {source} at the step's time within pose_timeout_s "
                                   f"({params['pose_timeout_s']:g} s): stepping on the latest")
        return Scene(pose, goal_xy, into["costmap"], into["global"])

    def _start_when_ready(self, now: int) -> None:
        if self.params["wait_for_learner"] and not self.learner_heard:
            return self._wait(f"for a learner on {self.resolve_topic_name(wire.CREDIT)}")
        if self.inputs.places is None:
            why = self.inputs.refused.get("places")
            return self._wait(f"no places yet on {self.inputs.topics['places']}" +
                              (f": the last were refused: {why}" if why else " (a latched geometry_msgs/PoseArray)"))
        new_layout = self.params["new_layout_each_episode"]
        if new_layout and self.inputs.places_stamp < self.ended_ns:
            return self._wait(f"for the next episode's places on {self.inputs.topics['places']} (new_layout_each_"
                              f"episode: published after the last episode ended)")
        if why := self.inputs.missing(now, self._ns("stale_after_s"), self.inputs.places_stamp if new_layout else 0):
            return self._wait(f"to start an episode: {why}")
        try:
            scene = self._scene(now, now)
        except Waiting as why:
            return self._wait(f"to start an episode: {why}")
        self._start_episode(now, scene)

    def _step_when_due(self, now: int) -> None:
        due = self.step_ns + self._ns("step_period")
        if self.pending_action is None or now < due:
            return  # the action, and the step's time
        if why := self.inputs.missing(now, self._ns("stale_after_s")):
            return self._wait(f"for step t={int(self.record['t']) + 1}: {why}")
        try:
            scene = self._scene(due, now)
        except Waiting as why:
            return self._wait(f"for step t={int(self.record['t']) + 1}: {why}")
        self._advance(now, scene)

    def _new_key(self, now: int, scene: Scene) -> None:
        self.key = max(now - self.key_origin, self.key + 1)
        self.step_ns, self.pending_action, self.scene = now, None, scene
        self.published_at = self.stepped_at = time.monotonic()
        self.wait_since = self.pose_wait_since = None
        self.latest_poses += scene.pose.latest

    def _start_episode(self, now: int, scene: Scene) -> None:
        self.episode += 1
        self.start_requested = False
        self.task.start(scene.goal_xy)
        self.running, self.episode_return, self.decision_s, self.option_subgoal = True, 0.0, [], -1
        self._new_key(now, scene)
        self.record = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        self.record.update(key=self.key, prev_key=0, env_steps=self.env_steps, episode=self.episode,
                           at_subgoal=self.task.where((scene.pose.x, scene.pose.y)), decision_point=1)
        self._publish()

    def _advance(self, now: int, scene: Scene) -> None:
        prev_key, action = self.key, self.pending_action
        self.task.goal_xy = scene.goal_xy  # the places in the pose's frame now (a frame of their own may move)
        robot = scene.robot_in(scene.to_costmap)
        outcome = self.task.step((scene.pose.x, scene.pose.y),
                                 self.inputs.on_lethal(self.inputs.costmap.value, robot[:2], self.params["lethal"]))
        if self.stop_requested and not outcome["terminated"]:
            outcome.update(truncated=True, decision_point=False)
        self.env_steps += 1
        self._new_key(now, scene)
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
        """The current step: ``env_step``, ``observation``, ``subgoal_images``, ``pose`` and the markers,
        each image drawn from its costmap in the costmap's frame."""
        key, params, inputs, scene = self.key, self.params, self.inputs, self.scene
        grid, images_grid = inputs.costmap.value, inputs.places_costmap

        def drawn(to: Transform) -> tuple[tuple[float, float], dict]:
            """The robot's (x, y) and the drawing's settings in the frame ``to`` maps into;
            image up: the robot's heading, or (north-up) the pose frame's +y."""
            x, y, yaw = scene.robot_in(to)
            goals = [None if xy is None else tuple(to.apply(xy)) for xy in self.task.uncollected_xy()]
            up = yaw if params["heading_up"] else (None if to.yaw == 0.0 else math.pi / 2 + to.yaw)
            return (x, y), {"view_cells": self.view, "cell_size_m": params["cell_size_m"], "lethal": params["lethal"],
                            "robot_yaw": up, "unknown": params["unknown_cells"], "goals_xy": goals}

        robot_xy, style = drawn(scene.to_costmap)
        obs = nav.costmap_to_observation(grid, robot_xy=robot_xy, **style)
        robot_xy, style = drawn(scene.to_images)
        images = np.concatenate([nav.costmap_to_observation(images_grid, robot_xy=scene.to_images.apply(xy),
                                                            agent_xy=robot_xy, **style) for xy in self.task.goal_xy])
        self.pub_step.publish(wire.make_record(ROS_MESSAGES, wire.FLOATS, wire.STEP_FIELDS,
                                               [self.record[f] for f in wire.STEP_FIELDS]))
        # the images' frame: the one whose axes a north-up view keeps (a motion primitive's moves are in it)
        self.pub_obs.publish(wire.make_image(ROS_MESSAGES, key, obs, scene.pose.frame))
        self.pub_images.publish(wire.make_image(ROS_MESSAGES, key, images, scene.pose.frame))
        self.pub_pose.publish(wire.make_pose(ROS_MESSAGES, key, scene.pose.frame, scene.pose.x, scene.pose.y))
        self._publish_markers()

    def _publish_markers(self) -> None:
        scene = self.scene
        header = wire.make_header(ROS_MESSAGES, self.key, scene.pose.frame)
        self.pub_markers.publish(place_markers(header, self.task.goal_xy, self.task.collected, self.option_subgoal,
                                               (scene.pose.x, scene.pose.y)))


def main(argv: list[str] | None = None) -> int:
    return run_node(RobotEnvironmentNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
