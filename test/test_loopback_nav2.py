"""The loopback robot speaks as a Nav2 robot (issue 38 item 9), as a real node process
watched by the test's own rclpy node:

- tf ``map -> odom -> base_link`` with a non-identity ``map -> odom`` that drifts while the
  robot moves: composed, it is the robot's start pose (the simulator's layout) and, at every
  ``/amcl_pose``, that pose; ``/odom`` in ``odom`` is tf's ``odom -> base_link``;
- ``/amcl_pose`` once at the start, then only after motion (none while the robot stands);
- the local costmap in ``odom``: through tf, each lethal cell is a wall of the map and every
  cell whose centre is in a wall is lethal, with Nav2's inflation costs around them; the
  global costmap in ``map``;
- the 1 s command deadman: one command drives the robot for 1 s of simulated time;
- ``always_send_full_costmap: false``: a standing robot's local costmap comes as
  ``map_msgs/OccupancyGridUpdate`` on ``local_costmap/costmap_updates``, a moving one's as
  full grids when the window moves.
"""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.nodes.qos import LATCHED_QOS, keep_last  # noqa: E402
from hdrqn_ros.robot.loopback_world import LoopbackWorld, compose  # noqa: E402
from hdrqn_ros.robot_graph import NODE_MODULES  # noqa: E402
from hdrqn_ros.supervisor import ProcessSpec, Supervisor, python_command  # noqa: E402

from ros_probe import RosProbe  # noqa: E402

SEED = 3
MAP_TO_ODOM = (0.8, 0.4, 0.2)
NAV2_LIKE = {"odom_frame": "odom", "map_to_odom": list(MAP_TO_ODOM), "odom_error": [0.02, 0.01], "drive": "diff",
             "start_yaw": 0.5, "inflation_radius": 0.7, "cmd_vel_timeout": 1.0, "seed": SEED, "real_time_factor": 5.0}
"""The robot as issue 38 measured Nav2's: frames with an offset, drift, 1 s deadman, inflation."""





def yaw_of(q) -> float:
    return 2.0 * math.atan2(q.z, q.w)


def pose_of(p) -> tuple[float, float, float]:
    """(x, y, yaw) of a geometry_msgs Pose or Transform."""
    position = getattr(p, "position", None) or p.translation
    orientation = getattr(p, "orientation", None) or p.rotation
    return position.x, position.y, yaw_of(orientation)


def stamp_ns(header) -> int:
    return header.stamp.sec * 10**9 + header.stamp.nanosec


