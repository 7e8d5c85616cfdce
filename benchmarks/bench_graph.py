"""Node-graph speed on rclpy: lock-step acting rate, and training throughput next to the
in-process trainer.

Runs real rclpy node processes (Fast DDS) on the loopback interface (its own domain id).
The probe that counts ``env_step`` messages is an rclpy node in this process.

1. acting only: environment, critic, meta- and sub-controller (hDRQNv2, no learner);
   env steps/s seen on ``env_step``, with 1 and 2 groups, ``--rounds`` measurements each;
   their mean is reported. Target: >= 500 steps/s.
2. training: the whole graph (``hdrqn up``'s processes) with the thesis update ratio
   (one update of each controller every 5 env steps) vs the in-process ``Trainer``
   with the same config, both measured after warm-up, for each ``--num-envs`` N (the
   environment node steps N environments as one batch; the trainer steps N too).
   Targets: graph >= 0.9x the best in-process rate; with batches, graph >= 1.0x the
   in-process trainer at the same N (``graph_vs_inprocess_same_n``).

Prints one JSON object; the figures are keyed by middleware (``"rclpy"``), as when this
benchmark also measured a second one. Usage: ``python benchmarks/bench_graph.py
[--seconds 60] [--rounds 2] [--num-envs 1,16] [--no-training] [--no-acting]``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from hdrqn_ros.config import build_config
from hdrqn_ros.graph import graph_processes, write_params
from hdrqn_ros.dds import apply_rmw_network_defaults
from hdrqn_ros.nodes.ros_packages import RosNotInstalled, require_rclpy
from hdrqn_ros.protocol import wire
from hdrqn_ros.supervisor import ProcessSpec, Supervisor
from hdrqn_ros.training.trainer import Trainer

ALGO = "hdrqn-v2"
ENV = "hdrqn/GridWorld-2Goals-v0"
MIDDLEWARE = "rclpy"
"""The key of every figure (the one middleware)."""


def _node(module: str, *args: str) -> list[str]:
    mod, _, func = module.partition(":")
    head = [sys.executable, "-m", mod] if not func else \
        [sys.executable, "-c", f"import sys; from {mod} import {func} as m; sys.exit(m())"]
    return head + ["--ros-args", "-p", f"algo:={ALGO}", *args]


def acting_rate(seconds: float, log_dir: Path, groups: int = 1) -> float:
    """Lock-step steps/s (all groups together) of env + critic + meta + sub per group
    (epsilon 0.1, no learner)."""
    specs = []
    for i in range(groups):
        ns = ("-r", f"__ns:=/g{i}", "-p", f"seed:={i}")
        specs += [ProcessSpec(f"g{i}/environment", _node("hdrqn_ros.nodes.environment", *ns)),
                  ProcessSpec(f"g{i}/critic", _node("hdrqn_ros.nodes.critic", *ns)),
                  ProcessSpec(f"g{i}/meta", _node("hdrqn_ros.nodes.controllers:main_meta", "-p", "epsilon:=0.1", *ns)),
                  ProcessSpec(f"g{i}/sub", _node("hdrqn_ros.nodes.controllers:main_sub", "-p", "epsilon:=0.1", *ns))]
    sup = Supervisor(specs, log_dir=log_dir)
    sup.start()
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from std_msgs.msg import Float64MultiArray

    from hdrqn_ros.nodes.qos import STEP_QOS

    apply_rmw_network_defaults(None)
    context = Context()
    rclpy.init(args=["bench_probe"], context=context)
    executor = SingleThreadedExecutor(context=context)
    steps: list[float] = []

    def spin(until, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while not until() and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)

    try:
        node = Node("bench_probe", context=context)
        executor.add_node(node)
        for i in range(groups):
            node.create_subscription(Float64MultiArray, f"/g{i}/{wire.ENV_STEP}",
                                     lambda m: steps.append(time.perf_counter()), STEP_QOS)
        spin(lambda: len(steps) > 200 * groups, 120)  # warm-up: all nodes up, loops running
        n0, t0 = len(steps), time.perf_counter()
        spin(lambda: False, seconds)
        rate = (len(steps) - n0) / (time.perf_counter() - t0)
    finally:
        executor.shutdown()
        rclpy.try_shutdown(context=context)
        sup.stop()
    return rate


def _config(episodes: int, num_envs: int = 1):
    return build_config([], algo=ALGO, env=ENV, episodes=episodes, learning_starts=500, num_envs=num_envs,
                        eval_every=0, checkpoint_every=10**6)


def graph_run_dir(tmp: Path, groups: int = 1, num_envs: int = 1) -> Path:
    """Where :func:`graph_training_rate` puts the graph's run (its ``status.json``, logs)."""
    return tmp / f"graph{groups}x{num_envs}"


