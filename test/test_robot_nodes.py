"""A trained agent's nodes on the loopback robot, as real node processes (issue 26):
loopback_robot, robot_environment, critic, meta_controller and sub_controller on
simulated time, watched by a probe node on the standard topics (cmd_vel, goal_pose, odom).

- sub-drives: the robot's episodes are the simulator's, step for step (same layouts
  without fire, greedy agent), with one cmd_vel per step and a zero one at each episode's end;
- meta-only: one goal_pose per option, no cmd_vel;
- stop means stop: a zero command when the sub-controller is stopped and when its
  observation goes stale (the robot environment killed);
- bad input: startup mistakes exit 2 naming the problem; bad messages are logged and
  skipped, and the node goes on.
"""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.nodes import nav  # noqa: E402
from hdrqn_ros.nodes.qos import LATCHED_QOS, STEP_QOS, keep_last  # noqa: E402
from hdrqn_ros.protocol import wire  # noqa: E402
from hdrqn_ros.robot_graph import RobotRun, robot_processes, write_params  # noqa: E402
from hdrqn_ros.supervisor import ProcessSpec, Supervisor, python_command  # noqa: E402
from hdrqn_ros.training.learner import load_trained_agent, play  # noqa: E402

from ros_probe import RosProbe  # noqa: E402
from test_graph import ENV, read_jsonl, wait_for  # noqa: E402
from test_onnx_export import _make_checkpoint  # noqa: E402

SEED = 2
EPISODES = 3


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """An hDRQNv2 checkpoint whose weights are moved off their start (a deterministic greedy agent)."""
    path = tmp_path_factory.mktemp("robot") / "run" / "checkpoints" / "last.pt"
    _make_checkpoint(path, "hdrqn-v2", ENV, seed=41)
    return path


class Probe:
    """The test's own node on the robot's standard topics: every cmd_vel, goal_pose, odometry
    twist, subgoal and env_step it hears, in order."""

    def __init__(self):
        self.mw = RosProbe(["probe"])
        node = self.node = self.mw.create_node("probe")
        self.cmd_vel: list[tuple[float, float, float]] = []
        self.goal_poses: list[tuple[float, float]] = []
        self.odom_twist: list[tuple[float, float, float]] = []
        self.new_options = 0
        self.steps: list[dict] = []
        self.diagnostics: dict[str, object] = {}  # status name -> the latest DiagnosticStatus
        self.markers = None  # the latest MarkerArray
        node.create_subscription("diagnostic_msgs/msg/DiagnosticArray", "/diagnostics", lambda m: self.diagnostics.update(
            {s.name: s for s in m.status}))
        node.create_subscription("visualization_msgs/msg/MarkerArray", "/subgoal_markers",
                                 lambda m: setattr(self, "markers", m))
        # the probe counts every command: a history deep enough for a test thread that falls
        # behind on a loaded machine (ROS's default 10 lost 4 of 150 in a stress run)
        counted = keep_last(1000)
        node.create_subscription(nav.TWIST, "/cmd_vel", lambda m: self.cmd_vel.append(
            (m.linear.x, m.linear.y, m.angular.z)), counted)
        node.create_subscription(nav.POSE_STAMPED, "/goal_pose", lambda m: self.goal_poses.append(
            (m.pose.position.x, m.pose.position.y)), counted)
        # every navigate_to_pose goal the action server has known (its status array lists each
        # goal until its result expires; latched: transient local)
        self.goals: dict[bytes, int] = {}  # goal id -> its latest action_msgs/GoalStatus status
        node.create_subscription("action_msgs/msg/GoalStatusArray", "/navigate_to_pose/_action/status",
                                 lambda m: self.goals.update({bytes(s.goal_info.goal_id.uuid): s.status
                                                              for s in m.status_list}), LATCHED_QOS)
        node.create_subscription(nav.POSE_TYPES["odometry"], "/odom", lambda m: self.odom_twist.append(
            (m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.angular.z)))
        node.create_subscription(wire.INTS, "/subgoal", self._on_subgoal, STEP_QOS)
        node.create_subscription(wire.FLOATS, "/env_step", lambda m: self.steps.append(
            wire.read_record(m, wire.STEP_FIELDS)), STEP_QOS)

    def _on_subgoal(self, msg) -> None:
        self.new_options += int(wire.read_records(msg, wire.SUBGOAL_FIELDS, np.int64)[0]["new_option"])

    def until(self, cond, timeout: float, what: str, sup: Supervisor) -> None:
        end = time.monotonic() + timeout
        while not cond():
            sup.poll()
            assert time.monotonic() < end, f"timed out after {timeout} s waiting for {what}: {sup.returncodes}"
            self.mw.spin(timeout_s=0.1)

    def spin_until(self, cond, timeout: float) -> bool:
        """Spin until ``cond()`` holds or ``timeout`` seconds pass; whether it holds."""
        end = time.monotonic() + timeout
        while not cond() and time.monotonic() < end:
            self.mw.spin(timeout_s=0.1)
        return cond()

    def close(self) -> None:
        self.mw.shutdown()


