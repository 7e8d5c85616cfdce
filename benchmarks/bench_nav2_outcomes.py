"""Two Nav2 outcomes on the Nav2-like loopback robot with the shipped policy (issue 38).

1. **An unreachable place ends on ABORTED.** Meta-only, both places in walls (the subgoal
   table of ``test_an_option_to_an_unreachable_place_ends_at_the_next_step``), for each
   ``--max-steps`` (0: the robot environment's default, 50): with ``navigation: action`` and
   the critic's ``navigation_outcome`` (each goal's ABORTED ends its option at the next step)
   against ``navigation: topic`` (a ``goal_pose``, no outcome: each option waits the critic's
   ``option_timeout``), and against that wait computed. Per run: each episode's steps,
   simulated and wall seconds, options and their simulated and wall seconds, and the goals'
   final statuses.
2. **Standing still 60 s resumes at once.** Each ``--stand-modes`` mode, the robot
   environment with ``autostart: false``: one episode by ``~/start_episode``; the robot stands
   ``--stand-s`` wall seconds (the loopback robot's clock runs on; counted: ``/amcl_pose``,
   full costmaps, costmap updates, the largest ``/odom`` speed); ``~/start_episode`` again:
   the wall and simulated seconds from the call to the new episode's first step (its key: the
   step times' phase on the loopback robot's 0.1 s ticks), against the first episode's, and
   the new episode to its end; and the same two episodes without the stand (``stand_s`` 0,
   the next ``~/start_episode`` at once: the loopback robot's clock still held at the last step).

Simulated seconds come from the step keys (ROS time with ``use_sim_time``) and ``/clock``;
wall seconds from when this process received each message. Prints one JSON object on
stdout, progress on stderr; node logs go to ``--out``. Run on its own DDS domain:

    ROS_DOMAIN_ID=92 python benchmarks/bench_nav2_outcomes.py [--episodes 3] [--max-steps 12 0]
        [--stand-s 60] [--stand-modes sub-drives meta-only] [--out runs/bench_nav2_outcomes]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
POLICY = ROOT / "policies" / "hdrqn-v2_gridworld-2goals"
ENV = "hdrqn/GridWorld-2Goals-v0"
STEP_S = 2.5
RTF = 20.0
OPTION_TIMEOUT_S = 30.0
DEFAULT_MAX_STEPS = 50
"""The robot environment's step limit when ``max_steps`` is 0."""
STATUS_NAMES = {4: "SUCCEEDED", 5: "CANCELED", 6: "ABORTED"}
"""action_msgs/GoalStatus's final statuses."""


def cell_centre(row: int, col: int) -> tuple[float, float]:
    """The gridworld map cell's centre (m, map frame; 0.25 m cells, row 0 at the top)."""
    return (col + 0.5) * 0.25, (10 - row + 0.5) * 0.25


def say(*words) -> None:
    print(*words, file=sys.stderr, flush=True)