def graph_training_rate(seconds: float, tmp: Path, groups: int = 1, learner: dict | None = None,
                        num_envs: int = 1) -> dict:
    """Env steps/s and updates/s of the whole graph (``num_envs`` per environment node),
    measured after 50 updates."""
    cfg = _config(100_000)
    run = graph_run_dir(tmp, groups, num_envs)
    run.mkdir()
    cfg_file = run / "in.yaml"
    cfg_file.write_text(json.dumps(cfg.model_dump()))
    params = write_params(cfg, run, groups, cfg_file, extra={"learner": learner or {}}, num_envs=num_envs)
    sup = Supervisor(graph_processes(cfg, params, groups, respawn=False), log_dir=run / "logs")
    sup.start()
    status = run / "status.json"

    def read():
        try:
            return json.loads(status.read_text())
        except (OSError, ValueError):
            return None

    try:
        end = time.monotonic() + 180
        while time.monotonic() < end and not ((s := read()) and s["updates"] > 50):
            sup.poll()
            time.sleep(0.2)
        s0, t0 = read(), time.perf_counter()
        time.sleep(seconds)
        s1, t1 = read(), time.perf_counter()
    finally:
        sup.stop()
    if not (s0 and s1):
        raise RuntimeError(f"the graph wrote no status in 180 s (logs: {run / 'logs'})")
    return {"steps_per_s": round((s1["env_steps"] - s0["env_steps"]) / (t1 - t0), 1),
            "updates_per_s": round((s1["updates"] - s0["updates"]) / (t1 - t0), 1)}


def inprocess_training_rate(seconds: float, tmp: Path, num_envs: int) -> float:
    trainer = Trainer(_config(100_000, num_envs), tmp / f"inproc{num_envs}", progress=False, tensorboard=False)
    while trainer.env_steps < 500 + 250:  # past warm-up, like the graph measurement
        trainer.step()
    s0, t0 = trainer.env_steps, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        trainer.step()
    return (trainer.env_steps - s0) / (time.perf_counter() - t0)


def _mean(values: list[float]) -> float:
    return round(sum(values) / len(values), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="training measurement (acting: at most 20)")
    ap.add_argument("--rounds", type=int, default=2, help="acting measurements per group count")
    ap.add_argument("--no-training", action="store_true", help="acting only")
    ap.add_argument("--no-acting", action="store_true", help="training only")
    ap.add_argument("--num-envs", default="1,16", help="comma-separated batch sizes for the training comparison")
    args = ap.parse_args()
    num_envs = [int(n) for n in args.num_envs.split(",")]
    if args.rounds < 1:
        ap.error("--rounds must be >= 1")
    try:
        require_rclpy()
    except RosNotInstalled as exc:
        ap.error(str(exc))
    os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        key = MIDDLEWARE
        out: dict = {"machine_cores": os.cpu_count(), "seconds": args.seconds, "backends": [key]}
        for groups in () if args.no_acting else (1, 2):
            samples = []
            for k in range(args.rounds):
                samples.append(acting_rate(min(args.seconds, 20.0), tmp / f"acting{groups}-{k}", groups))
                print(f"acting, {groups} group(s): {samples[-1]:.1f} steps/s", file=sys.stderr)
            out[f"acting_{groups}group_steps_per_s"] = {key: _mean(samples)}
            out[f"acting_{groups}group_rounds"] = {key: [round(x, 1) for x in samples]}
        if not args.no_acting:
            out["acting_target"] = 500
            best = max(out[f"acting_{g}group_steps_per_s"][key] for g in (1, 2))
            out["acting_ratio"] = round(best / 500, 2)
        if not args.no_training:
            inproc = {n: round(inprocess_training_rate(args.seconds, tmp, n), 1) for n in sorted({1, 16, *num_envs})}
            for n, rate in inproc.items():
                out[f"inprocess_n{n}_steps_per_s"] = rate
            graph = {n: graph_training_rate(args.seconds, tmp, num_envs=n) for n in num_envs}
            for n, g in graph.items():
                print(f"training, graph of {n} env(s): {g}", file=sys.stderr)
            out["graph_steps_per_s"] = {f"n{n}": {key: g["steps_per_s"]} for n, g in graph.items()}
            out["graph_updates_per_s"] = {f"n{n}": {key: g["updates_per_s"]} for n, g in graph.items()}
            best_inproc = max(inproc[1], inproc[16])
            best_graph = max(g["steps_per_s"] for g in graph.values())
            out["graph_vs_inprocess_best"] = {key: round(best_graph / best_inproc, 2)}
            out["training_target"] = 0.9
            out["graph_vs_inprocess_same_n"] = {f"n{n}": {key: round(g["steps_per_s"] / inproc[n], 2)}
                                                for n, g in graph.items()}
            out["same_n_target"] = 1.0
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