def start(tmp_path: Path, checkpoint: Path, mode: str, episodes: int = EPISODES, managed: tuple[str, ...] = (),
          **overrides) -> tuple[Supervisor, Path]:
    """The robot graph's processes for ``checkpoint`` (``overrides``: extra parameters by node;
    ``managed``: nodes started as managed nodes)."""
    log = tmp_path / "episodes.jsonl"
    run = RobotRun(algo="hdrqn-v2", env=ENV, view="5", checkpoint=str(checkpoint), mode=mode, episodes=episodes,
                   seed=SEED, real_time_factor=40.0, episode_log=str(log))
    params = write_params(run, tmp_path / "params.yaml")
    specs = []
    for spec in robot_processes(run, params, hierarchical=True, managed=managed):
        extra = [f"{name}:={value}" for name, value in overrides.get(spec.name, {}).items()]
        specs.append(ProcessSpec(spec.name, spec.argv + [a for item in extra for a in ("-p", item)],
                                 required=spec.required, stack_dump_signal=spec.stack_dump_signal))
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    return sup, log


def finished(sup: Supervisor):
    """The robot environment ran its episodes and exited."""
    return lambda: sup.returncodes["robot_environment"] is not None


def test_sub_drives_the_simulators_episodes_on_the_nav2_like_robot(tmp_path, checkpoint, domain):
    """``hdrqn robot``'s sub-drives as it ships: the loopback robot as Nav2 ships a robot (tf
    with a map -> odom offset, start yaw 0.3 rad, inflated costmaps in odom sent as updates,
    a 1 s deadman) and each action a motion primitive streamed on cmd_vel: the simulator's
    episodes, step for step."""
    probe = Probe()
    sup, log = start(tmp_path, checkpoint, "sub-drives")
    try:
        def acting() -> bool:
            sub = probe.diagnostics.get("hdrqn_ros: /sub_controller")
            return sub is not None and any(kv.key == "decisions_per_s" and float(kv.value) > 0 for kv in sub.values)

        probe.until(lambda: len(probe.diagnostics) >= 3 and probe.markers is not None and acting(), 120,
                    f"the diagnostics of every deployed node and the markers ({sorted(probe.diagnostics)})", sup)
        running = dict(probe.diagnostics)
        markers = probe.markers
        probe.until(finished(sup), 240, f"{EPISODES} robot episodes", sup)
        probe.until(lambda: probe.cmd_vel and probe.cmd_vel[-1] == (0.0, 0.0, 0.0), 30, "the last zero command", sup)
        probe.until(lambda: probe.odom_twist and probe.odom_twist[-1] == (0.0, 0.0, 0.0), 30, "the robot at rest", sup)
    finally:
        codes = sup.stop()
        probe.close()
    assert codes["robot_environment"] == 0, codes
    robot = read_jsonl(log)
    cfg, agent = load_trained_agent(checkpoint)
    cfg = cfg.model_copy(update={"env_kwargs": {**cfg.env_kwargs, "obstacles": False}})
    simulated = play(agent, cfg, EPISODES, SEED, num_envs=1)
    assert [(r["steps"], r["success"]) for r in robot] == [(e.steps, e.success) for e in simulated]
    moves = [c for c in probe.cmd_vel if c != (0.0, 0.0, 0.0)]
    assert len(moves) > sum(r["steps"] for r in robot), "commands streamed through each primitive"
    assert len(probe.cmd_vel) - len(moves) >= EPISODES, "a zero command at each primitive's end"
    assert probe.goal_poses == []
    values = {name: {kv.key: kv.value for kv in status.values} for name, status in running.items()}
    sub = values["hdrqn_ros: /sub_controller"]
    assert sub["policy"].startswith(f"checkpoint {checkpoint} sha256:") and float(sub["decisions_per_s"]) > 0
    assert float(sub["decision_ms_median"]) > 0 and "episodes" in values["hdrqn_ros: /robot_environment"]
    assert "hdrqn_ros: /meta_controller" in values
    places = [m for m in markers.markers if m.ns == "hdrqn_places"]
    assert len(places) == 2 and {m.header.frame_id for m in markers.markers} == {"map"}
    assert any(m.ns == "hdrqn_subgoal" and m.text.startswith("subgoal: ") for m in markers.markers)