class Probe:
    """This process's node: the steps, options, goal statuses, clock and robot outputs, each
    with the wall time (monotonic s) it arrived; a ``~/start_episode`` client."""

    def __init__(self):
        from ros_probe import RosProbe
        from std_srvs.srv import Trigger

        from hdrqn_ros.nodes import nav
        from hdrqn_ros.nodes.qos import CLOCK_QOS, LATCHED_QOS, STEP_QOS
        from hdrqn_ros.protocol import wire

        self.wire, self.trigger = wire, Trigger
        self.mw = RosProbe(["bench_nav2_outcomes"])
        node = self.node = self.mw.create_node("bench_nav2_outcomes")
        self.steps: list[dict] = []  # env_step records (+ "wall"), each key once
        self.options: list[tuple[int, float]] = []  # (key, wall) of each new option
        self.goals: dict[bytes, int] = {}  # goal id -> its latest status
        self.clock_ns = 0
        self.heard = {"amcl_pose": [], "costmap": [], "costmap_updates": []}  # wall times
        self.odom: list[tuple[float, float]] = []  # (wall, |v| + |w|)
        node.create_subscription(wire.FLOATS, "/" + wire.ENV_STEP, self._on_step, STEP_QOS)
        node.create_subscription(wire.INTS, "/" + wire.SUBGOAL, self._on_subgoal, STEP_QOS)
        node.create_subscription("action_msgs/msg/GoalStatusArray", "/navigate_to_pose/_action/status",
                                 self._on_status, 100)
        node.create_subscription(wire.CLOCK_TYPE, wire.CLOCK, self._on_clock, CLOCK_QOS)
        node.create_subscription(nav.POSE_TYPES["odometry"], "/odom", self._on_odom, 10)
        for name, msg_type in (("amcl_pose", "geometry_msgs/msg/PoseWithCovarianceStamped"),
                               ("costmap", nav.OCCUPANCY_GRID),
                               ("costmap_updates", "map_msgs/msg/OccupancyGridUpdate")):
            topic = "/amcl_pose" if name == "amcl_pose" else f"/local_costmap/{name}"
            node.create_subscription(msg_type, topic, lambda _m, name=name: self.heard[name].append(time.monotonic()),
                                     LATCHED_QOS)
        self.start_client = node.create_client(Trigger, "/robot_environment/start_episode")

    def _on_step(self, msg) -> None:
        step = self.wire.read_record(msg, self.wire.STEP_FIELDS)
        if self.steps and int(step["key"]) <= int(self.steps[-1]["key"]):
            return  # re-published
        self.steps.append({**step, "wall": time.monotonic()})

    def _on_subgoal(self, msg) -> None:
        record = self.wire.read_records(msg, self.wire.SUBGOAL_FIELDS, np.int64)[0]
        if record["new_option"]:
            self.options.append((int(record["key"]), time.monotonic()))

    def _on_status(self, msg) -> None:
        for status in msg.status_list:
            self.goals[bytes(status.goal_info.goal_id.uuid)] = status.status

    def _on_clock(self, msg) -> None:
        self.clock_ns = msg.clock.sec * 10**9 + msg.clock.nanosec

    def _on_odom(self, msg) -> None:
        twist = msg.twist.twist
        self.odom.append((time.monotonic(), math.hypot(twist.linear.x, twist.linear.y) + abs(twist.angular.z)))

    def until(self, cond, timeout: float, what: str, sup) -> None:
        """Spin until ``cond()``; an error naming ``what`` after ``timeout`` wall seconds, or when the
        robot environment exited first."""
        end = time.monotonic() + timeout
        while True:
            sup.poll()
            if cond():
                return
            if sup.returncodes["robot_environment"] is not None:
                raise RuntimeError(f"the robot environment exited while waiting for {what}: {sup.returncodes}")
            if time.monotonic() > end:
                raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}: exit codes {sup.returncodes}")
            self.mw.spin(timeout_s=0.05)

    def controllers_up(self) -> bool:
        """The critic, meta-controller and sub-controller publish (their policies loaded)."""
        return all(self.node.count_publishers("/" + topic) for topic in (self.wire.CRITIC, self.wire.SUBGOAL,
                                                                         self.wire.ACTION))

    def start_episode(self, sup) -> tuple[float, int]:
        """Call ``~/start_episode``: (wall time of the call, simulated ns on /clock then)."""
        self.until(self.start_client.service_is_ready, 120, "the robot environment's ~/start_episode", sup)
        called, clock_ns = time.monotonic(), self.clock_ns
        future = self.start_client.call_async(self.trigger.Request())
        self.until(future.done, 60, "~/start_episode's answer", sup)
        if not future.result().success:
            raise RuntimeError(f"~/start_episode refused: {future.result().message}")
        return called, clock_ns

    def episode(self, number: int) -> list[dict]:
        return [s for s in self.steps if int(s["episode"]) == number]

    def ended(self, number: int) -> bool:
        return any(s["terminated"] or s["truncated"] for s in self.episode(number))

    def close(self) -> None:
        self.mw.shutdown()


def graph(out: Path, mode: str, episodes: int, table: Path | None = None, **overrides):
    """The robot graph with the shipped policy (``overrides``: parameters by node, written
    into the parameters file); ``table``: the places instead of each episode's layout."""
    from hdrqn_ros.robot_graph import RobotRun, robot_processes, write_params
    from hdrqn_ros.supervisor import Supervisor

    run = RobotRun(algo="hdrqn-v2", env=ENV, view="5", policy=str(POLICY), mode=mode, episodes=episodes, seed=0,
                   real_time_factor=RTF, step_period=STEP_S, option_timeout=OPTION_TIMEOUT_S,
                   episode_log=str(out / "episodes.jsonl"))
    out.mkdir(parents=True, exist_ok=True)
    Path(run.episode_log).unlink(missing_ok=True)  # the node appends: this run's episodes only
    params = write_params(run, out / "params.yaml")
    doc = yaml.safe_load(params.read_text())
    if table is not None:
        for node in ("meta_controller", "robot_environment"):
            values = doc[f"/**/{node}"]["ros__parameters"]
            values.pop("subgoal_poses_topic")
            values["subgoal_table"] = str(table)
        doc["/**/robot_environment"]["ros__parameters"]["new_layout_each_episode"] = False
    for node, values in overrides.items():
        doc.setdefault(f"/**/{node}", {"ros__parameters": {}})["ros__parameters"].update(values)
    params.write_text(yaml.safe_dump(doc, sort_keys=False))
    sup = Supervisor(robot_processes(run, params, hierarchical=True), log_dir=out / "logs", stop_timeout_s=30)
    sup.start()
    return sup


