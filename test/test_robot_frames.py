"""The robot environment on a robot that speaks Nav2 as Nav2 ships (issue 38, items 1, 4, 5, 7),
as a real node process beside the test's own node playing the robot and the sub-controller:

- frames the REP 105 way: the pose from tf (``map -> odom`` non-identity on ``/tf``, a static
  ``base_footprint -> base_link`` on ``/tf_static``), the local costmap in ``odom``, the places
  in ``map``: episodes run, the observation shows the places where they are, and a robot that
  stops 0.2 m short of each place (Nav2's ``xy_goal_tolerance`` is 0.25 m) visits it;
- a frame missing from the tree is a WARN on ``/diagnostics`` naming it;
- a pose topic that, like AMCL's ``/amcl_pose``, is published only after motion: steps go on
  with the latest pose, then a WARN naming the topic and AMCL's rule;
- Nav2's ``always_send_full_costmap: false``: one grid, then ``_updates`` only: steps go on
  and an update shows in the observation; a bad update is refused with the reason;
- ``~/start_episode`` starts one episode.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")
pytest.importorskip("tf2_msgs", reason="tf2_msgs is not built here (scripts/install)")
pytest.importorskip("map_msgs", reason="map_msgs is not built here (scripts/install)")

from hdrqn_ros.envs.domain import NO_SUBGOAL  # noqa: E402
from hdrqn_ros.nodes import nav  # noqa: E402
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS, STEP_QOS, keep_last  # noqa: E402
from hdrqn_ros.protocol import wire  # noqa: E402
from hdrqn_ros.supervisor import ProcessSpec, Supervisor  # noqa: E402

from ros_probe import RosProbe  # noqa: E402

MAP_TO_ODOM = (0.8, 0.4, 0.2)
"""x, y (m), yaw (rad) of ``odom`` in ``map``: a localised robot's offset."""
START = (1.0, 1.0, 0.0)
"""The robot in ``map``."""
PLACES = ((1.5, 1.0), (1.5, 1.5))
"""Blue, green in ``map``."""
STOPS = ((1.3, 1.0, 0.0), (1.5, 1.3, math.pi / 2))
"""Where the robot stops after steps 0 and 1: 0.2 m short of each place, as Nav2 does."""
RESOLUTION, CELLS = 0.05, 80
"""The local costmap: 4 m x 4 m."""
WALL_BELOW_Y = 0.6
"""The map's wall: every cell whose centre has ``y`` (m, ``map``) below this."""