class Robot:
    """The loopback robot process and a probe that keeps everything it says, by stamp."""

    def __init__(self, tmp_path, **params):
        argv = python_command(NODE_MODULES["loopback_robot"]) + ["--ros-args"]
        for name, value in params.items():
            text = str(value).lower() if isinstance(value, bool) else str(value)
            argv += ["-p", f"{name}:={text}"]
        self.log = tmp_path / "loopback_robot.log"
        self.sup = Supervisor([ProcessSpec("loopback_robot", argv)], log_dir=tmp_path)
        self.probe = RosProbe(["probe"])
        node = self.node = self.probe.create_node("probe")
        self.tf: dict[int, dict[tuple[str, str], tuple]] = {}  # stamp -> (parent, child) -> (x, y, yaw)
        self.odom, self.amcl, self.grids, self.updates, self.places = [], [], [], [], []
        deep = keep_last(1000)
        node.create_subscription("tf2_msgs/msg/TFMessage", "/tf", self._on_tf, deep)
        node.create_subscription("nav_msgs/msg/Odometry", "/odom", self.odom.append, deep)
        node.create_subscription("geometry_msgs/msg/PoseWithCovarianceStamped", "/amcl_pose", self.amcl.append,
                                 LATCHED_QOS)
        node.create_subscription("nav_msgs/msg/OccupancyGrid", "/local_costmap/costmap", self.grids.append,
                                 keep_last(100, transient_local=True))
        node.create_subscription("map_msgs/msg/OccupancyGridUpdate", "/local_costmap/costmap_updates",
                                 self.updates.append, keep_last(100, transient_local=True))
        node.create_subscription("geometry_msgs/msg/PoseArray", "/subgoal_poses", self.places.append, LATCHED_QOS)
        self.global_grids: list = []
        node.create_subscription("nav_msgs/msg/OccupancyGrid", "/global_costmap/costmap", self.global_grids.append,
                                 LATCHED_QOS)
        self.cmd_vel = node.create_publisher("geometry_msgs/msg/Twist", "/cmd_vel")
        self.sup.start()

    def _on_tf(self, msg) -> None:
        for t in msg.transforms:
            self.tf.setdefault(stamp_ns(t.header), {})[(t.header.frame_id, t.child_frame_id)] = pose_of(t.transform)

    def until(self, cond, what: str, timeout: float = 60.0) -> None:
        """Spin until ``cond()``; fails naming ``what`` (and the robot's log) after ``timeout`` s."""
        def done():
            self.sup.poll()
            assert self.sup.returncodes["loopback_robot"] is None, self.log.read_text()[-3000:]
            return cond()

        self.probe.spin(until=done, timeout_s=timeout)
        assert cond(), f"timed out after {timeout} s waiting for {what}: {self.log.read_text()[-2000:]}"

    def drive(self, vx: float, wz: float) -> None:
        msg = self.node.msg("geometry_msgs/msg/Twist")()
        msg.linear.x, msg.angular.z = vx, wz
        self.cmd_vel.publish(msg)

    def in_map(self, stamp: int) -> tuple[float, float, float]:
        """tf's ``map -> odom -> base_link`` at ``stamp``: the robot's pose in the map."""
        links = self.tf[stamp]
        return compose(links[("map", "odom")], links[("odom", "base_link")])

    def close(self) -> None:
        try:
            codes = self.sup.stop()
        finally:
            self.probe.shutdown()
        assert codes["loopback_robot"] == 0, self.log.read_text()[-3000:]


def standing_still(odom) -> bool:
    twist = odom.twist.twist
    return twist.linear.x == twist.linear.y == twist.angular.z == 0.0


def close_to(a, b, tol: float = 1e-6) -> bool:
    return abs(a[0] - b[0]) < tol and abs(a[1] - b[1]) < tol and abs(math.remainder(a[2] - b[2], 2 * math.pi)) < tol