@pytest.mark.parametrize("cut_short", [False, True], ids=["navigator-arrives", "options-time-out"])
def test_meta_only_sends_one_navigation_goal_per_option_and_no_cmd_vel(tmp_path, checkpoint, domain, cut_short):
    """``options-time-out``: a navigator too slow to get anywhere and an ``option_timeout``
    below the step period: every option ends at its next step, away from the places. hDRQNv2's
    meta-controller then needs the sub-controller's LSTM state for a step that is no decision
    point; before, it waited for it for ever (the robot stood still, seen once in a stress run
    where a loaded start-up let the clock run free past the 12 s timeout)."""
    probe = Probe()
    slow = {"critic": {"option_timeout": 1.0}, "loopback_robot": {"nav_speed": 0.01}} if cut_short else \
        {"critic": {"option_timeout": 12.0}}
    sup, log = start(tmp_path, checkpoint, "meta-only", **slow)
    try:
        probe.until(finished(sup), 240, f"{EPISODES} robot episodes", sup)
        probe.until(lambda: len(probe.goals) == probe.new_options, 30, "a navigate_to_pose goal for every option",
                    sup)
    finally:
        codes = sup.stop()
        probe.close()
    assert codes["robot_environment"] == 0, codes
    assert probe.new_options >= EPISODES and len(probe.goals) == probe.new_options
    assert probe.cmd_vel == [] and probe.goal_poses == []
    episodes = read_jsonl(log)
    if cut_short:
        # the robot hardly moves, so the episodes run to the step limit through options that time out
        assert [e["steps"] for e in episodes] == [50] * EPISODES, episodes
        assert probe.new_options > EPISODES + sum(len(e["visits"]) for e in episodes), (probe.new_options, episodes)
    else:
        assert any(e["visits"] for e in episodes), "the navigator reached the places chosen"


@pytest.mark.parametrize("stop", ["sigterm", "stale"])
def test_stop_means_a_zero_command(tmp_path, checkpoint, domain, stop):
    """The sub-controller stopped (SIGTERM), or its observation stale (the robot environment
    killed): the last cmd_vel is the zero one and the robot stands still."""
    probe = Probe()
    sup, log = start(tmp_path, checkpoint, "sub-drives", episodes=50, loopback_robot={"lockstep_timeout": 2.0},
                     sub_controller={"stale_after_s": 5.0})
    try:
        probe.until(lambda: sum(c != (0.0, 0.0, 0.0) for c in probe.cmd_vel) >= 3, 240, "the robot driving", sup)
        sup.kill("sub_controller" if stop == "sigterm" else "robot_environment",
                 signal.SIGTERM if stop == "sigterm" else signal.SIGKILL)
        probe.until(lambda: probe.cmd_vel[-1] == (0.0, 0.0, 0.0), 60, "a zero command", sup)
        count = len(probe.odom_twist)
        probe.until(lambda: len(probe.odom_twist) > count + 30 and probe.odom_twist[-1] == (0.0, 0.0, 0.0), 60,
                    "the robot at rest", sup)
    finally:
        sup.stop()
        probe.close()
    sub_log = (tmp_path / "logs" / "sub_controller.log").read_text()
    if stop == "stale":
        assert "stale_after_s" in sub_log, sub_log[-2000:]


def run_node(tmp_path: Path, name: str, *params: str, timeout: float = 120) -> tuple[int, str]:
    from hdrqn_ros.robot_graph import NODE_MODULES

    argv = python_command(NODE_MODULES[name]) + ["--ros-args"]
    for param in params:
        argv += ["-p", param]
    sup = Supervisor([ProcessSpec(name, argv)], log_dir=tmp_path)
    sup.start()
    try:
        wait_for(lambda: sup.returncodes[name] is not None, timeout, f"{name} to exit", sup)
    finally:
        codes = sup.stop()
    return codes[name], (tmp_path / f"{name}.log").read_text()


@pytest.mark.parametrize("params, problem", [
    (["subgoal_poses_topic:=places", "pose_type:=gps"], "pose_type must be one of"),
    ([], "exactly one"),
    (["subgoal_poses_topic:=places", "step_period:=0.0"], "step_period must be > 0"),
    (["subgoal_table:=TABLE3"], "3 entries but the agent has 2"),
])
def test_robot_environment_startup_mistakes_exit_2(tmp_path, domain, params, problem):
    table = tmp_path / "three.yaml"
    table.write_text("subgoals: [{x: 0, y: 0}, {x: 1, y: 0}, {x: 2, y: 0}]\n")
    code, out = run_node(tmp_path, "robot_environment", *(p.replace("TABLE3", str(table)) for p in params))
    assert code == 2 and problem in out, out


