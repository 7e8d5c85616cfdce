"""Sub-drives with exact motion primitives on the Nav2-like loopback robot (issue 38 item 3), real processes.

The loopback robot as Nav2 ships a robot: a 1 s velocity deadman (the velocity smoother's
``velocity_timeout``), tf ``map -> odom -> base_link`` with ``map -> odom`` away from the
identity, the robot starting each episode at a yaw of 0.3 rad, the local costmap in
``odom``. With ``drive: primitives`` (measured from tf in the observation's frame) the
robot's episodes are the simulator's, step for step, and each primitive's outcome is on
``/diagnostics``; the control, today's one command per step (``drive: commands``), moves
half a cell per step along a turned axis and does not reproduce them.
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")
pytest.importorskip("onnxruntime", reason="the shipped policy needs onnxruntime")

from hdrqn_ros.deploy.onnx_agent import OnnxAgent  # noqa: E402
from hdrqn_ros.deploy.onnx_policy import OnnxPolicy  # noqa: E402
from hdrqn_ros.robot_graph import HOLONOMIC_ACTIONS, RobotRun, robot_processes, write_params  # noqa: E402
from hdrqn_ros.supervisor import Supervisor  # noqa: E402
from hdrqn_ros.training.learner import play  # noqa: E402

from test_graph import read_jsonl  # noqa: E402
from test_robot_nodes import Probe, finished  # noqa: E402

POLICY = Path(__file__).resolve().parents[1] / "policies" / "hdrqn-v2_gridworld-2goals"
"""The shipped policy: it visits the places, so its episodes turn, stop and vary (a random
checkpoint pushes one wall for 50 steps, which any drive reproduces)."""
SEED, EPISODES = 2, 3
HOLONOMIC, DIFF = HOLONOMIC_ACTIONS, HOLONOMIC_ACTIONS.with_name("actions.yaml")
"""The simulator's moves (north-up, holonomic); forward, back, turn left, turn right (heading-up)."""

NAV2_ROBOT = {"real_time_factor": 20.0}
"""The loopback robot as the robot graph sets it up (:data:`~hdrqn_ros.robot_graph.NAV2_LOOPBACK`:
``map -> odom`` at (0.8 m, 0.4 m, 0.2 rad), the local costmap in ``odom``, the 1 s deadman;
start yaw 0.3 rad; ``lockstep: control``: while the robot drives, each tick of its clock waits
for the next command, so the control loop, closed across processes on the simulated clock,
does not depend on how loaded the machine is), at 20x real time."""


def simulated(episodes: int) -> tuple[list[tuple[int, bool]], list[int]]:
    """The shipped policy's first ``episodes`` in the simulator (layouts of :data:`SEED`, no
    fire): (steps, success) of each, and every action, in order."""
    agent = OnnxAgent(OnnxPolicy.load(POLICY))
    actions = []
    sink = SimpleNamespace(write=lambda record: actions.append(int(record.action[0])))
    stats = play(agent, agent.settings(obstacles=False), episodes, SEED, num_envs=1, sink=sink)
    return [(e.steps, bool(e.success)) for e in stats], actions[:sum(e.steps for e in stats)]


