"""NavigateToPose with outcomes (issue 38, meta-only), as real rclpy processes.

- the loopback robot's ``navigate_to_pose`` server, driven by the test's own rclpy
  ``ActionClient``: a reachable goal ends SUCCEEDED with the robot stopped within Nav2's
  0.25 m (not at the goal itself), holonomic and differential drive, with feedback on the
  way; a goal in a wall, off the map or in another frame ends ABORTED at once with Jazzy's
  error codes; a newer goal preempts; a cancel ends CANCELED with the robot stopped;
- the meta-controller waits for a missing action server and says so (log, /diagnostics);
- the robot graph in meta-only with ``navigation: action``: an option to an unreachable
  place ends at the next step (ABORTED) instead of after ``option_timeout``; reachable
  places are visited, one goal per option; deactivating or stopping (SIGTERM) the
  meta-controller cancels the active goal and the robot stops; the goal's feedback is on
  the meta-controller's /diagnostics.
"""
from __future__ import annotations

import math
import signal
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")
pytest.importorskip("nav2_msgs", reason="nav2_msgs is not built here (scripts/install builds it)")

from lifecycle_msgs.msg import Transition  # noqa: E402
from nav2_msgs.action import NavigateToPose  # noqa: E402
from rclpy.action import ActionClient  # noqa: E402

from hdrqn_ros.nodes import nav  # noqa: E402
from hdrqn_ros.nodes.navigation_outcomes import (STATUS_ABORTED, STATUS_CANCELED, STATUS_EXECUTING,  # noqa: E402
                                                  STATUS_SUCCEEDED)
from hdrqn_ros.nodes.qos import STEP_QOS  # noqa: E402
from hdrqn_ros.protocol import wire  # noqa: E402
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL  # noqa: E402
from hdrqn_ros.robot_graph import NODE_MODULES, RobotRun, robot_parameters, robot_processes  # noqa: E402
from hdrqn_ros.supervisor import ProcessSpec, Supervisor, python_command  # noqa: E402

from test_graph import ENV, read_jsonl  # noqa: E402
from test_managed_nodes import LifecycleClient  # noqa: E402

SHIPPED = Path(__file__).resolve().parents[1] / "policies" / "hdrqn-v2_gridworld-2goals"
TOLERANCE = 0.25
STEP_S = 2.5
OPTION_TIMEOUT_S = 30.0


