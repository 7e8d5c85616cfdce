"""Node-graph speed: lock-step acting rate, and training throughput next to the in-process trainer.

Runs real node processes over Cyclone DDS on the loopback interface (its own domain id).

1. acting only: environment, critic, meta- and sub-controller (hDRQNv2, no learner);
   env steps/s seen on ``env_step``. Target >= 500.
2. training: the whole graph (``hdrqn up``'s processes) with the thesis update ratio
   (one update of each controller every 5 env steps) vs the in-process ``Trainer``
   with the same config, both measured after warm-up. Target: graph >= 0.9x.

Prints one JSON object. Usage: ``python benchmarks/bench_graph.py [--seconds 60]``.
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
from hdrqn_ros.middleware.cyclone import CycloneMiddleware
from hdrqn_ros.protocol import wire as P
from hdrqn_ros.supervisor import ProcessSpec, Supervisor
from hdrqn_ros.training.trainer import Trainer

ALGO = "hdrqn-v2"
ENV = "hdrqn/GridWorld-2Goals-v0"


def _node(module: str, *args: str) -> list[str]:
    mod, _, func = module.partition(":")
    head = [sys.executable, "-m", mod] if not func else \
        [sys.executable, "-c", f"import sys; from {mod} import {func} as m; sys.exit(m())"]
    return head + ["--ros-args", "-p", f"algo:={ALGO}", *args]


def acting_rate(seconds: float, log_dir: Path, groups: int = 1) -> dict:
    """Lock-step steps/s of env + critic + meta + sub per group (epsilon 0.1, no learner)."""
    specs = []
    for i in range(groups):
        ns = ("-r", f"__ns:=/g{i}", "-p", f"seed:={i}")
        specs += [ProcessSpec(f"g{i}/environment", _node("hdrqn_ros.nodes.environment", *ns)),
                  ProcessSpec(f"g{i}/critic", _node("hdrqn_ros.nodes.critic", *ns)),
                  ProcessSpec(f"g{i}/meta", _node("hdrqn_ros.nodes.controllers:main_meta", "-p", "epsilon:=0.1", *ns)),
                  ProcessSpec(f"g{i}/sub", _node("hdrqn_ros.nodes.controllers:main_sub", "-p", "epsilon:=0.1", *ns))]
    sup = Supervisor(specs, log_dir=log_dir)
    sup.start()
    mw = CycloneMiddleware([])
    steps: list[float] = []
    try:
        node = mw.create_node("bench_probe")
        for i in range(groups):
            node.create_subscription(P.FLOATS, f"/g{i}/{P.ENV_STEP}", lambda m: steps.append(time.perf_counter()))
        mw.spin(until=lambda: len(steps) > 200 * groups, timeout_s=120)  # warm-up: all nodes up, loops running
        n0, t0 = len(steps), time.perf_counter()
        mw.spin(timeout_s=seconds)
        rate = (len(steps) - n0) / (time.perf_counter() - t0)
    finally:
        mw.shutdown()
        sup.stop()
    return {f"acting_{groups}group_steps_per_s": round(rate, 1)}


def _config(episodes: int, num_envs: int = 1):
    return build_config([], algo=ALGO, env=ENV, episodes=episodes, learning_starts=500, num_envs=num_envs,
                        eval_every=0, checkpoint_every=10**6)


def graph_training_rate(seconds: float, tmp: Path, groups: int = 1, learner: dict | None = None) -> dict:
    cfg = _config(100_000)
    run = tmp / f"graph{groups}"
    run.mkdir()
    cfg_file = run / "in.yaml"
    cfg_file.write_text(json.dumps(cfg.model_dump()))
    params = write_params(cfg, run, groups, cfg_file, extra={"learner": learner or {}})
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
    rate = (s1["env_steps"] - s0["env_steps"]) / (t1 - t0)
    return {"graph_steps_per_s": round(rate, 1), "graph_updates_per_s": round((s1["updates"] - s0["updates"]) / (t1 - t0), 1)}


def inprocess_training_rate(seconds: float, tmp: Path, num_envs: int) -> float:
    trainer = Trainer(_config(100_000, num_envs), tmp / f"inproc{num_envs}", progress=False, tensorboard=False)
    while trainer.env_steps < 500 + 250:  # past warm-up, like the graph measurement
        trainer.step()
    s0, t0 = trainer.env_steps, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        trainer.step()
    return (trainer.env_steps - s0) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out = {"machine_cores": os.cpu_count(), "seconds": args.seconds}
        for groups in (1, 2):
            out.update(acting_rate(min(args.seconds, 20.0), tmp / f"acting{groups}", groups))
        out["acting_target"] = 500
        out["acting_ratio"] = round(max(out["acting_1group_steps_per_s"], out["acting_2group_steps_per_s"]) / 500, 2)
        out.update(graph_training_rate(args.seconds, tmp))
        for n in (1, 16):
            out[f"inprocess_n{n}_steps_per_s"] = round(inprocess_training_rate(args.seconds, tmp, n), 1)
        best = max(out["inprocess_n1_steps_per_s"], out["inprocess_n16_steps_per_s"])
        out["graph_vs_inprocess_best"] = round(out["graph_steps_per_s"] / best, 2)
        out["training_target"] = 0.9
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
