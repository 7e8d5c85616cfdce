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

import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")
pytest.importorskip("onnxruntime", reason="the shipped policy needs onnxruntime")

from hdrqn_ros.agents.specs import ALGO_SPECS, stack_subgoal  # noqa: E402
from hdrqn_ros.deploy.onnx_policy import OnnxPolicy  # noqa: E402
from hdrqn_ros.robot_graph import RobotRun, robot_processes, write_params  # noqa: E402
from hdrqn_ros.supervisor import ProcessSpec, Supervisor  # noqa: E402
from hdrqn_ros.training.learner import play  # noqa: E402

from test_graph import domain, read_jsonl  # noqa: E402, F401  (domain: a fixture)
from test_robot_nodes import Probe, finished  # noqa: E402

POLICY = Path(__file__).resolve().parents[1] / "policies" / "hdrqn-v2_gridworld-2goals"
"""The shipped policy: it visits the places, so its episodes turn, stop and vary (a random
checkpoint pushes one wall for 50 steps, which any drive reproduces)."""
SEED, EPISODES = 2, 3

NAV2_ROBOT = {"odom_frame": "odom", "map_to_odom": "[0.8, 0.4, 0.0]", "start_yaw": 0.3, "cmd_vel_timeout": 1.0,
              "real_time_factor": 10.0}
"""The loopback robot's Nav2 settings. ``map -> odom`` turns nothing here: the observation is
drawn in the costmap's frame (odom), and a turned one would differ from the simulator's view."""


class _Role:
    """One controller of the shipped policy, as the simulator's rollout acts with it."""

    def __init__(self, policy: OnnxPolicy, role: str):
        self.policy, self.role = policy, role

    def act(self, x, state):
        return self.policy.act(self.role, x, state)

    def initial_state(self, batch_size: int):
        return self.policy.initial_state(self.role, batch_size)


def simulated(episodes: int) -> tuple[list[tuple[int, bool]], list[int]]:
    """The shipped policy's first ``episodes`` in the simulator (layouts of :data:`SEED`, no
    fire): (steps, success) of each, and every action, in order."""
    policy = OnnxPolicy.load(POLICY)
    agent = SimpleNamespace(sub=_Role(policy, "sub"), meta=_Role(policy, "meta"), spec=ALGO_SPECS[policy.algo],
                            sub_input=stack_subgoal)
    cfg = SimpleNamespace(env=policy.env, env_kwargs={**policy.env_kwargs, "obstacles": False},
                          meta_state=policy.meta_state)
    actions = []
    sink = SimpleNamespace(write=lambda record: actions.append(int(record.action[0])))
    stats = play(agent, cfg, episodes, SEED, num_envs=1, sink=sink)
    return [(e.steps, bool(e.success)) for e in stats], actions[:sum(e.steps for e in stats)]


def start(tmp_path: Path, **overrides) -> tuple[Supervisor, Path]:
    """The robot graph in sub-drives with the shipped policy (``overrides``: parameters by node)."""
    log = tmp_path / "episodes.jsonl"
    run = RobotRun(algo="hdrqn-v2", env="hdrqn/GridWorld-2Goals-v0", view="5", policy=str(POLICY), mode="sub-drives",
                   episodes=EPISODES, seed=SEED, episode_log=str(log))
    params = write_params(run, tmp_path / "params.yaml")
    specs = [ProcessSpec(spec.name, spec.argv + [a for name, value in overrides.get(spec.name, {}).items()
                                                 for a in ("-p", f"{name}:={value}")], required=spec.required,
                         stack_dump_signal=spec.stack_dump_signal)
             for spec in robot_processes(run, params, hierarchical=True)]
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    return sup, log


def _values(probe: Probe, name: str) -> dict[str, str]:
    status = probe.diagnostics.get(f"hdrqn_ros: /{name}")
    return {} if status is None else {kv.key: kv.value for kv in status.values}


@pytest.mark.parametrize("drive", ["primitives", "commands"])
def test_sub_drives_equal_the_simulator_with_a_1s_deadman_a_start_yaw_and_map_to_odom(tmp_path, drive):
    probe = Probe()
    sup, log = start(tmp_path, loopback_robot=NAV2_ROBOT, sub_controller={"drive": drive, "pose_source": "tf"})
    try:
        probe.until(finished(sup), 240, f"{EPISODES} robot episodes", sup)
        probe.until(lambda: probe.cmd_vel and probe.cmd_vel[-1] == (0.0, 0.0, 0.0), 30, "the last zero command", sup)
        probe.until(lambda: "drive" in _values(probe, "sub_controller"), 30, "the sub-controller's diagnostics", sup)
        sub = _values(probe, "sub_controller")
    finally:
        codes = sup.stop()
        probe.close()
    assert codes["robot_environment"] == 0, codes
    robot = [(r["steps"], bool(r["success"])) for r in read_jsonl(log)]
    actions = [int(row["action"]) for row in probe.steps if row["t"] > 0]
    episodes, sim_actions = simulated(EPISODES)
    assert any(success for _, success in episodes) and len(set(sim_actions)) == 4, "the comparison means something"
    moves = [c for c in probe.cmd_vel if c != (0.0, 0.0, 0.0)]
    steps = sum(r[0] for r in robot)
    if drive == "commands":
        assert sub["drive"].startswith("one command per action")
        assert (robot, actions) != (episodes, sim_actions), "the control: one command per step under a 1 s " \
            "deadman, turned by the start yaw, must not reproduce the simulator"
        return
    assert robot == episodes, (robot, episodes, sub)
    assert actions == sim_actions
    assert len(moves) > 5 * steps, "commands stream through each primitive (a 1 s deadman would cut one)"
    assert sub["drive"] == "primitives from tf odom <- base_link at 20 Hz", sub
    assert "completed" in sub["primitives"] and sub["last_primitive"].startswith("move of one cell"), sub
    ended = [line.split("motion primitive: ", 1)[1] for line in
             sup.log_path("sub_controller").read_text().splitlines() if "motion primitive: " in line]
    assert len(ended) == steps and all(" completed: " in e or " blocked: " in e for e in ended), ended
    assert all(float(e.split(": ")[1].split(" m ")[0]) <= 0.011 for e in ended if " completed: " in e), ended