class NavProbe:
    """The test's node: a NavigateToPose client, and a listener of odometry, the action's
    status, subgoals, steps and /diagnostics (``client``: a
    :class:`~test_managed_nodes.LifecycleClient`'s node and context, for transitions too)."""

    def __init__(self, client: LifecycleClient):
        self.client, self.mw, node = client, client.mw, client.node
        self.action = ActionClient(node, NavigateToPose, "navigate_to_pose")
        self.odom: list[tuple[float, float, float, float]] = []  # x, y, |v|, |w|
        self.statuses: dict[bytes, list[int]] = {}  # goal id -> the statuses seen, in order
        self.options: list[tuple[int, int]] = []  # (key, subgoal) of each new option
        self.steps: list[dict] = []
        self.feedback: list[float] = []
        node.create_subscription(nav.POSE_TYPES["odometry"], "/odom", self._on_odom)
        node.create_subscription("action_msgs/msg/GoalStatusArray", "/navigate_to_pose/_action/status",
                                 self._on_status, 100)
        node.create_subscription(wire.INTS, "/subgoal", self._on_subgoal, STEP_QOS)
        node.create_subscription(wire.FLOATS, "/env_step", lambda m: self.steps.append(
            wire.read_record(m, wire.STEP_FIELDS)), STEP_QOS)

    def _on_odom(self, msg) -> None:
        twist = msg.twist.twist
        self.odom.append((msg.pose.pose.position.x, msg.pose.pose.position.y,
                          math.hypot(twist.linear.x, twist.linear.y), abs(twist.angular.z)))

    def _on_status(self, msg) -> None:
        for status in msg.status_list:
            seen = self.statuses.setdefault(bytes(status.goal_info.goal_id.uuid), [])
            if not seen or seen[-1] != status.status:
                seen.append(status.status)

    def _on_subgoal(self, msg) -> None:
        record = wire.read_records(msg, wire.SUBGOAL_FIELDS, np.int64)[0]
        if record["new_option"]:
            self.options.append((int(record["key"]), int(record["subgoal"])))

    def until(self, cond, timeout: float, what: str, sup: Supervisor | None = None) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if sup is not None:
                sup.poll()
            assert time.monotonic() < end, f"timed out after {timeout} s waiting for {what}" + \
                (f": {sup.returncodes}" if sup is not None else "")
            self.mw.spin(timeout_s=0.05)

    def send(self, x: float, y: float, frame: str = "map"):
        """A goal, accepted: its handle."""
        goal = NavigateToPose.Goal()
        goal.pose.header.frame_id = frame
        goal.pose.pose.position.x, goal.pose.pose.position.y, goal.pose.pose.orientation.w = x, y, 1.0
        future = self.action.send_goal_async(goal, feedback_callback=lambda m: self.feedback.append(
            m.feedback.distance_remaining))
        self.until(future.done, 60, "the goal's acceptance")
        handle = future.result()
        assert handle.accepted
        return handle

    def result(self, handle, timeout: float = 60):
        """(status, result, wall seconds it took to come)."""
        started = time.monotonic()
        future = handle.get_result_async()
        self.until(future.done, timeout, "the goal's result")
        return future.result().status, future.result().result, time.monotonic() - started

    def at_rest(self, ticks: int = 10) -> bool:
        """The last ``ticks`` odometry messages say the robot stands still."""
        return len(self.odom) >= ticks and all(v == 0.0 and w == 0.0 for _, _, v, w in self.odom[-ticks:])

    def goals_ended(self, status: int) -> int:
        return sum(seen[-1] == status for seen in self.statuses.values())


@pytest.fixture
def probe(domain, monkeypatch, tmp_path):
    monkeypatch.setenv("ROS_LOG_DIR", str(tmp_path / "ros_log"))
    client = LifecycleClient()
    yield NavProbe(client)
    client.close()


def node_process(node: str, *params: str) -> ProcessSpec:
    """The robot graph's ``node`` as a process of its own (``params``: ``name:=value``)."""
    return ProcessSpec(node, python_command(NODE_MODULES[node]) + ["--ros-args"] +
                       [a for p in params for a in ("-p", p)], stack_dump_signal=STACK_DUMP_SIGNAL)