def test_frames_odom_amcl_and_the_costmap_in_odom(tmp_path, domain):
    robot = Robot(tmp_path, **NAV2_LIKE)
    world = LoopbackWorld("gridworld", 2, SEED, start_yaw=0.5)
    start = world.new_episode() and world.pose
    try:
        robot.until(lambda: robot.amcl and robot.tf and robot.grids and robot.odom and robot.global_grids,
                    "amcl_pose, tf, costmaps, odom")
        first_tf = min(robot.tf)
        standing = len(robot.amcl)
        robot.probe.spin(timeout_s=2.0)  # 10 s of simulated time standing
        assert len(robot.amcl) == standing == 1, "amcl_pose while the robot stood"
        end = len(robot.tf) + 150  # 15 s of simulated time driving (0.1 m/s, turning)
        robot.until(lambda: (robot.drive(0.1, 0.15) or True) and len(robot.tf) >= end, "the robot driving")
        robot.until(lambda: standing_still(robot.odom[-1]), "the deadman's stop")
        moved = len(robot.amcl)
        robot.probe.spin(timeout_s=2.0)
        assert len(robot.amcl) == moved, "amcl_pose after the robot stopped"
    finally:
        robot.close()
    # tf: map -> odom starts at the offset and drifts; composed it is the robot's start pose
    assert robot.tf[first_tf][("map", "odom")] == pytest.approx(MAP_TO_ODOM)
    assert close_to(robot.in_map(first_tf), start), (robot.in_map(first_tf), start)
    last_tf = max(robot.tf)
    drift = robot.tf[last_tf][("map", "odom")]
    assert 1e-3 < math.hypot(drift[0] - MAP_TO_ODOM[0], drift[1] - MAP_TO_ODOM[1]) < 0.1, drift
    assert math.hypot(*np.subtract(robot.in_map(last_tf)[:2], start[:2])) > 0.2, "the robot did not move"
    # amcl_pose: at the start, then after motion; each is tf's pose at its stamp
    assert robot.amcl[0].header.frame_id == "map" and close_to(pose_of(robot.amcl[0].pose.pose), start)
    assert moved >= 3, f"{moved} amcl_pose for 15 s of driving and turning"
    for msg in robot.amcl[1:]:
        assert close_to(pose_of(msg.pose.pose), robot.in_map(stamp_ns(msg.header)))
    # odom: odom -> base_link, in frame odom
    assert {(m.header.frame_id, m.child_frame_id) for m in robot.odom} == {("odom", "base_link")}
    both = [m for m in robot.odom if stamp_ns(m.header) in robot.tf]
    assert len(both) >= 100
    for msg in both:
        assert close_to(pose_of(msg.pose.pose), robot.tf[stamp_ns(msg.header)][("odom", "base_link")])
    # the global costmap in map: the walls lethal, inflated around
    whole = robot.global_grids[-1]
    assert whole.header.frame_id == "map" and (whole.info.width, whole.info.height) == (55, 55)
    data = np.asarray(whole.data, np.int64).reshape(55, 55)
    np.testing.assert_array_equal(data == 100, np.kron(world.walls[::-1], np.ones((5, 5), bool)))
    assert 99 in data and len(set(data[data < 99].tolist())) > 10, "no inflation costs in the global costmap"
    # the local costmap in odom agrees with the map through tf at its stamp
    assert {g.header.frame_id for g in robot.grids} == {"odom"}
    seen = [g for g in robot.grids if stamp_ns(g.header) in robot.tf]  # (the first may predate tf's matching)
    assert len(seen) >= 10, "local costmaps while the robot drove"
    for grid in (seen[0], seen[len(seen) // 2], seen[-1]):
        check_costmap_in_odom(grid, robot.tf[stamp_ns(grid.header)][("map", "odom")], world)


def check_costmap_in_odom(grid, map_to_odom, world: LoopbackWorld) -> None:
    """Each cell's centre, taken into the map: in a wall -> 100; off the map -> -1 (99 within
    the robot's radius of a wall); else free or inflated (0..99); cells touching a wall's
    cell are 99 (inscribed)."""
    info = grid.info
    assert (info.width, info.height, info.resolution) == (60, 60, pytest.approx(0.05))
    data = np.asarray(grid.data, np.int64).reshape(info.height, info.width)
    rows, cols = np.indices(data.shape)
    x0, y0 = info.origin.position.x, info.origin.position.y
    cx, cy = x0 + (cols + 0.5) * 0.05, y0 + (rows + 0.5) * 0.05
    c, s = math.cos(map_to_odom[2]), math.sin(map_to_odom[2])
    mx, my = map_to_odom[0] + c * cx - s * cy, map_to_odom[1] + s * cx + c * cy
    map_row, map_col = 10 - np.floor(my / 0.25).astype(int), np.floor(mx / 0.25).astype(int)
    on_map = (map_row >= 0) & (map_row < 11) & (map_col >= 0) & (map_col < 11)
    wall = on_map & world.walls[map_row.clip(0, 10), map_col.clip(0, 10)]
    assert (data[wall] == 100).all() and (data[~wall] != 100).all()
    assert np.isin(data[~on_map], (-1, 99)).all() and ((data[on_map & ~wall] >= 0) & (data[on_map & ~wall] <= 99)).all()
    beside = np.zeros_like(wall)
    beside[1:, :] |= wall[:-1, :]
    beside[:-1, :] |= wall[1:, :]
    beside[:, 1:] |= wall[:, :-1]
    beside[:, :-1] |= wall[:, 1:]
    assert (data[beside & ~wall] == 99).all() and len(set(data[on_map & ~wall].tolist())) > 10, "no graded costs"


def test_deadman_and_costmap_updates_only(tmp_path, domain):
    """``cmd_vel_timeout`` 1 s: one command of 0.1 m/s moves the robot 0.1 m in 1 s of
    simulated time, then it stops. With ``always_send_full_costmap`` false, standing still:
    OccupancyGridUpdates of the whole window, equal to the last grid; moving: full grids."""
    robot = Robot(tmp_path, **NAV2_LIKE, always_send_full_costmap=False)
    try:
        robot.until(lambda: len(robot.updates) >= 3 and robot.grids and robot.odom and
                    stamp_ns(robot.odom[-1].header) in robot.tf, "costmap updates, odom and tf")
        grids = len(robot.grids)
        robot.probe.spin(timeout_s=1.0)
        assert len(robot.grids) == grids, "a full grid while the window stood"
        robot.until(lambda: robot.cmd_vel.get_subscription_count() > 0, "the robot's cmd_vel subscription")
        before = len(robot.odom)
        robot.drive(0.1, 0.0)
        robot.until(lambda: any(m.twist.twist.linear.x for m in robot.odom[before:]), "the robot moving")
        robot.until(lambda: standing_still(robot.odom[-1]), "the deadman's stop")
        robot.probe.spin(timeout_s=1.0)
    finally:
        robot.close()
    moving = [stamp_ns(m.header) for m in robot.odom[before:] if m.twist.twist.linear.x]
    last = max(i for i, m in enumerate(robot.odom) if stamp_ns(m.header) in robot.tf)
    assert standing_still(robot.odom[last]) and last > before
    start, stop = (robot.in_map(stamp_ns(robot.odom[i].header)) for i in (before - 1, last))
    assert math.hypot(stop[0] - start[0], stop[1] - start[1]) == pytest.approx(0.1, abs=1e-6)
    odometry = pose_of(robot.odom[before - 1].pose.pose), pose_of(robot.odom[last].pose.pose)
    assert math.dist(odometry[0][:2], odometry[1][:2]) == pytest.approx(0.102, abs=1e-6), "odom_error: 2 % more"
    assert (max(moving) - min(moving)) / 1e9 == pytest.approx(1.0, abs=0.11), "moved for other than 1 s"
    assert len(robot.grids) > grids, "no full grid when the window moved"
    grid = robot.grids[grids - 1]
    for update in robot.updates[:3]:
        assert update.header.frame_id == "odom" and (update.x, update.y) == (0, 0)
        assert (update.width, update.height) == (grid.info.width, grid.info.height)
        assert list(update.data) == list(grid.data), "a standing robot's costmap changed"


@pytest.mark.parametrize("params, problem", [
    ({"map_to_odom": "[0.8, 0.4, 0.2]"}, "need an odometry frame: set odom_frame"),
    ({"odom_frame": "odom", "map_to_odom": "[0.8, 0.4]"}, "map_to_odom: must be [x, y, yaw]"),
    ({"odom_frame": "odom", "odom_error": "[0.02, 1.5]"}, "odom_error: must be relative errors"),
    ({"odom_frame": "odom", "base_frame": "odom"}, "base_frame 'odom' must differ"),
    ({"drive": "tracked"}, "drive must be one of"),
])
def test_startup_mistakes_exit_2_naming_the_parameter(tmp_path, domain, params, problem):
    argv = python_command(NODE_MODULES["loopback_robot"]) + ["--ros-args"]
    for name, value in params.items():
        argv += ["-p", f"{name}:={value}"]
    sup = Supervisor([ProcessSpec("loopback_robot", argv)], log_dir=tmp_path)
    sup.start()
    try:
        end = time.monotonic() + 60
        while sup.returncodes["loopback_robot"] is None and time.monotonic() < end:
            sup.poll()
            time.sleep(0.1)
    finally:
        codes = sup.stop()
    out = (tmp_path / "loopback_robot.log").read_text()
    assert codes["loopback_robot"] == 2 and problem in out, out[-2000:]