def test_bad_messages_are_logged_and_skipped(tmp_path, domain):
    """A pose in a frame tf cannot join to the places' is a wait naming both frames; a
    non-finite pose and a costmap smaller than the view are refused with a reason; the node
    goes on and starts an episode from good inputs."""
    table = tmp_path / "places.yaml"
    table.write_text("frame_id: map\nsubgoals: [{x: 1.0, y: 1.0}, {x: 2.0, y: 1.0}]\n")
    sup = Supervisor([ProcessSpec("robot_environment", [sys.executable, "-m", "hdrqn_ros.nodes.robot_environment",
                                                        "--ros-args", "-p", f"subgoal_table:={table}",
                                                        "-p", "costmap_topic:=/costmap", "-p", "pose_topic:=/odom"])],
                     log_dir=tmp_path)
    mw = RosProbe(["probe"])
    node = mw.create_node("probe")
    steps = []
    node.create_subscription(wire.FLOATS, "/env_step", steps.append, STEP_QOS)
    pose_pub = node.create_publisher(nav.POSE_TYPES["odometry"], "/odom")
    map_pub = node.create_publisher(nav.OCCUPANCY_GRID, "/costmap", LATCHED_QOS)
    log = tmp_path / "robot_environment.log"

    def odom(frame: str, x: float):
        msg = node.msg(nav.POSE_TYPES["odometry"])()
        msg.header.frame_id, msg.pose.pose.position.x, msg.pose.pose.position.y = frame, x, 1.5
        msg.pose.pose.orientation.w = 1.0
        return msg

    def costmap(cells: int):
        msg = node.msg(nav.OCCUPANCY_GRID)()
        msg.header.frame_id = "map"
        msg.info.width = msg.info.height = cells
        msg.info.resolution = 0.05
        msg.data = node.pack(np.zeros(cells * cells, np.int8))
        return msg

    sup.start()
    try:
        def seen(text: str):
            return log.exists() and text in log.read_text()

        for msg, text in ((odom("odom", 1.5), "no transform odom <- map"),
                          (odom("map", float("nan")), "not finite"), (costmap(10), "less than the view")):
            publish = pose_pub if text != "less than the view" else map_pub
            end = time.monotonic() + 60
            while not seen(text):
                sup.poll()
                assert time.monotonic() < end and sup.returncodes["robot_environment"] is None, log.read_text()
                map_pub.publish(costmap(60))  # fresh: the pose is what the node waits for
                publish.publish(msg)
                mw.spin(timeout_s=0.2)
        map_pub.publish(costmap(60))
        end = time.monotonic() + 60
        while not steps:
            assert time.monotonic() < end, log.read_text()
            pose_pub.publish(odom("map", 1.5))
            mw.spin(timeout_s=0.2)
    finally:
        codes = sup.stop()
        mw.shutdown()
    assert codes["robot_environment"] == 0, codes
    first = wire.read_record(steps[0], wire.STEP_FIELDS)
    assert first["t"] == 0 and first["episode"] == 0


def test_episodes_start_and_stop_on_request(tmp_path, checkpoint, domain):
    """``autostart`` off: nothing steps until ``~/start_episode``; ``~/stop_episode`` ends the
    running episode (truncated) at its next step, and no other starts."""
    from std_srvs.srv import Trigger

    probe = Probe()
    sup, log = start(tmp_path, checkpoint, "sub-drives", episodes=5, robot_environment={"autostart": False})
    clients = {name: probe.node.create_client(Trigger, f"/robot_environment/{name}")
               for name in ("start_episode", "stop_episode")}

    def call(name: str):
        future = clients[name].call_async(Trigger.Request())
        probe.until(future.done, 60, f"the answer of {name}", sup)
        return future.result()

    try:
        probe.until(lambda: all(c.service_is_ready() for c in clients.values()), 120, "the services", sup)
        probe.mw.spin(timeout_s=2.0)
        assert probe.steps == [], "no episode before start_episode"
        assert call("start_episode").success
        probe.until(lambda: len(probe.steps) >= 3, 120, "the episode's steps", sup)
        assert call("stop_episode").success
        probe.until(lambda: log.exists() and read_jsonl(log), 60, "the stopped episode's end", sup)
        ended = len(probe.steps)
        probe.mw.spin(timeout_s=3.0)
    finally:
        sup.stop()
        probe.close()
    assert probe.steps[ended - 1]["truncated"] == 1 and len(probe.steps) == ended
    assert read_jsonl(log)[0]["steps"] < 50