def start_robot(tmp_path: Path, *params: str) -> Supervisor:
    """The loopback robot alone, on its own clock."""
    sup = Supervisor([node_process("loopback_robot", *params)], log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    return sup


def cell_centre(row: int, col: int) -> tuple[float, float]:
    """The gridworld map cell's centre (m, map frame; 0.25 m cells, row 0 at the top)."""
    return (col + 0.5) * 0.25, (10 - row + 0.5) * 0.25


@pytest.mark.parametrize("drive", ["holonomic", "diff"])
def test_a_reachable_goal_succeeds_stopped_within_tolerance(tmp_path, probe, drive):
    sup = start_robot(tmp_path, f"drive:={drive}", "start_yaw:=0.7", "nav_speed:=0.1")
    try:
        probe.until(lambda: probe.action.server_is_ready() and probe.odom, 60, "the navigate_to_pose server", sup)
        for goal in (cell_centre(9, 9), cell_centre(1, 1)):  # two far corners
            handle = probe.send(*goal)
            status, result, _ = probe.result(handle)
            assert status == STATUS_SUCCEEDED and result.error_code == 0, (status, result)
            probe.until(probe.at_rest, 30, "the robot at rest", sup)
            x, y, _, _ = probe.odom[-1]
            distance = math.hypot(goal[0] - x, goal[1] - y)
            assert 0.15 < distance <= TOLERANCE, f"stopped {distance:.3f} m from {goal}: Nav2 stops at its tolerance"
        remaining = probe.feedback
        assert len(remaining) >= 5 and max(remaining) > 1.0 and min(remaining) < 0.5, remaining
    finally:
        sup.stop()


def test_unreachable_goals_abort_at_once_with_jazzys_codes(tmp_path, probe):
    sup = start_robot(tmp_path)
    try:
        probe.until(lambda: probe.action.server_is_ready() and probe.odom, 60, "the navigate_to_pose server", sup)
        for goal, frame, code, words in ((cell_centre(0, 5), "map", 206, "not free"),  # the map's edge wall
                                         ((9.0, 1.0), "map", 204, "off the 11x11 grid"),
                                         (cell_centre(5, 5), "odom", 202, "frame 'odom'")):
            status, result, took = probe.result(probe.send(*goal, frame=frame))
            assert status == STATUS_ABORTED and result.error_code == code, (goal, status, result)
            assert words in result.error_msg and took < 5.0, (result.error_msg, took)
        assert probe.at_rest(), "an aborted goal does not move the robot"
    finally:
        sup.stop()


def test_a_newer_goal_preempts_and_a_cancel_stops_the_robot(tmp_path, probe):
    sup = start_robot(tmp_path, "nav_speed:=0.1")
    try:
        probe.until(lambda: probe.action.server_is_ready() and probe.odom, 60, "the navigate_to_pose server", sup)
        first = probe.send(*cell_centre(9, 9))
        probe.until(lambda: probe.odom[-1][2] > 0, 60, "the robot moving", sup)
        second = probe.send(*cell_centre(1, 9))
        status, result, _ = probe.result(first)
        assert status == STATUS_ABORTED and "preempted" in result.error_msg, (status, result)
        probe.until(lambda: probe.odom[-1][2] > 0, 60, "the robot moving to the newer goal", sup)
        cancel = second.cancel_goal_async()
        probe.until(cancel.done, 60, "the cancel's answer", sup)
        assert len(cancel.result().goals_canceling) == 1
        status, _, _ = probe.result(second)
        assert status == STATUS_CANCELED
        probe.until(probe.at_rest, 30, "the robot at rest after the cancel", sup)
        x, y, _, _ = probe.odom[-1]
        probe.mw.spin(timeout_s=1.0)
        assert probe.at_rest() and probe.odom[-1][:2] == (x, y), "the robot stays where it stopped"
        assert math.hypot(x - cell_centre(1, 9)[0], y - cell_centre(1, 9)[1]) > TOLERANCE
    finally:
        sup.stop()


def test_the_meta_controller_waits_visibly_for_a_missing_action_server(tmp_path, probe):
    table = tmp_path / "places.yaml"
    table.write_text("frame_id: map\nsubgoals: [{x: 1.125, y: 1.125}, {x: 2.125, y: 2.125}]\n")
    meta = node_process("meta_controller", f"policy:={SHIPPED}", f"subgoal_table:={table}")
    sup = Supervisor([meta], log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    robot = None
    try:
        def status() -> str:
            found = probe.client.diagnostics.get("hdrqn_ros: /meta_controller")
            return "" if found is None else f"{found.level[0]} {found.message}"

        probe.until(lambda: "navigate_to_pose" in status(), 60, "the meta-controller's WARN", sup)
        assert status().startswith("1 ") and "/navigate_to_pose action server" in status() and \
            "bt_navigator" in status(), status()
        log = tmp_path / "logs" / "meta_controller.log"
        probe.until(lambda: "waiting" in log.read_text() and "/navigate_to_pose action server" in log.read_text(),
                    60, "the wait in the log", sup)
        robot = start_robot(tmp_path / "robot")
        probe.until(lambda: status() and "navigate_to_pose" not in status(), 60, "the WARN gone with a server", sup)
        probe.until(lambda: "action server is up" in log.read_text(), 30, "the server's arrival in the log", sup)
    finally:
        sup.stop()
        if robot is not None:
            robot.stop()


def meta_only(tmp_path: Path, table: Path | None = None, episodes: int = 3, managed: tuple[str, ...] = (),
              **overrides) -> tuple[Supervisor, Path]:
    """The robot graph, meta-only, with the shipped policy and ``navigation: action`` (the
    critic's ``navigation_outcome`` on); ``table``: the places instead of each episode's layout."""
    log = tmp_path / "episodes.jsonl"
    run = RobotRun(algo="hdrqn-v2", env=ENV, view="5", policy=str(SHIPPED), mode="meta-only", episodes=episodes,
                   seed=0, real_time_factor=20.0, option_timeout=OPTION_TIMEOUT_S, episode_log=str(log))
    params = robot_parameters(run)
    params["meta_controller"]["navigation"] = "action"
    params["critic"]["navigation_outcome"] = True
    if table is not None:
        for node in ("meta_controller", "robot_environment"):
            params[node].pop("subgoal_poses_topic")
            params[node]["subgoal_table"] = str(table)
        params["robot_environment"]["new_layout_each_episode"] = False
    for node, values in overrides.items():
        params[node].update(values)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({("/**" if n == "/**" else f"/**/{n}"): {"ros__parameters": v}
                                    for n, v in params.items()}, sort_keys=False))
    sup = Supervisor(robot_processes(run, path, hierarchical=True, managed=managed), log_dir=tmp_path / "logs",
                     stop_timeout_s=30)
    sup.start()
    return sup, log


def finished(sup: Supervisor):
    return lambda: sup.returncodes["robot_environment"] is not None


def test_an_option_to_an_unreachable_place_ends_at_the_next_step(tmp_path, probe):
    """Both places in walls: every goal ends ABORTED at once, and its option at the next step
    (``option_timeout`` 30 s would have held each option for 12 steps)."""
    table = tmp_path / "walls.yaml"
    table.write_text("frame_id: map\nsubgoals: [{x: %.3f, y: %.3f}, {x: %.3f, y: %.3f}]\n"
                     % (*cell_centre(0, 3), *cell_centre(10, 7)))
    max_steps = 12
    sup, log = meta_only(tmp_path, table, episodes=2, robot_environment={"max_steps": max_steps})
    try:
        probe.until(finished(sup), 240, "2 robot episodes", sup)
    finally:
        codes = sup.stop()
    assert codes["robot_environment"] == 0, codes
    episodes = read_jsonl(log)
    assert [e["steps"] for e in episodes] == [max_steps] * 2 and not any(e["visits"] for e in episodes), episodes
    aborted = probe.goals_ended(STATUS_ABORTED)
    assert aborted >= len(probe.options) - 2 and len(probe.statuses) >= len(probe.options) - 2, \
        (aborted, len(probe.statuses), len(probe.options))
    # every option ends at the next step, or (an outcome later than the step, on a loaded machine) soon after
    episode_of = {int(step["key"]): int(step["episode"]) for step in probe.steps}
    keys = [key for key, _ in probe.options]
    lasted = [(b - a) / 1e9 for a, b in zip(keys, keys[1:]) if episode_of.get(a, -1) == episode_of.get(b, -2)]
    assert len(probe.options) >= 2 * max_steps / 3, f"{len(probe.options)} options in {2 * max_steps} steps"
    assert lasted and max(lasted) <= 3 * STEP_S + 1e-6 and np.mean(lasted) <= 2 * STEP_S, lasted
    print(f"\nunreachable places: {len(probe.options)} options in {2 * max_steps} steps, each "
          f"{np.mean(lasted):.2f} s of simulated time on average (max {max(lasted):.1f} s); "
          f"option_timeout {OPTION_TIMEOUT_S:g} s")


def test_reachable_places_are_visited_one_goal_per_option(tmp_path, probe):
    ended = (STATUS_SUCCEEDED, STATUS_ABORTED, STATUS_CANCELED)

    def goals_sent() -> int:
        found = probe.client.diagnostics.get("hdrqn_ros: /meta_controller")
        return -1 if found is None else int({kv.key: kv.value for kv in found.values}.get("goals_sent", -1))

    sup, log = meta_only(tmp_path, episodes=3)
    try:
        probe.until(finished(sup), 240, "3 robot episodes", sup)
        try:
            probe.until(lambda: len(probe.statuses) == goals_sent() and all(
                seen[-1] in ended for seen in probe.statuses.values()), 30, "every goal sent, and its end", sup)
        except AssertionError as exc:
            raise AssertionError(f"{exc}; the meta-controller's goals_sent {goals_sent()}, the statuses seen of "
                                 f"each goal {list(probe.statuses.values())}") from None
    finally:
        codes = sup.stop()
    assert codes["robot_environment"] == 0, codes
    episodes = read_jsonl(log)
    visits = sum(len(e["visits"]) for e in episodes)
    assert visits >= 3 and any(e["success"] for e in episodes), episodes
    # a goal for each option: every goal the meta-controller sent reached the server, one per visit at least
    # (the probe's own count of options may miss the first episode's: it is over in a few seconds)
    assert len(probe.statuses) == goals_sent() >= visits, (len(probe.statuses), goals_sent(), visits)
    assert probe.goals_ended(STATUS_SUCCEEDED) >= visits - len(episodes)
    print(f"\nreachable places: {len(episodes)} episodes, {visits} visits, success "
          f"{sum(e['success'] for e in episodes)}, steps {[e['steps'] for e in episodes]}; "
          f"{len(probe.statuses)} goals: "
          f"{probe.goals_ended(STATUS_SUCCEEDED)} SUCCEEDED, "
          f"{probe.goals_ended(STATUS_CANCELED)} CANCELED, {probe.goals_ended(STATUS_ABORTED)} "
          f"ABORTED")


@pytest.mark.parametrize("stop", ["deactivate", "sigterm"])
def test_stopping_the_meta_controller_cancels_its_goal(tmp_path, probe, stop):
    """Deactivated (as Nav2's lifecycle manager does it) or stopped (SIGTERM, as ``ros2 launch``
    ends it): the goal it was driving ends CANCELED and the robot stands still. While the goal
    runs, its feedback is on the meta-controller's /diagnostics."""
    sup, _ = meta_only(tmp_path, episodes=50, managed=("meta_controller",), critic={"option_timeout": 0.0},
                       loopback_robot={"nav_speed": 0.02, "real_time_factor": 10.0})
    client = probe.client
    try:
        client.until(lambda: client._services("meta_controller")[1].service_is_ready(), 120,
                     "the meta-controller's lifecycle services")
        assert client.change("meta_controller", Transition.TRANSITION_CONFIGURE)
        assert client.change("meta_controller", Transition.TRANSITION_ACTIVATE)

        def executing() -> list[bytes]:
            return [goal for goal, seen in probe.statuses.items() if seen[-1] == STATUS_EXECUTING]

        probe.until(lambda: executing() and probe.odom and probe.odom[-1][2] > 0, 120, "a goal driving the robot", sup)
        goal = executing()[0]

        def feedback() -> dict[str, str]:
            found = client.diagnostics.get("hdrqn_ros: /meta_controller")
            return {} if found is None else {kv.key: kv.value for kv in found.values}

        probe.until(lambda: "distance_remaining_m" in feedback(), 30, "the goal's feedback on /diagnostics", sup)
        assert float(feedback()["distance_remaining_m"]) > 0 and feedback()["number_of_recoveries"] == "0"
        assert feedback()["goal"].startswith("subgoal ") and feedback()["navigation"] == "action /navigate_to_pose"
        if stop == "deactivate":
            assert client.change("meta_controller", Transition.TRANSITION_DEACTIVATE)
        else:
            sup.kill("meta_controller", signal.SIGTERM)
        probe.until(lambda: probe.statuses[goal][-1] == STATUS_CANCELED, 30, "the goal cancelled", sup)
        probe.until(probe.at_rest, 30, "the robot at rest", sup)
        probe.mw.spin(timeout_s=2.0)
        assert probe.at_rest(30) and not executing(), "the robot stays still without its meta-controller"
    finally:
        codes = sup.stop()
    if stop == "sigterm":
        assert codes["meta_controller"] == 0, codes