def _planar(x: float, y: float, yaw: float) -> np.ndarray:
    """The 3x3 homogeneous matrix of a planar pose."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _in(frame_from: np.ndarray, xy) -> tuple[float, float]:
    x, y, _ = frame_from @ np.array([xy[0], xy[1], 1.0])
    return float(x), float(y)


class FakeRobot:
    """The test's node: a robot publishing what ``robot_environment`` reads (``/tf``,
    ``/tf_static``, a local costmap, the places, optionally ``/amcl_pose``) and a sub-controller
    answering each step with action 0; it records every ``env_step``, ``observation`` and
    ``/diagnostics`` status of the robot environment."""

    def __init__(self):
        self.mw = RosProbe(["fake_robot"])
        node = self.node = self.mw.create_node("fake_robot")
        self.pose = START  # map frame
        self.steps: list[dict] = []
        self.observations: dict[int, np.ndarray] = {}  # key -> (44, 44, 3)
        self.observation_frames: set[str] = set()
        self.diagnostics: list[tuple[int, str]] = []  # the robot environment's (level, message)
        self.tf = node.create_publisher("tf2_msgs/msg/TFMessage", "/tf", keep_last(100))
        self.tf_static = node.create_publisher("tf2_msgs/msg/TFMessage", "/tf_static",
                                               keep_last(100, transient_local=True))
        self.costmap = node.create_publisher(nav.OCCUPANCY_GRID, "/local_costmap/costmap", LATCHED_QOS)
        self.updates = node.create_publisher("map_msgs/msg/OccupancyGridUpdate", "/local_costmap/costmap_updates",
                                             keep_last(10, transient_local=True))
        self.places = node.create_publisher(nav.POSE_ARRAY, "/places", LATCHED_QOS)
        self.amcl = node.create_publisher("geometry_msgs/msg/PoseWithCovarianceStamped", "/amcl_pose", DEFAULT_QOS)
        self.action = node.create_publisher(wire.INTS, wire.ACTION, STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.ENV_STEP, self._on_step, STEP_QOS)
        node.create_subscription(wire.IMAGE, wire.OBSERVATION, self._on_observation, STEP_QOS)
        node.create_subscription("diagnostic_msgs/msg/DiagnosticArray", "/diagnostics", self._on_diagnostics)
        self.plan = list(STOPS)  # where the robot goes after each step of an episode
        self.moves = list(self.plan)
        self.costmap_sent = 0.0  # when the local costmap was last sent (monotonic s)

    def now_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def stamp(self):
        return self.node.get_clock().now().to_msg()

    # -- what the robot publishes --------------------------------------------------------------------
    def transform(self, parent: str, child: str, x: float, y: float, yaw: float, z: float = 0.0):
        msg = self.node.msg("geometry_msgs/msg/TransformStamped")()
        msg.header.stamp, msg.header.frame_id, msg.child_frame_id = self.stamp(), parent, child
        msg.transform.translation.x, msg.transform.translation.y, msg.transform.translation.z = x, y, z
        msg.transform.rotation.z, msg.transform.rotation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        return msg

    def odom_pose(self) -> tuple[float, float, float]:
        """The robot in ``odom``."""
        x, y = _in(np.linalg.inv(_planar(*MAP_TO_ODOM)), self.pose[:2])
        return x, y, self.pose[2] - MAP_TO_ODOM[2]

    def publish_tf(self, with_base: bool = True) -> None:
        """``map -> odom`` and ``odom -> base_footprint`` on ``/tf``, stamped now."""
        transforms = [self.transform("map", "odom", *MAP_TO_ODOM)]
        if with_base:
            transforms.append(self.transform("odom", "base_footprint", *self.odom_pose()))
        self.tf.publish(self.node.msg("tf2_msgs/msg/TFMessage")(transforms=transforms))

    def publish_tf_and_costmap(self, with_base: bool = True) -> None:
        """``/tf`` now, and the local costmap about twice a second (Nav2's ``publish_frequency``)."""
        self.publish_tf(with_base)
        self.publish_costmap_at_2hz(self.odom_grid)

    def publish_static(self) -> None:
        """``base_footprint -> base_link`` (0.1 m up) on ``/tf_static``."""
        self.tf_static.publish(self.node.msg("tf2_msgs/msg/TFMessage")(transforms=[
            self.transform("base_footprint", "base_link", 0.0, 0.0, 0.0, z=0.1)]))

    def grid(self, frame: str, origin_xy: tuple[float, float]):
        """A free ``CELLS`` x ``CELLS`` OccupancyGrid in ``frame``, stamped now."""
        msg = self.node.msg(nav.OCCUPANCY_GRID)()
        msg.header.stamp, msg.header.frame_id = self.stamp(), frame
        msg.info.resolution, msg.info.width, msg.info.height = RESOLUTION, CELLS, CELLS
        msg.info.origin.position.x, msg.info.origin.position.y = origin_xy
        msg.info.origin.orientation.w = 1.0
        msg.data = self.node.pack(np.zeros(CELLS * CELLS, np.int8))
        return msg

    def odom_grid(self):
        """The local costmap in ``odom``, centred on the robot's start: the map's wall
        (:data:`WALL_BELOW_Y`) seen through ``map -> odom``, cell by cell."""
        x0, y0 = (v - CELLS * RESOLUTION / 2 for v in _in(np.linalg.inv(_planar(*MAP_TO_ODOM)), START[:2]))
        msg = self.grid("odom", (x0, y0))
        centres = (np.arange(CELLS) + 0.5) * RESOLUTION
        xs, ys = np.meshgrid(x0 + centres, y0 + centres)  # row-major from the origin, as OccupancyGrid
        map_y = (_planar(*MAP_TO_ODOM) @ np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]))[1]
        msg.data = self.node.pack(np.where(map_y < WALL_BELOW_Y, 100, 0).astype(np.int8))
        return msg

    def update(self, frame: str, x: int, y: int, width: int, height: int, value: int):
        msg = self.node.msg("map_msgs/msg/OccupancyGridUpdate")()
        msg.header.stamp, msg.header.frame_id = self.stamp(), frame
        msg.x, msg.y, msg.width, msg.height = x, y, width, height
        msg.data = self.node.pack(np.full(width * height, value, np.int8))
        return msg

    def publish_places(self, frame: str = "map") -> None:
        msg = self.node.msg(nav.POSE_ARRAY)()
        msg.header.stamp, msg.header.frame_id = self.stamp(), frame
        for x, y in PLACES:
            pose = self.node.msg("geometry_msgs/msg/Pose")()
            pose.position.x, pose.position.y, pose.orientation.w = x, y, 1.0
            msg.poses.append(pose)
        self.places.publish(msg)

    def publish_amcl_and_map_costmap(self) -> None:
        """``/amcl_pose`` now, and a free local costmap in ``map`` about twice a second."""
        self.publish_amcl()
        self.publish_costmap_at_2hz(lambda: self.grid("map", (0.0, 0.0)))

    def publish_costmap_at_2hz(self, make_grid) -> None:
        """``make_grid()`` on the local costmap topic if the last was sent over 0.5 s ago."""
        if time.monotonic() - self.costmap_sent > 0.5:
            self.costmap_sent = time.monotonic()
            self.costmap.publish(make_grid())

    def publish_amcl(self) -> None:
        msg = self.node.msg("geometry_msgs/msg/PoseWithCovarianceStamped")()
        msg.header.stamp, msg.header.frame_id = self.stamp(), "map"
        msg.pose.pose.position.x, msg.pose.pose.position.y = self.pose[:2]
        msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(self.pose[2] / 2), math.cos(self.pose[2] / 2)
        self.amcl.publish(msg)

    # -- what it hears --------------------------------------------------------------------------------
    def _on_step(self, msg) -> None:
        step = wire.read_record(msg, wire.STEP_FIELDS)
        if self.steps and step["key"] == self.steps[-1]["key"]:
            return  # re-published
        self.steps.append(step)
        if step["terminated"] or step["truncated"]:
            self.pose, self.moves = START, list(self.plan)
            return
        if self.moves:
            self.pose = self.moves.pop(0)  # the action moves the robot before the next step
        self.action.publish(wire.make_record(self.node, wire.INTS, wire.ACTION_FIELDS, [int(step["key"]), 0]))

    def _on_observation(self, msg) -> None:
        key, pixels = wire.read_images(msg, 44, 44, 1)
        self.observations[key] = pixels[0]
        self.observation_frames.add(msg.header.frame_id)

    def _on_diagnostics(self, msg) -> None:
        self.diagnostics += [(int.from_bytes(s.level, "little"), s.message) for s in msg.status
                             if s.name == "hdrqn_ros: /robot_environment"]

    def run(self, until, timeout: float, what: str, sup: Supervisor, every=None) -> None:
        """Spin (calling ``every()`` about each 20 ms) until ``until()``, failing after ``timeout`` s."""
        end = time.monotonic() + timeout
        while not until():
            sup.poll()
            assert sup.returncodes["robot_environment"] is None, self.log(sup)
            assert time.monotonic() < end, f"timed out after {timeout} s waiting for {what}: {self.log(sup)[-3000:]}"
            if every is not None:
                every()
            self.mw.spin(timeout_s=0.02)

    @staticmethod
    def log(sup: Supervisor) -> str:
        path = sup.log_dir / "robot_environment.log"
        return path.read_text() if path.exists() else ""

    def warned(self, *words: str) -> bool:
        return any(level == 1 and all(w in message for w in words) for level, message in self.diagnostics)

    def close(self) -> None:
        self.mw.shutdown()


