"""``robot_environment`` node: the environment node's place on a robot.

On a robot nothing simulates the task, so this node builds, every ``step_period`` seconds
of ROS time (simulated with ``use_sim_time``; from a pose stamped at or after the step's
time), what the environment node publishes
(``docs/topics.md``): ``observation`` (the local costmap around the robot, drawn as the
simulator draws its view, the places still to visit in their colours), ``subgoal_images``
(the costmap around each place), ``env_step`` (``at_subgoal`` from the robot's distance to
each place, visits paid by the gridworld's ordered-goal rules:
:class:`~hdrqn_ros.robot.ordered_visits.OrderedVisits`, episode boundaries) and ``pose``.
The critic, meta-controller, sub-controller and learner run unchanged, lock-step as in
training: a step waits for the sub-controller's ``action`` on the previous one. What moves
the robot is the controllers' business (``goal_pose`` to Nav2, or ``cmd_vel``).

Inputs: the robot pose (``pose_topic``: Odometry, PoseStamped or PoseWithCovarianceStamped),
the local costmap (``costmap_topic``), optionally a global costmap for the places' images,
and the places: a ``subgoal_table`` YAML or a latched ``geometry_msgs/PoseArray`` on
``subgoal_poses_topic`` (a loopback robot publishes each episode's layout there). Every
input must be in the places' frame (there is no tf2 here). Episodes start and stop with
``~/start_episode`` and ``~/stop_episode`` (``std_srvs/Trigger``, rclpy) or one after the
other with ``autostart``; each ends when every place was visited in order or at
``max_steps``. Each finished episode is logged, and appended to ``episode_log`` (JSON lines:
``episode``, ``success``, ``steps``, ``visits`` (place indices in visit order), ``return``,
``decision_ms``: the median wall time from a step's publication to its action's arrival,
critic, meta-controller and sub-controller on the way, and ``success_rate`` so far).
"""
from __future__ import annotations

import json
import math
import time

import numpy as np

from hdrqn_ros.middleware import LATCHED_QOS, BackendError, Middleware, ParameterRule
from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.common import (ENV_DEFAULTS, ENV_RULES, NodeConfigError, check_algo, domain_sizes,
                                    live_parameters, run_node)
from hdrqn_ros.nodes.diagnostics import OK, WARN, Diagnostics
from hdrqn_ros.nodes.ros_time import RosTime
from hdrqn_ros.protocol import wire
from hdrqn_ros.robot.ordered_visits import OrderedVisits
from hdrqn_ros.throttle import Throttle

PARAMETERS = {**ENV_DEFAULTS, "use_sim_time": False, "step_period": 2.5, "pose_topic": "/odom",
              "pose_type": "odometry", "costmap_topic": "/local_costmap/costmap", "global_costmap_topic": "",
              "subgoal_table": "", "subgoal_poses_topic": "", "new_layout_each_episode": False,
              "goal_tolerance": 0.125, "max_steps": 0, "cell_size_m": 0.25, "heading_up": False,
              "lethal": nav.LETHAL, "unknown_cells": "outside", "stale_after_s": 5.0, "action_timeout": 5.0,
              "autostart": True, "max_episodes": 0, "episode_log": "", "wait_for_learner": False}
"""``step_period``: seconds (ROS time) per agent step; ``goal_tolerance``: metres within
which the robot is at a place; ``max_steps``: step limit (0: the domain's, 50);
``cell_size_m``: metres per simulator cell in the observation; ``heading_up``: observation
turned with the robot's yaw (forward/turn action tables) instead of north-up;
``unknown_cells``: ``outside`` (black, as beyond the simulator's map) or ``wall``;
``stale_after_s``: a pose or costmap older than this (ROS time since it arrived) holds the
next step; ``action_timeout``: wall seconds before a missing action is reported and the
step re-published; ``new_layout_each_episode``: start an episode only on places published
after the last one ended; ``max_episodes``: stop after this many (0: never);
``wait_for_learner``: start the first episode only once a learner is heard (its
``learner_credit``): a learner that records the episodes gets all of them."""