def test_param_set_on_the_robot_nodes(tmp_path, checkpoint, domain):
    """``ros2 param set`` on the robot's nodes: a new ``step_period`` holds from the next step
    (the step keys are simulated ns); read-only and out-of-range values are refused with a reason."""
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    probe = Probe()
    sup, _ = start(tmp_path, checkpoint, "sub-drives", episodes=50)

    def result(future, what: str):
        probe.until(future.done, 30, what, sup)
        return future.result()

    try:
        env = AsyncParameterClient(probe.node, "/robot_environment")
        robot = AsyncParameterClient(probe.node, "/loopback_robot")
        probe.until(lambda: env.services_are_ready() and robot.services_are_ready(), 120, "parameter services", sup)
        probe.until(lambda: len(probe.steps) >= 3, 120, "the robot stepping", sup)
        for client, name, value, words in ((env, "pose_topic", "/elsewhere", "read-only"),
                                           (env, "goal_tolerance", -1.0, "must be > 0"),
                                           (env, "lethal", 500, "out of range"),
                                           (robot, "lockstep", "off", "read-only"),
                                           (robot, "nav_speed", 0.0, "must be > 0")):
            outcome = result(client.set_parameters([Parameter(name, value=value)]), name).results[0]
            assert not outcome.successful and words in outcome.reason and name in outcome.reason, outcome.reason
        for client in (env, robot):  # the loopback robot's lockstep waits for steps at the same period
            assert result(client.set_parameters([Parameter("step_period", value=5.0)]), "step_period").results[0].successful
        seen = len(probe.steps)
        probe.until(lambda: len(probe.steps) >= seen + 6, 120, "steps after the change", sup)
    finally:
        sup.stop()
        probe.close()
    gaps = {int(b["key"] - a["key"]) for a, b in zip(probe.steps[seen + 1:], probe.steps[seen + 2:])
            if b["prev_key"] == a["key"]}
    assert gaps == {5 * 10**9}, gaps


SHIPPED = Path(__file__).resolve().parents[1] / "policies" / "hdrqn-v2_gridworld-2goals"


def test_the_shipped_trained_policy_visits_the_goals_in_order(tmp_path, domain):
    """The trained hDRQNv2 the package ships (ONNX, no torch in the controllers) drives the
    loopback robot through cmd_vel: on the seed-0 layouts it visits blue then green in each
    episode, in the steps the simulator takes with the checkpoint it was exported from
    (4, 8, 9: the lockstep robot is deterministic)."""
    log = tmp_path / "episodes.jsonl"
    run = RobotRun(algo="hdrqn-v2", env=ENV, view="5", policy=str(SHIPPED), episodes=3, seed=0,
                   real_time_factor=40.0, episode_log=str(log))
    sup = Supervisor(robot_processes(run, write_params(run, tmp_path / "params.yaml"), hierarchical=True),
                     log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    try:
        wait_for(lambda: sup.returncodes["robot_environment"] is not None, 240, "3 robot episodes", sup)
    finally:
        codes = sup.stop()
    assert codes["robot_environment"] == 0, codes
    assert [(r["visits"], r["success"], r["steps"]) for r in read_jsonl(log)] == [([0, 1], True, 4),
                                                                                   ([0, 1], True, 8),
                                                                                   ([0, 1], True, 9)]


def test_robot_episodes_recorded_then_trained_on_offline(tmp_path, domain):
    """``hdrqn robot --record``: a learner node records every robot episode to a bag, which
    ``hdrqn train --from-bag`` trains on."""
    bag, out = tmp_path / "bag", tmp_path / "robot"

    def hdrqn(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", *argv], capture_output=True, text=True,
                              timeout=600)

    ran = hdrqn("robot", "--policy", str(SHIPPED), "--episodes", "5", "--record", str(bag), "--out", str(out),
                "--real-time-factor", "40")
    assert ran.returncode == 0, ran.stderr[-3000:]
    info = json.loads(hdrqn("bag", "info", str(bag), "--json").stdout)
    # every episode whole: the robot environment steps on the learner's credit, which it grants
    # once each of its subscriptions has a publisher and it holds the first step's answers
    assert info["episodes"]["/"]["episodes"] == 5 and info["episodes"]["/"]["incomplete"] == 0, info["episodes"]
    trained = hdrqn("train", "--from-bag", str(bag), "--out", str(tmp_path / "offline"), "--updates", "20",
                    "--no-progress")
    assert trained.returncode == 0 and "done: 20 updates on 5 episodes" in trained.stdout, trained.stderr[-3000:]
    assert "5 episodes (0 incomplete ones left out)" in trained.stderr, trained.stderr[-3000:]