def start(tmp_path: Path, *params: str) -> Supervisor:
    """The robot environment with ``params`` (``name:=value``) over this test's defaults."""
    values = {"subgoal_poses_topic": "/places", "step_period": "0.5", "max_steps": "6", "global_frame": "map",
              "robot_base_frame": "base_link"}
    values.update(param.split(":=", 1) for param in params)
    argv = [sys.executable, "-m", "hdrqn_ros.nodes.robot_environment", "--ros-args"]
    for name, value in values.items():
        argv += ["-p", f"{name}:={value}"]
    sup = Supervisor([ProcessSpec("robot_environment", argv)], log_dir=tmp_path, stop_timeout_s=30)
    sup.start()
    return sup


def expected_observation(robot_map: tuple[float, float, float], places) -> np.ndarray:
    """The observation the simulator's drawing gives in ``map`` itself, of the map's wall with
    the robot and ``places`` (``None``: visited), no transform involved."""
    info = SimpleNamespace(width=CELLS, height=CELLS, resolution=RESOLUTION,
                           origin=SimpleNamespace(position=SimpleNamespace(x=0.0, y=0.0)))
    rows = (np.arange(CELLS) + 0.5) * RESOLUTION < WALL_BELOW_Y
    grid = SimpleNamespace(info=info, data=np.where(rows[:, None], 100, 0).astype(np.int8).repeat(CELLS, 1).ravel())
    return nav.costmap_to_observation(grid, robot_xy=robot_map[:2], view_cells=5, cell_size_m=0.25,
                                      unknown="outside", goals_xy=list(places))