RULES = {
    **ENV_RULES,
    "step_period": ParameterRule("seconds (ROS time) per agent step", live=True, positive=True),
    "pose_topic": ParameterRule("the robot's pose (e.g. /odom, /amcl_pose)"),
    "pose_type": ParameterRule("the pose topic's type", choices=tuple(nav.POSE_TYPES)),
    "costmap_topic": ParameterRule("the observation's costmap (nav_msgs/OccupancyGrid)"),
    "global_costmap_topic": ParameterRule("the places' images' costmap ('': the local one)"),
    "subgoal_table": ParameterRule("the places as a YAML table (this or subgoal_poses_topic)"),
    "subgoal_poses_topic": ParameterRule("the places as a latched geometry_msgs/PoseArray"),
    "new_layout_each_episode": ParameterRule("start an episode only on places published since the last one ended"),
    "goal_tolerance": ParameterRule("metres within which the robot is at a place", live=True, positive=True),
    "max_steps": ParameterRule("an episode's step limit (0: the domain's, 50)", live=True, low=0, high=100000),
    "cell_size_m": ParameterRule("metres per simulator cell in the observation", positive=True),
    "heading_up": ParameterRule("observation turned with the robot's yaw instead of north-up"),
    "lethal": ParameterRule("costmap cost drawn as wall (and reported as hit_obstacle under the robot)", live=True,
                            low=1, high=100),
    "unknown_cells": ParameterRule("unknown costmap cells drawn black (outside) or as wall",
                                   choices=("outside", "wall")),
    "stale_after_s": ParameterRule("a pose or costmap older than this (ROS time) holds the next step", live=True,
                                   positive=True),
    "action_timeout": ParameterRule("wall seconds without an action before a warning and a re-published step",
                                    live=True, positive=True),
    "autostart": ParameterRule("start the next episode as soon as one ends (false: on ~/start_episode)", live=True),
    "max_episodes": ParameterRule("exit after this many episodes (0: never)", live=True, low=0, high=2**31),
    "episode_log": ParameterRule("append each finished episode to this JSON-lines file ('': off)"),
    "wait_for_learner": ParameterRule("start the first episode once a learner is heard (one that records them all)"),
}
"""Descriptions and rules of :data:`PARAMETERS`; the live ones take effect at the next step."""

MARKERS = "subgoal_markers"
"""``visualization_msgs/MarkerArray`` of the places, the current option's highlighted."""
MARKER_ARRAY, MARKER = "visualization_msgs/msg/MarkerArray", "visualization_msgs/msg/Marker"
CYLINDER, TEXT, ADD = 3, 9, 0
"""``visualization_msgs/Marker`` type and action constants."""