def episode_figures(probe: Probe, number: int) -> dict | None:
    """One episode as the probe saw it (None when it missed the episode's first or last step, or
    the option chosen at its first step)."""
    steps = probe.episode(number)
    if not steps or steps[0]["t"] != 0 or not (steps[-1]["terminated"] or steps[-1]["truncated"]):
        return None
    first, last = steps[0], steps[-1]
    starts = [(key, wall) for key, wall in probe.options if int(first["key"]) <= key <= int(last["key"])]
    if not starts or starts[0][0] != int(first["key"]):
        return None
    ends = starts[1:] + [(int(last["key"]), last["wall"])]
    option_sim = [(b[0] - a[0]) / 1e9 for a, b in zip(starts, ends)]
    option_wall = [b[1] - a[1] for a, b in zip(starts, ends)]
    return {"episode": number, "steps": int(last["t"]), "success": bool(last["success"]),
            "sim_s": round((int(last["key"]) - int(first["key"])) / 1e9, 2),
            "wall_s": round(last["wall"] - first["wall"], 2), "options": len(starts),
            "option_sim_s_mean": round(float(np.mean(option_sim)), 2), "option_sim_s_max": round(max(option_sim), 2),
            "option_wall_s_mean": round(float(np.mean(option_wall)), 3)}


def goal_figures(probe: Probe) -> dict:
    """How many goals the navigator's status listed, and how many ended in each final status."""
    return {"goals": len(probe.goals),
            **{name: sum(status == code for status in probe.goals.values()) for code, name in STATUS_NAMES.items()}}


def timeout_computed(max_steps: int) -> dict:
    """What each option costs when it waits ``option_timeout`` (the critic's rule: an option
    ends at the first step whose key is ``option_timeout`` after its start)."""
    steps_per_option = math.ceil(OPTION_TIMEOUT_S / STEP_S - 1e-9)
    return {"option_sim_s": steps_per_option * STEP_S,
            "option_wall_s_at_rtf": round(steps_per_option * STEP_S / RTF, 3),
            "options_per_episode": math.ceil(max_steps / steps_per_option),
            "episode_sim_s": max_steps * STEP_S, "episode_wall_s_at_rtf": round(max_steps * STEP_S / RTF, 3)}


def unreachable(out: Path, navigation: str, max_steps: int, episodes: int) -> dict:
    """Part 1: one graph, meta-only, both places in walls."""
    table = out / "walls.yaml"
    table.parent.mkdir(parents=True, exist_ok=True)
    table.write_text("frame_id: map\nsubgoals: [{x: %.3f, y: %.3f}, {x: %.3f, y: %.3f}]\n"
                     % (*cell_centre(0, 3), *cell_centre(10, 7)))
    probe, started = Probe(), time.monotonic()
    sup = graph(out, "meta-only", episodes, table, robot_environment={"max_steps": max_steps},
                meta_controller={"navigation": navigation},
                critic={"option_timeout": OPTION_TIMEOUT_S, "navigation_outcome": navigation == "action"})
    try:
        probe.until(lambda: sup.returncodes["robot_environment"] is not None, 600, f"{episodes} episodes", sup)
        probe.mw.spin(timeout_s=1.0)  # the last step, the last goals' statuses
    finally:
        codes = sup.stop()
        probe.close()
    if codes["robot_environment"] != 0:
        raise RuntimeError(f"the robot environment exited with {codes['robot_environment']}: {out / 'logs'}")
    logged = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    seen = [f for f in (episode_figures(probe, n) for n in range(len(logged))) if f is not None]
    return {"navigation": navigation, "max_steps": max_steps or DEFAULT_MAX_STEPS, "episodes": len(logged),
            "steps": [e["steps"] for e in logged], "visits": sum(len(e["visits"]) for e in logged),
            "episodes_seen_whole": len(seen), "per_episode": seen,
            "option_sim_s_mean": round(float(np.mean([f["option_sim_s_mean"] for f in seen])), 2) if seen else None,
            "options_per_episode_mean": round(float(np.mean([f["options"] for f in seen])), 2) if seen else None,
            "episode_wall_s_median": round(float(np.median([f["wall_s"] for f in seen])), 2) if seen else None,
            **goal_figures(probe), "session_wall_s": round(time.monotonic() - started, 1)}