def test_pose_from_tf_costmap_in_odom_places_in_map(tmp_path, domain):
    """A non-identity ``map -> odom`` (0.8 m, 0.4 m, 0.2 rad) on ``/tf``, a static
    ``base_footprint -> base_link`` on ``/tf_static``, the local costmap in ``odom``, the places
    in ``map``: the episode runs; each observation is the one drawn in ``map`` itself (the
    map's wall along the view's bottom row, the places where they are: north-up is the map's
    +y); a robot that stops 0.2 m short of each place visits it (``goal_tolerance`` 0.25 m by
    default). Before: every costmap was refused (frame ``odom``, places in ``map``)."""
    robot = FakeRobot()
    sup = start(tmp_path, "step_period:=1.0")  # the robot moves right after a step, long before the next
    try:
        robot.publish_static()
        robot.publish_places()
        robot.run(lambda: any(s["terminated"] for s in robot.steps) and len(robot.observations) >= 3, 90,
                  "an episode through both places", sup, every=robot.publish_tf_and_costmap)
    finally:
        sup.stop()
        robot.close()
    first, second, last = robot.steps[:3]
    assert first["t"] == 0 and first["at_subgoal"] == NO_SUBGOAL
    assert second["collected"] == 1 and second["at_subgoal"] == 0 and second["extrinsic"] == 1.0, robot.steps
    assert last["collected"] == 1 and last["at_subgoal"] == 1 and last["success"] == 1, robot.steps
    keys = [int(s["key"]) for s in robot.steps[:3]]
    np.testing.assert_array_equal(robot.observations[keys[0]], expected_observation(START, PLACES))
    np.testing.assert_array_equal(robot.observations[keys[1]], expected_observation(STOPS[0], (None, PLACES[1])))
    assert robot.observation_frames == {"map"}  # the frame whose axes the view keeps