def _pose_msg(msg, x: float, y: float, z: float):
    return msg("geometry_msgs/msg/Pose")(position=msg("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=float(z)),
                                         orientation=msg("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0))


class RobotEnvironmentNode:
    active = True
    """Stepping (a managed node steps only while active: :mod:`hdrqn_ros.nodes.managed`)."""

    def __init__(self, mw: Middleware):
        node = self.node = mw.create_node("robot_environment")
        params = self.params = node.declare_parameters(PARAMETERS, rules=RULES)
        check_algo(params["algo"])
        self.num_actions, self.num_subgoals = domain_sizes(params["env"], params["view"])
        if not params["view"].isdigit():
            raise NodeConfigError(f"the robot's observation needs a numeric view (cells), got {params['view']!r}")
        self.view = int(params["view"])
        for name in ("step_period", "goal_tolerance", "cell_size_m", "stale_after_s", "action_timeout"):
            if not (math.isfinite(params[name]) and params[name] > 0):
                raise NodeConfigError(f"{name} must be a positive number, got {params[name]!r}")
        if params["pose_type"] not in nav.POSE_TYPES:
            raise NodeConfigError(f"pose_type must be one of {sorted(nav.POSE_TYPES)}, got {params['pose_type']!r}")
        if params["unknown_cells"] not in ("outside", "wall"):
            raise NodeConfigError(f"unknown_cells must be 'outside' or 'wall', got {params['unknown_cells']!r}")
        if bool(params["subgoal_table"]) == bool(params["subgoal_poses_topic"]):
            raise NodeConfigError("give the places either as subgoal_table (a YAML file) or as subgoal_poses_topic "
                                  "(a latched geometry_msgs/PoseArray), exactly one")
        self.task = OrderedVisits(self.num_subgoals, params["goal_tolerance"], params["max_steps"] or 50)
        for name in ("step_period", "stale_after_s"):
            self._apply(name, params[name])
        live_parameters(node, params, RULES, self._apply)
        self.places: nav.SubgoalTable | None = None
        self.places_stamp = 0  # header stamp (ns) of the places (a table: 0)
        if params["subgoal_table"]:
            self.places = nav.SubgoalTable.load(params["subgoal_table"], self.num_subgoals)
        else:
            node.create_subscription(nav.POSE_ARRAY, params["subgoal_poses_topic"], self._on_places, LATCHED_QOS)
        self.clock = RosTime(node, params["use_sim_time"], on_clock=self._tick)
        self.key_origin = 0 if self.clock.use_sim_time else time.time_ns() - 10**9
        self.pose: tuple[float, float, float] | None = None
        self.pose_ns = self.costmap_ns = -1  # ROS time each input last arrived
        self.pose_stamp = self.costmap_stamp = -1  # and its header stamp (ns)
        self.costmap = self.global_costmap = None
        node.create_subscription(nav.POSE_TYPES[params["pose_type"]], params["pose_topic"], self._on_pose)
        node.create_subscription(nav.OCCUPANCY_GRID, params["costmap_topic"], self._on_costmap, LATCHED_QOS)
        if params["global_costmap_topic"]:
            node.create_subscription(nav.OCCUPANCY_GRID, params["global_costmap_topic"],
                                     self._on_global_costmap, LATCHED_QOS)
        self.pub_obs = node.create_publisher(wire.IMAGE, wire.OBSERVATION, wire.STEP_QOS)
        self.pub_images = node.create_publisher(wire.IMAGE, wire.SUBGOAL_IMAGES, wire.STEP_QOS)
        self.pub_step = node.create_publisher(wire.FLOATS, wire.ENV_STEP, wire.STEP_QOS)
        self.pub_pose = node.create_publisher(wire.POSE_STAMPED, wire.POSE)
        node.create_subscription(wire.INTS, wire.ACTION, self._on_action, wire.STEP_QOS)
        self.start_requested, self.stop_requested = params["autostart"], False
        try:
            node.create_service("std_srvs/srv/Trigger", "~/start_episode", self._on_start)
            node.create_service("std_srvs/srv/Trigger", "~/stop_episode", self._on_stop)
        except BackendError as exc:
            if not params["autostart"]:
                raise NodeConfigError(f"autostart is false, so episodes start on request, but {exc}") from None
            node.logger.info("no start/stop services (%s); episodes start one after the other", exc)
        self.rejected = {name: Throttle(node.logger, f"rejected a message on {node.resolve_topic(topic)}")
                         for name, topic in (("pose", params["pose_topic"]), ("costmap", params["costmap_topic"]),
                                             ("global", params["global_costmap_topic"]),
                                             ("places", params["subgoal_poses_topic"]), (wire.ACTION, wire.ACTION),
                                             (wire.SUBGOAL, wire.SUBGOAL))
                         if topic}
        self.wait_since: float | None = None  # wall time the current wait began
        self.wait_logged = 0.0
        self.running = False
        self.finished = False
        self.record: dict = {}
        self.key = self.step_ns = 0
        self.ended_ns = -1  # ROS time the last episode ended
        self.episode, self.env_steps, self.episodes_done, self.successes = -1, 0, 0, 0
        self.episode_return = 0.0
        self.pending_action: int | None = None
        self.published_at = self.stepped_at = time.monotonic()
        self.decision_s: list[float] = []  # this episode's wall seconds from a step to its action
        self.episode_log = open(params["episode_log"], "a", buffering=1) if params["episode_log"] else None
        self.option_subgoal = -1  # the current option's place (the meta-controller's subgoal), for the markers
        node.create_subscription(wire.INTS, wire.SUBGOAL, self._on_subgoal, wire.STEP_QOS)
        self.learner_heard = False
        if params["wait_for_learner"]:
            node.create_subscription(wire.FLOATS, wire.CREDIT, lambda _: setattr(self, "learner_heard", True),
                                     LATCHED_QOS)
        self.pub_markers = node.create_publisher(MARKER_ARRAY, MARKERS)
        self.wait_reason = ""
        self.diagnostics = Diagnostics(node, self._health)
        node.create_timer(0.02, self._tick)
        node.create_timer(0.5, self._watchdog)

    def _apply(self, name: str, value) -> None:
        """A live parameter's derived value (at start, and on ``ros2 param set``)."""
        if name == "step_period":
            self.period_ns = int(round(value * 1e9))
        elif name == "stale_after_s":
            self.stale_ns = int(round(value * 1e9))
        elif name == "goal_tolerance":
            self.task.tolerance_m = float(value)
        elif name == "max_steps":
            self.task.max_steps = int(value) or 50
        elif name == "autostart" and value:
            self.start_requested = True

    # -- inputs ------------------------------------------------------------------------------
    def _check_frame(self, frame_id: str, what: str) -> None:
        if self.places is not None and frame_id != self.places.frame_id:
            raise nav.NavConfigError(f"{what} is in frame {frame_id!r} but the places are in {self.places.frame_id!r} "
                                     f"({self.places.source}); publish both in one frame (no tf2 here)")

    def _on_pose(self, msg) -> None:
        try:
            pose = nav.robot_pose(msg)
            self._check_frame(msg.header.frame_id, "the robot pose")
        except nav.NavConfigError as exc:
            self.rejected["pose"].warn(exc)
            return
        self.pose, self.pose_ns, self.pose_stamp = pose, self.clock.now_ns() or 0, wire.key_of(msg.header.stamp)

    def _check_costmap(self, msg, what: str) -> None:
        self._check_frame(msg.header.frame_id, what)
        info = msg.info
        side = min(int(info.width), int(info.height)) * float(info.resolution)
        need = self.view * self.params["cell_size_m"]
        if side < need:
            raise nav.NavConfigError(f"{what} covers {side:.2f} m, less than the view's {self.view} cells of "
                                     f"{self.params['cell_size_m']} m ({need:.2f} m)")
        nav.costmap_to_observation(msg, view_cells=self.view, cell_size_m=self.params["cell_size_m"])  # size checks

    def _usable_costmap(self, msg, which: str) -> bool:
        """``msg`` can be drawn from (else the rejection is logged); ``which``: costmap or global."""
        try:
            self._check_costmap(msg, "the costmap" if which == "costmap" else "the global costmap")
        except (nav.NavConfigError, ValueError) as exc:
            self.rejected[which].warn(exc)
            return False
        return True

    def _on_costmap(self, msg) -> None:
        if self._usable_costmap(msg, "costmap"):
            self.costmap, self.costmap_ns = msg, self.clock.now_ns() or 0
            self.costmap_stamp = wire.key_of(msg.header.stamp)

    def _on_global_costmap(self, msg) -> None:
        if self._usable_costmap(msg, "global"):
            self.global_costmap = msg

    def _on_places(self, msg) -> None:
        try:
            places = nav.SubgoalTable.from_pose_array(msg, self.num_subgoals,
                                                      self.node.resolve_topic(self.params["subgoal_poses_topic"]))
        except nav.NavConfigError as exc:
            self.rejected["places"].warn(exc)
            return
        self.places, self.places_stamp = places, wire.key_of(msg.header.stamp)

    def _on_action(self, msg) -> None:
        try:
            key, actions = wire.read_actions(msg, self.num_actions, 1)
        except wire.ProtocolError as exc:
            self.rejected[wire.ACTION].warn(exc)
            return
        if self.running and key == self.key and self.pending_action is None and actions[0] >= 0:
            self.pending_action = int(actions[0])
            self.decision_s.append(time.monotonic() - self.stepped_at)
            self.diagnostics.decision(self.decision_s[-1])
            self._tick()

    def _on_subgoal(self, msg) -> None:
        try:
            _, chosen = wire.read_subgoals(msg, self.num_subgoals, 1)
        except wire.ProtocolError as exc:
            self.rejected[wire.SUBGOAL].warn(exc)
            return
        if chosen[0] >= 0:
            self.option_subgoal = int(chosen[0])
            if self.running:
                self._publish_markers()

    def _health(self) -> tuple[int, str, dict[str, str]]:
        """The diagnostics: WARN while a step has waited over 2 s (saying for what), or messages were rejected."""
        rejected = sum(throttle.count for throttle in self.rejected.values())
        values = {"episodes": str(self.episodes_done), "successes": str(self.successes),
                  "step_period_s": f"{self.params['step_period']:g}", "messages_rejected": str(rejected),
                  "places": self.places.source if self.places is not None else "none yet"}
        if self.finished:
            return OK, f"finished {self.episodes_done} episodes", values
        if not self.active:
            return OK, "inactive (managed node: activate to step)", values
        waited = 0.0 if self.wait_since is None else time.monotonic() - self.wait_since
        if waited > 2.0:
            return WARN, f"waiting {waited:.0f} s {self.wait_reason}", values
        if self.running and self.pending_action is None and time.monotonic() - self.stepped_at > 2.0:
            return WARN, f"waiting for the action of step t={int(self.record['t'])} on " \
                         f"{self.node.resolve_topic(wire.ACTION)} (is the sub_controller running?)", values
        state = f"episode {self.episode} step t={int(self.record['t'])}" if self.running else "between episodes"
        return OK, state, values

    def _publish_markers(self) -> None:
        """The places as RViz / Foxglove markers: a disc per place in its goal colour (faint once
        visited), the current option's place tall, with its name above it."""
        msg, key, frame = self.node.msg, self.key, self.places.frame_id
        header = wire.make_header(self.node, key, frame)
        markers = []
        for g, (x, y) in enumerate(self.task.goal_xy):
            current = g == self.option_subgoal
            red, green, blue = (int(c) / 255 for c in nav.PALETTE[nav.GOAL0 + g])
            alpha = 0.25 if self.task.collected[g] else 0.9
            height = 0.4 if current else 0.05
            markers.append(msg(MARKER)(
                header=header, ns="hdrqn_places", id=g, type=CYLINDER, action=ADD,
                pose=_pose_msg(msg, x, y, height / 2),
                scale=msg("geometry_msgs/msg/Vector3")(x=0.2, y=0.2, z=height),
                color=msg("std_msgs/msg/ColorRGBA")(r=red, g=green, b=blue, a=alpha)))
        label = nav.GOAL_NAMES[self.option_subgoal] if 0 <= self.option_subgoal < len(nav.GOAL_NAMES) else "none"
        x, y = self.task.goal_xy[self.option_subgoal] if self.option_subgoal >= 0 else self.pose[:2]
        markers.append(msg(MARKER)(
            header=header, ns="hdrqn_subgoal", id=0, type=TEXT, action=ADD, pose=_pose_msg(msg, x, y, 0.6),
            scale=msg("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.15),
            color=msg("std_msgs/msg/ColorRGBA")(r=0.0, g=0.0, b=0.0, a=1.0), text=f"subgoal: {label}"))
        self.pub_markers.publish(msg(MARKER_ARRAY)(markers=markers))

    def _on_start(self, _request, response):
        response.success = not self.finished
        response.message = "finished: max_episodes reached" if self.finished else \
            ("an episode is running" if self.running else "the next episode starts when the inputs are fresh")
        self.start_requested, self.stop_requested = not self.finished, False
        return response

    def _on_stop(self, _request, response):
        response.success = True
        response.message = f"episode {self.episode} ends at the next step" if self.running else "no episode running"
        self.start_requested, self.stop_requested = False, self.running
        return response

    # -- stepping ------------------------------------------------------------------------------
    def _inputs_missing(self, now: int, since_stamp: int) -> str:
        """Why no step can be built at ``now`` from inputs stamped at or after ``since_stamp`` ('' if it can)."""
        params = self.params
        for what, topic, arrived, stamp in (("pose", params["pose_topic"], self.pose_ns, self.pose_stamp),
                                            ("costmap", params["costmap_topic"], self.costmap_ns, self.costmap_stamp)):
            name = self.node.resolve_topic(topic)
            if arrived < 0:
                return f"no {what} on {name} yet"
            if now - arrived > self.stale_ns:
                return f"the {what} on {name} is {(now - arrived) / 1e9:.1f} s old (stale_after_s {params['stale_after_s']})"
            if stamp < since_stamp:
                return f"a {what} on {name} stamped after the places"
        return ""

    def _wait(self, why: str) -> None:
        """Report a wait that lasts (after 2 s, then every 10 s), not a momentary one."""
        now = time.monotonic()
        self.wait_reason = why
        if self.wait_since is None:
            self.wait_since = now
        elif now - self.wait_since >= 2.0 and now - self.wait_logged >= 10.0:
            self.wait_logged = now
            self.node.logger.warning("waiting %.0f s %s", now - self.wait_since, why)

    def activate(self) -> None:
        self.wait_since = None
        self.active = True

    def deactivate(self) -> None:
        """Stop stepping; a running episode is abandoned (no further step of it is published)."""
        self.active = False
        if self.running:
            self.running, self.stop_requested = False, False
            self.node.logger.info("episode %d abandoned at step t=%d: the node was deactivated", self.episode,
                                  int(self.record["t"]))

    def _tick(self) -> None:
        now = self.clock.now_ns()
        if now is None or self.finished or not self.active:
            return
        if not self.running:
            if not self.start_requested:
                return
            if self.params["wait_for_learner"] and not self.learner_heard:
                return self._wait(f"for a learner on {self.node.resolve_topic(wire.CREDIT)}")
            if self.places is None:
                return self._wait(f"no places yet on {self.node.resolve_topic(self.params['subgoal_poses_topic'])}")
            new_layout = self.params["new_layout_each_episode"]
            if new_layout and self.places_stamp < self.ended_ns:
                return
            if why := self._inputs_missing(now, self.places_stamp if new_layout else 0):
                return self._wait(f"to start an episode: {why}")
            return self._start_episode(now)
        due = self.step_ns + self.period_ns
        if self.pending_action is None or now < due or self.pose_stamp < due:
            return  # the action, the step's time, and a pose measured at or after it
        if why := self._inputs_missing(now, 0):
            return self._wait(f"for step t={int(self.record['t']) + 1}: {why}")
        self._advance(now)

    def _new_key(self, now: int) -> None:
        """Step keys are ROS time in ns: simulated time as it is, wall time since the node
        started (keys stay below 2^53, exact in the float64 records)."""
        self.key = max(now - self.key_origin, self.key + 1)
        self.step_ns, self.pending_action = now, None
        self.published_at = self.stepped_at = time.monotonic()
        self.wait_since = None

    def _start_episode(self, now: int) -> None:
        self.episode += 1
        self.task.start(np.array([pose[:2] for pose in self.places.poses]))
        self.running, self.episode_return, self.decision_s, self.option_subgoal = True, 0.0, [], -1
        self._new_key(now)
        self.record = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        self.record.update(key=self.key, prev_key=0, env_steps=self.env_steps, episode=self.episode,
                           at_subgoal=self.task.where(self.pose[:2]), decision_point=1)
        self._publish()

    def _on_lethal(self) -> bool:
        """The robot's costmap cell is at or above ``lethal``."""
        info, (x, y, _) = self.costmap.info, self.pose
        col = math.floor((x - info.origin.position.x) / info.resolution)
        row = math.floor((y - info.origin.position.y) / info.resolution)
        if not (0 <= col < info.width and 0 <= row < info.height):
            return False
        return int(np.asarray(self.costmap.data, np.int8)[row * info.width + col]) >= self.params["lethal"]

    def _advance(self, now: int) -> None:
        prev_key, action = self.key, self.pending_action
        outcome = self.task.step(self.pose[:2], self._on_lethal())
        if self.stop_requested and not outcome["terminated"]:
            outcome.update(truncated=True, decision_point=False)
        self.env_steps += 1
        self._new_key(now)
        self.record = {"key": self.key, "prev_key": prev_key, "env_steps": self.env_steps, "episode": self.episode,
                       "t": self.task.t, "action": action, **outcome}
        self.episode_return += outcome["extrinsic"]
        self._publish()
        if outcome["terminated"] or outcome["truncated"]:
            self._end_episode(now, outcome)

    def _end_episode(self, now: int, outcome: dict) -> None:
        self.running, self.stop_requested, self.ended_ns = False, False, now
        self.episodes_done += 1
        self.successes += outcome["success"]
        names = [nav.GOAL_NAMES[g] if g < len(nav.GOAL_NAMES) else str(g) for g in self.task.visits]
        row = {"episode": self.episode, "success": bool(outcome["success"]), "steps": self.task.t,
               "visits": self.task.visits, "return": round(self.episode_return, 4),
               "decision_ms": round(1e3 * float(np.median(self.decision_s)), 3) if self.decision_s else 0.0,
               "success_rate": self.successes / self.episodes_done}
        self.node.logger.info("episode %d: visited %s in %d steps, %s (success %d of %d)", self.episode,
                              ", ".join(names) or "nothing", self.task.t,
                              "in order" if outcome["success"] else "not in order", self.successes,
                              self.episodes_done)
        if self.episode_log is not None:
            self.episode_log.write(json.dumps(row) + "\n")
        if self.params["max_episodes"] and self.episodes_done >= self.params["max_episodes"]:
            self.finished = True

    def _publish(self) -> None:
        node, key, frame = self.node, self.key, self.places.frame_id
        x, y, yaw = self.pose
        params = self.params
        view = {"view_cells": self.view, "cell_size_m": params["cell_size_m"], "lethal": params["lethal"],
                "robot_yaw": yaw if params["heading_up"] else None, "unknown": params["unknown_cells"],
                "goals_xy": self.task.uncollected_xy()}
        obs = nav.costmap_to_observation(self.costmap, robot_xy=(x, y), **view)
        around = self.global_costmap or self.costmap
        images = np.concatenate([nav.costmap_to_observation(around, robot_xy=xy, agent_xy=(x, y), **view)
                                 for xy in self.task.goal_xy])
        self.pub_step.publish(wire.make_record(node, wire.FLOATS, wire.STEP_FIELDS,
                                               [self.record[f] for f in wire.STEP_FIELDS]))
        self.pub_obs.publish(wire.make_image(node, key, obs, frame))
        self.pub_images.publish(wire.make_image(node, key, images, frame))
        self.pub_pose.publish(wire.make_pose(node, key, frame, x, y))
        self._publish_markers()

    def _watchdog(self) -> None:
        if not self.running or self.pending_action is not None or not self.active:
            return
        waited = time.monotonic() - self.published_at
        if waited >= self.params["action_timeout"]:
            self.node.logger.warning("no action for step t=%d of episode %d after %.1f s on %s (is the "
                                     "sub_controller running?); re-publishing the step", int(self.record["t"]),
                                     self.episode, waited, self.node.resolve_topic(wire.ACTION))
            self._publish()
            self.published_at = time.monotonic()

    def close(self) -> None:
        if self.episode_log is not None:
            self.episode_log.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: RobotEnvironmentNode(mw), argv, (nav.NavConfigError,),
                    managed_name="robot_environment")


if __name__ == "__main__":
    raise SystemExit(main())