def stand_still(out: Path, mode: str, stand_s: float) -> dict:
    """Part 2: one episode, ``stand_s`` wall seconds standing, the next episode."""
    probe, started = Probe(), time.monotonic()
    sup = graph(out, mode, 2, robot_environment={"autostart": False})
    try:
        probe.until(probe.controllers_up, 300, "the controllers", sup)
        first_call, first_clock = probe.start_episode(sup)
        probe.until(lambda: probe.episode(0), 300, "episode 0's first step", sup)
        first_step = probe.episode(0)[0]
        probe.until(lambda: probe.ended(0), 300, "episode 0's end", sup)
        say(f"  {mode}: episode 0 ended after {int(probe.episode(0)[-1]['t'])} steps; standing {stand_s:g} s")
        stand_from, clock_from, odom_from = time.monotonic(), probe.clock_ns, len(probe.odom)
        heard_from = {name: len(times) for name, times in probe.heard.items()}
        probe.until(lambda: time.monotonic() - stand_from >= stand_s, stand_s + 10, "the stand", sup)
        stood = {"wall_s": round(time.monotonic() - stand_from, 1),
                 "sim_s": round((probe.clock_ns - clock_from) / 1e9, 1),
                 **{name: len(times) - heard_from[name] for name, times in probe.heard.items()},
                 "amcl_pose_at_s": [round(t - stand_from, 2)
                                    for t in probe.heard["amcl_pose"][heard_from["amcl_pose"]:]],
                 "odom_messages": len(probe.odom) - odom_from,
                 "odom_max_speed": max((v for _, v in probe.odom[odom_from:]), default=None),
                 "steps_while_standing": sum(s["wall"] >= stand_from for s in probe.steps)}
        call, clock = probe.start_episode(sup)
        probe.until(lambda: probe.episode(1), 300, "episode 1's first step", sup)
        step = probe.episode(1)[0]
        probe.until(lambda: sup.returncodes["robot_environment"] is not None, 300, "episode 1's end", sup)
        probe.mw.spin(timeout_s=1.0)  # the last step
    finally:
        codes = sup.stop()
        probe.close()
    logged = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    return {"mode": mode, "stand_s": stand_s, "robot_environment_exit": codes["robot_environment"], "stand": stood,
            "first_episode_start": {"wall_s": round(first_step["wall"] - first_call, 3),
                                    "sim_s": round((int(first_step["key"]) - first_clock) / 1e9, 2)},
            "after_stand_start": {"wall_s": round(step["wall"] - call, 3),
                                  "sim_s": round((int(step["key"]) - clock) / 1e9, 2),
                                  "key_s": round(int(step["key"]) / 1e9, 9)},
            "episodes": [{k: e[k] for k in ("episode", "success", "steps", "visits")} for e in logged],
            "episode_after_stand_seen_whole": episode_figures(probe, 1),
            "session_wall_s": round(time.monotonic() - started, 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3, help="episodes per unreachable-place run")
    parser.add_argument("--max-steps", type=int, nargs="*", default=[12, 0],
                        help="the robot environment's max_steps of the unreachable-place runs (0: its default)")
    parser.add_argument("--navigations", nargs="*", default=["action", "topic"])
    parser.add_argument("--stand-s", type=float, default=60.0)
    parser.add_argument("--stand-modes", nargs="*", default=["sub-drives", "meta-only"])
    parser.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_nav2_outcomes")
    args = parser.parse_args()
    if "ROS_DOMAIN_ID" not in os.environ:
        parser.error("set ROS_DOMAIN_ID to a DDS domain of this run's own")
    sys.path.insert(0, str(ROOT / "test"))
    result = {"settings": {"policy": str(POLICY.relative_to(ROOT)), "env": ENV, "seed": 0, "step_period_s": STEP_S,
                           "real_time_factor": RTF, "option_timeout_s": OPTION_TIMEOUT_S,
                           "ros_domain_id": int(os.environ["ROS_DOMAIN_ID"]),
                           "walls": [cell_centre(0, 3), cell_centre(10, 7)], "stand_s": args.stand_s},
              "unreachable": [], "timeout_computed": {}, "stand_still": []}
    for max_steps in args.max_steps:
        limit = max_steps or DEFAULT_MAX_STEPS
        result["timeout_computed"][str(limit)] = timeout_computed(limit)
        for navigation in args.navigations:
            say(f"unreachable places: navigation {navigation}, max_steps {limit}")
            row = unreachable(args.out / f"unreachable-{navigation}-{max_steps}", navigation, max_steps, args.episodes)
            say("  " + json.dumps({k: v for k, v in row.items() if k != "per_episode"}))
            result["unreachable"].append(row)
    for mode in args.stand_modes:
        for stand_s in sorted({0.0, args.stand_s}):  # 0: the same two episodes without the stand
            say(f"standing still: {mode}, {stand_s:g} s")
            row = stand_still(args.out / f"stand-{mode}-{stand_s:g}", mode, stand_s)
            say("  " + json.dumps({k: row[k] for k in ("stand", "after_stand_start", "episodes")}))
            result["stand_still"].append(row)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