def test_a_frame_missing_from_the_tree_is_a_warning_naming_it(tmp_path, domain):
    """``map -> odom`` comes, ``odom -> base_footprint`` never does: ``/diagnostics`` says
    WARN naming ``base_link`` and who publishes the transforms (before: "no pose on /odom")."""
    robot = FakeRobot()
    sup = start(tmp_path)
    try:
        robot.publish_places()
        robot.run(lambda: robot.warned("map <- base_link", "odometry") and "'base_link'" in robot.log(sup), 60,
                  "a WARN naming the frames, and the log line", sup,
                  every=lambda: robot.publish_tf_and_costmap(with_base=False))
    finally:
        sup.stop()
        log = robot.log(sup)
        robot.close()
    assert robot.steps == []
    assert "map <- base_link" in log and "'base_link'" in log, log[-3000:]


def test_an_amcl_like_pose_topic_steps_on_then_warns(tmp_path, domain):
    """``/amcl_pose`` published until the episode starts, then never again (AMCL publishes
    only after motion; this robot stands still): the steps go on with the latest pose, and
    once it is older than ``stale_after_s`` ``/diagnostics`` says WARN naming the topic and
    AMCL's rule. Before: the first step after the pose stopped waited for ever, OK on
    ``/diagnostics``."""
    robot = FakeRobot()
    robot.plan = robot.moves = []
    sup = start(tmp_path, "pose_topic:=/amcl_pose", "pose_type:=pose_with_covariance", "stale_after_s:=6.0",
                "max_steps:=50")
    try:
        robot.costmap.publish(robot.grid("map", (0.0, 0.0)))
        robot.publish_places()
        robot.run(lambda: robot.steps, 60, "the first step", sup, every=robot.publish_amcl)
        robot.run(lambda: len(robot.steps) >= 3, 60, "steps on the latest pose", sup)
        robot.run(lambda: robot.warned("/amcl_pose", "update_min_d"), 60, "a WARN naming AMCL's rule", sup)
    finally:
        sup.stop()
        robot.close()