def start(tmp_path: Path, episodes: int = EPISODES, action_table: Path = HOLONOMIC,
          **overrides) -> tuple[Supervisor, Path]:
    """The robot graph in sub-drives with the shipped policy (``overrides``: parameters by
    node, written into its parameters file, where they win over the graph's own)."""
    log = tmp_path / "episodes.jsonl"
    run = RobotRun(algo="hdrqn-v2", env="hdrqn/GridWorld-2Goals-v0", view="5", policy=str(POLICY), mode="sub-drives",
                   episodes=episodes, seed=SEED, episode_log=str(log), action_table=str(action_table))
    params = write_params(run, tmp_path / "params.yaml")
    doc = yaml.safe_load(params.read_text())
    for node, values in overrides.items():
        doc.setdefault(f"/**/{node}", {"ros__parameters": {}})["ros__parameters"].update(values)
    params.write_text(yaml.safe_dump(doc, sort_keys=False))
    sup = Supervisor(robot_processes(run, params, hierarchical=True), log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    return sup, log


def _values(probe: Probe, name: str) -> dict[str, str]:
    status = probe.diagnostics.get(f"hdrqn_ros: /{name}")
    return {} if status is None else {kv.key: kv.value for kv in status.values}


def _outcomes(sup: Supervisor) -> list[str]:
    """Each primitive's outcome as the sub-controller logged it."""
    return [line.split("motion primitive: ", 1)[1] for line in sup.log_path("sub_controller").read_text().splitlines()
            if "motion primitive: " in line]


def _metres(outcome: str) -> float:
    return float(outcome.split(": ")[1].split(" m ")[0])


def _degrees(outcome: str) -> float:
    return float(outcome.split(" m and ")[1].split(" deg ")[0])


@pytest.mark.parametrize("drive, pose_source", [("primitives", "tf"), ("primitives", "odometry"),
                                                ("commands", "tf")])
def test_sub_drives_equal_the_simulator_with_a_1s_deadman_a_start_yaw_and_map_to_odom(tmp_path, domain, drive,
                                                                                      pose_source):
    probe = Probe()
    lockstep = "control" if drive == "primitives" else "cmd_vel"  # one command per step: nothing per tick
    # odometry measures in odom: north-up moves along the map's axes need odom unturned from map
    unturned = {"map_to_odom": [0.8, 0.4, 0.0]} if pose_source == "odometry" else {}
    sup, log = start(tmp_path, loopback_robot={**NAV2_ROBOT, "lockstep": lockstep, **unturned},
                     sub_controller={"drive": drive, "pose_source": pose_source})
    try:
        probe.until(finished(sup), 240, f"{EPISODES} robot episodes", sup)
        last = read_jsonl(log)[-1]["steps"]  # the probe's queue may still hold the last episode's steps
        # a step published just before the robot environment exits may never arrive: the check
        # below asks for every step of all but one episode, so this wait only lets the queue drain
        probe.spin_until(lambda: any(r["episode"] == EPISODES - 1 and r["t"] == last for r in probe.steps), 30)
        probe.until(lambda: probe.cmd_vel and probe.cmd_vel[-1] == (0.0, 0.0, 0.0), 30, "the last zero command", sup)
        probe.until(lambda: "drive" in _values(probe, "sub_controller"), 30, "the sub-controller's diagnostics", sup)
        sub = _values(probe, "sub_controller")
    finally:
        codes = sup.stop()
        probe.close()
    assert codes["robot_environment"] == 0, codes
    robot = [(r["steps"], bool(r["success"])) for r in read_jsonl(log)]
    episodes, sim_actions = simulated(EPISODES)
    assert any(success for _, success in episodes) and len(set(sim_actions)) == 4, "the comparison means something"
    heard: dict[int, dict[int, int]] = {}  # episode -> t -> the action before step t, as the probe heard them
    for row in probe.steps:
        if row["t"] > 0:
            heard.setdefault(int(row["episode"]), {})[int(row["t"])] = int(row["action"])
    bounds = np.cumsum([0] + [n for n, _ in episodes])
    complete = [e for e, (n, _) in enumerate(episodes) if sorted(heard.get(e, {})) == list(range(1, n + 1))]
    moves = [c for c in probe.cmd_vel if c != (0.0, 0.0, 0.0)]
    steps = sum(r[0] for r in robot)
    if drive == "commands":
        assert sub["drive"].startswith("one command per action")
        assert robot != episodes, "the control: one command per step under a 1 s deadman, turned by the start " \
            "yaw, must not reproduce the simulator"
        return
    assert robot == episodes, (robot, episodes, sub)
    # each step is due one step_period after the previous one's key, for the robot environment and the
    # lockstep robot alike; an episode's first step, at the time of the step before it, has a key 1 ns
    # later, so the second step comes at the robot's next 0.1 s tick (before: 2.5 s - 1 ns or 2.6 s - 1 ns,
    # whichever of the two schedules won)
    keys = {(int(r["episode"]), int(r["t"])): int(r["key"]) for r in probe.steps}  # ROS time of each step, ns
    apart = {t == 1: set() for t in (1, 2)}
    for e, t in keys:
        if (e, t - 1) in keys:
            apart[t == 1].add(keys[e, t] - keys[e, t - 1])
    assert apart[True] <= {int(2.6e9) - 1} and apart[False] == {int(2.5e9)}, apart
    # the probe may join after the first steps, and the last step may be lost when its publisher exits
    assert complete, "the probe heard no episode whole"
    for e in complete:  # a probe that joins late misses the first steps
        assert [heard[e][t] for t in range(1, episodes[e][0] + 1)] == sim_actions[bounds[e]:bounds[e + 1]], e
    assert len(moves) > 5 * steps, "commands stream through each primitive (a 1 s deadman would cut one)"
    assert sub["drive"] == ("primitives from tf map <- base_link at 20 Hz" if pose_source == "tf" else
                            "primitives from odometry on /odom at 20 Hz"), sub
    warned = "primitives from odometry move along 'odom''s axes and the observation is drawn in 'map'"
    assert (warned in sup.log_path("sub_controller").read_text()) == (pose_source == "odometry")
    assert "completed" in sub["primitives"] and sub["last_primitive"].startswith("move of one cell"), sub
    ended = _outcomes(sup)
    assert len(ended) == steps and all(" completed: " in e or " blocked: " in e for e in ended), ended
    assert all(_metres(e) <= 0.011 for e in ended if " completed: " in e), ended


def test_differential_drive_turns_exactly_90_degrees_and_moves_a_cell(tmp_path, domain):
    """The heading-up table on a differential-drive robot (start yaw 0.3 rad, 1 s deadman):
    every turn ends within the angle tolerance (1.15 degrees) of its 90 degrees, every move at
    its cell (0.01 m along the way) or against a wall; none times out."""
    probe = Probe()
    sup, log = start(tmp_path, episodes=1, action_table=DIFF, loopback_robot={**NAV2_ROBOT, "drive": "diff"},
                     robot_environment={"heading_up": True})
    try:
        probe.until(finished(sup), 240, "one robot episode", sup)
        probe.until(lambda: probe.cmd_vel and probe.cmd_vel[-1] == (0.0, 0.0, 0.0), 30, "the last zero command", sup)
    finally:
        codes = sup.stop()
        probe.close()
    assert codes["robot_environment"] == 0, codes
    ended = _outcomes(sup)
    turns, moves = [e for e in ended if e.startswith("turn")], [e for e in ended if e.startswith("move")]
    assert len(ended) == read_jsonl(log)[0]["steps"] and turns and moves, ended
    assert all(" completed: " in e and _degrees(e) <= 1.2 for e in turns), turns
    # within the tolerance along the way; sideways a differential drive cannot close what the
    # moves before left (short by up to a tolerance, then turned across; stopped by a wall): 0.05 m in all
    assert all((" completed: " in e and _metres(e) <= 0.05) or " blocked: " in e for e in moves), moves
    assert all(cmd[1] == 0.0 for cmd in probe.cmd_vel), "a differential drive gets no sideways command"