def test_costmap_updates_only(tmp_path, domain):
    """Nav2 with ``always_send_full_costmap: false``: one full grid, then only
    ``_updates``: the steps go on past ``stale_after_s`` and a lethal window sent as an update
    shows as wall in the observation; an update outside the grid is refused naming its window.
    Before: the costmap went stale and no step was taken."""
    robot = FakeRobot()
    robot.plan = robot.moves = []
    sup = start(tmp_path, "stale_after_s:=2.0", "max_steps:=50")
    updates_sent = [0.0]

    def tick() -> None:
        robot.publish_tf()
        if time.monotonic() - updates_sent[0] > 0.5:
            updates_sent[0] = time.monotonic()
            # the cell one up from the robot's (the grid is centred on the robot): lethal
            robot.updates.publish(robot.update("odom", CELLS // 2 - 2, CELLS // 2 + 3, 5, 5, 100))

    try:
        robot.publish_static()
        robot.costmap.publish(robot.odom_grid())
        robot.publish_places()
        robot.run(lambda: len(robot.steps) >= 10, 90, "10 steps on updates only (5 s)", sup, every=tick)
        robot.updates.publish(robot.update("odom", CELLS - 2, 0, 5, 5, 100))
        robot.run(lambda: "outside the 80 x 80 grid" in robot.log(sup), 60, "the bad update refused", sup, every=tick)
    finally:
        sup.stop()
        robot.close()
    # the latest step whose observation arrived too (a step's env_step and its observation come on two topics)
    obs = robot.observations[max(int(s["key"]) for s in robot.steps if int(s["key"]) in robot.observations)]
    cell = 44 // 5  # 8 or 9 pixels a cell: the cell above the agent's is wall (grey)
    assert (obs[cell + 4, 22] == [128, 128, 128]).all(), obs[:, 22]
    assert (obs[2 * cell + 4, 22] != [128, 128, 128]).any()


def test_start_episode_starts_one_episode(tmp_path, domain):
    """``autostart`` off: each ``~/start_episode`` runs one episode (here to ``max_steps`` 3),
    then nothing until the next call. Before: episodes ran back to back after one call. (All
    in ``map``, the pose on a topic: what the node read before tf.)"""
    from std_srvs.srv import Trigger

    robot = FakeRobot()
    robot.plan = robot.moves = []
    sup = start(tmp_path, "autostart:=false", "max_steps:=3", "pose_topic:=/amcl_pose",
                "pose_type:=pose_with_covariance")
    tick = robot.publish_amcl_and_map_costmap

    client = robot.node.create_client(Trigger, "/robot_environment/start_episode")

    def call():
        future = client.call_async(Trigger.Request())
        robot.run(future.done, 60, "start_episode's answer", sup, every=tick)
        return future.result()

    def ended() -> int:
        return sum(bool(s["truncated"] or s["terminated"]) for s in robot.steps)

    try:
        robot.publish_places()
        robot.run(client.service_is_ready, 60, "the service", sup, every=tick)
        assert call().success
        robot.run(lambda: ended() == 1, 60, "one episode", sup, every=tick)
        until = time.monotonic() + 3.0  # 6 step periods: another episode would have started
        robot.run(lambda: time.monotonic() > until, 10, "a quiet while", sup, every=tick)
        assert len(robot.steps) == 4 and {s["episode"] for s in robot.steps} == {0}, robot.steps
        assert call().success
        robot.run(lambda: ended() == 2, 60, "the second episode", sup, every=tick)
    finally:
        sup.stop()
        robot.close()
    assert [int(s["episode"]) for s in robot.steps] == [0] * 4 + [1] * 4


def test_a_recording_learners_credit_paces_the_steps(tmp_path, domain):
    """``wait_for_learner`` (``hdrqn robot --record``): no episode before a learner is heard,
    no step beyond its credit (the step waits, a WARN naming the credit, and is re-published
    after ``action_timeout`` for a subscription of the learner matched late), then the
    episode runs on the credit. Before: any credit message let every step go, and a recording
    lost the answers the learner's late subscriptions missed."""
    robot = FakeRobot()
    robot.plan = robot.moves = []
    credit = robot.node.create_publisher(wire.FLOATS, wire.CREDIT, LATCHED_QOS)
    sup = start(tmp_path, "wait_for_learner:=true", "max_steps:=3", "action_timeout:=1.0", "pose_topic:=/amcl_pose",
                "pose_type:=pose_with_covariance")
    tick = robot.publish_amcl_and_map_costmap

    def grant(steps: int) -> None:
        credit.publish(wire.make_record(robot.node, wire.FLOATS, wire.CREDIT_FIELDS, [steps, 0.0, 0.0, 0, 1.0]))

    try:
        robot.publish_places()
        robot.run(lambda: robot.warned("for a learner"), 60, "the wait for a learner", sup, every=tick)
        assert not robot.steps
        grant(0)  # heard, no credit ahead: the learner does not yet hold the first step's answers
        robot.run(lambda: robot.steps and robot.warned("learner's credit"), 60, "the wait for credit", sup,
                  every=tick)
        robot.run(lambda: "no credit from the learner" in robot.log(sup), 60, "the step re-published", sup,
                  every=tick)
        assert [int(s["t"]) for s in robot.steps] == [0], robot.steps
        grant(10)
        robot.run(lambda: any(s["truncated"] or s["terminated"] for s in robot.steps), 60, "the episode's end", sup,
                  every=tick)
    finally:
        sup.stop()
        robot.close()
    assert [int(s["t"]) for s in robot.steps[:4]] == [0, 1, 2, 3], robot.steps


# -- the parts on their own (no processes) ------------------------------------------------------------
def _inputs():
    import logging

    from hdrqn_ros.nodes.robot_inputs import Frames, RobotInputs

    topics = {"pose": "/pose", "costmap": "/costmap", "costmap_updates": "/costmap_updates", "places": "/places"}
    return RobotInputs(logging.getLogger("test"), topics, None, 2, 5, 0.25, Frames(None, "no tf in this test"))


def _message(type_name: str, frame: str, stamp_s: int, **fields):
    from hdrqn_ros.nodes.ros_messages import interface_class, pack

    msg = interface_class(type_name)()
    msg.header.frame_id, msg.header.stamp.sec = frame, stamp_s
    for name, value in fields.items():
        setattr(msg, name, pack(value) if isinstance(value, np.ndarray) else value)
    return msg


def test_an_update_is_applied_on_the_last_full_grid_or_refused_with_the_reason():
    inputs = _inputs()
    update = "map_msgs/msg/OccupancyGridUpdate"
    window = {"x": 2, "y": 3, "width": 4, "height": 2, "data": np.full(8, 100, np.int8)}
    assert not inputs.take_update(_message(update, "odom", 1, **window), 1)
    assert "no full grid on /costmap yet" in inputs.refused["costmap_updates"]
    grid = _message(nav.OCCUPANCY_GRID, "odom", 2, data=np.zeros(30 * 30, np.int8))
    grid.info.width = grid.info.height = 30
    grid.info.resolution = 0.05
    assert inputs.take_costmap(grid, 2)
    assert inputs.take_update(_message(update, "odom", 3, **window), 3)
    cells = inputs.costmap.value.data.reshape(30, 30)
    assert (cells[3:5, 2:6] == 100).all() and cells.sum() == 800
    assert inputs.costmap.value.stamp_ns == 3 * 10**9 and inputs.costmap.arrived_ns == 3
    for msg, why in ((_message(update, "map", 4, **window), "in frame 'map', the grid on /costmap in 'odom'"),
                     (_message(update, "odom", 4, **{**window, "x": 28}), "outside the 30 x 30 grid"),
                     (_message(update, "odom", 4, **{**window, "data": np.zeros(3, np.int8)}), "has 3 data values"),
                     (_message(update, "odom", 1, **window), "before the grid")):
        assert not inputs.take_update(msg, 4)
        assert why in inputs.refused["costmap_updates"], inputs.refused
    assert inputs.costmap.value.stamp_ns == 3 * 10**9


def test_visit_rules():
    """``tolerance``: within ``goal_tolerance`` (a navigator's stop 0.248 m away counts);
    ``cell``: in the place's cell (the next cell's centre, 0.25 m away, does not)."""
    from hdrqn_ros.nodes.robot_environment import CellVisits
    from hdrqn_ros.robot.ordered_visits import OrderedVisits

    near, tolerance, cell = (1.0, 1.0), OrderedVisits(2, 0.25, 50), CellVisits(2, 0.25, 50)
    for rule in (tolerance, cell):
        rule.start([near, (3.0, 3.0)])
    assert tolerance.where((1.248, 1.0)) == 0 and cell.where((1.248, 1.0)) == NO_SUBGOAL
    assert cell.where((1.25, 1.0)) == NO_SUBGOAL and cell.where((1.12, 0.88)) == 0


def test_frames_without_tf_and_at_the_latest_time():
    from hdrqn_ros.nodes.robot_inputs import Frames, Waiting
    from hdrqn_ros.robot.transforms import Transform, TransformBuffer

    assert Frames(None, "why").transform("map", "map", 5, "the places").almost_equal(Transform.identity())
    with pytest.raises(Waiting, match="the places needs the transform odom <- map, and there is no tf here: why"):
        Frames(None, "why").transform("odom", "map", 5, "the places")
    buffer = TransformBuffer()
    buffer.set_transform("map", "odom", 10, Transform.from_xy_yaw(1.0, 0.0, 0.0))
    frames = Frames(buffer.lookup)
    assert frames.transform("map", "odom", 20, "x").translation[0] == 1.0 and frames.fell_back == 1
    with pytest.raises(Waiting, match="no transform map <- base_link"):
        frames.transform("map", "base_link", 20, "x")
