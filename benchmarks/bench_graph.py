"""Node-graph speed on each middleware backend: lock-step acting rate, and training throughput
next to the in-process trainer.

Runs real node processes on the loopback interface (its own domain id), once per backend
(rclpy on Fast DDS, and our Cyclone DDS backend; ``--backends``). The probe that counts
``env_step`` messages is a Cyclone-backend node in this process for both.

1. acting only: environment, critic, meta- and sub-controller (hDRQNv2, no learner);
   env steps/s seen on ``env_step``, with 1 and 2 groups. The backends take turns in
   rounds A B B A ... (``--rounds`` per backend), so a machine's drifting load hits both
   alike; the mean per backend is reported. Targets: >= 500 steps/s; rclpy >= 0.9x Cyclone.
2. training: the whole graph (``hdrqn up``'s processes) with the thesis update ratio
   (one update of each controller every 5 env steps) vs the in-process ``Trainer``
   with the same config, both measured after warm-up, for each ``--num-envs`` N (the
   environment node steps N environments as one batch; the trainer steps N too).
   Targets: graph >= 0.9x the best in-process rate; with batches, graph >= 1.0x the
   in-process trainer at the same N (``graph_vs_inprocess_same_n``).

Prints one JSON object. Usage: ``python benchmarks/bench_graph.py [--seconds 60]
[--rounds 2] [--backends rclpy,cyclone] [--num-envs 1,16] [--no-training] [--no-acting]``.
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
from hdrqn_ros.middleware import BACKEND_ENV
from hdrqn_ros.middleware.cyclone import CycloneMiddleware
from hdrqn_ros.middleware.rclpy_backend import rclpy_available
from hdrqn_ros.protocol import wire
from hdrqn_ros.supervisor import ProcessSpec, Supervisor
from hdrqn_ros.training.trainer import Trainer

ALGO = "hdrqn-v2"
ENV = "hdrqn/GridWorld-2Goals-v0"


def _node(module: str, *args: str) -> list[str]:
    mod, _, func = module.partition(":")
    head = [sys.executable, "-m", mod] if not func else \
        [sys.executable, "-c", f"import sys; from {mod} import {func} as m; sys.exit(m())"]
    return head + ["--ros-args", "-p", f"algo:={ALGO}", *args]


def acting_rate(seconds: float, log_dir: Path, backend: str, groups: int = 1) -> float:
    """Lock-step steps/s (all groups together) of env + critic + meta + sub per group
    (epsilon 0.1, no learner), every node on ``backend``."""
    specs = []
    for i in range(groups):
        ns = ("-r", f"__ns:=/g{i}", "-p", f"seed:={i}")
        specs += [ProcessSpec(f"g{i}/environment", _node("hdrqn_ros.nodes.environment", *ns)),
                  ProcessSpec(f"g{i}/critic", _node("hdrqn_ros.nodes.critic", *ns)),
                  ProcessSpec(f"g{i}/meta", _node("hdrqn_ros.nodes.controllers:main_meta", "-p", "epsilon:=0.1", *ns)),
                  ProcessSpec(f"g{i}/sub", _node("hdrqn_ros.nodes.controllers:main_sub", "-p", "epsilon:=0.1", *ns))]
    sup = Supervisor(specs, env={BACKEND_ENV: backend}, log_dir=log_dir)
    sup.start()
    mw = CycloneMiddleware([])
    steps: list[float] = []
    try:
        node = mw.create_node("bench_probe")
        for i in range(groups):
            node.create_subscription(wire.FLOATS, f"/g{i}/{wire.ENV_STEP}", lambda m: steps.append(time.perf_counter()))
        mw.spin(until=lambda: len(steps) > 200 * groups, timeout_s=120)  # warm-up: all nodes up, loops running
        n0, t0 = len(steps), time.perf_counter()
        mw.spin(timeout_s=seconds)
        rate = (len(steps) - n0) / (time.perf_counter() - t0)
    finally:
        mw.shutdown()
        sup.stop()
    return rate


def _config(episodes: int, num_envs: int = 1):
    return build_config([], algo=ALGO, env=ENV, episodes=episodes, learning_starts=500, num_envs=num_envs,
                        eval_every=0, checkpoint_every=10**6)


def graph_training_rate(seconds: float, tmp: Path, backend: str, groups: int = 1,
                        learner: dict | None = None, num_envs: int = 1) -> dict:
    """Env steps/s and updates/s of the whole graph on ``backend`` (``num_envs`` per
    environment node), measured after 50 updates."""
    cfg = _config(100_000)
    run = tmp / f"graph{groups}x{num_envs}-{backend}"
    run.mkdir()
    cfg_file = run / "in.yaml"
    cfg_file.write_text(json.dumps(cfg.model_dump()))
    params = write_params(cfg, run, groups, cfg_file, extra={"learner": learner or {}}, num_envs=num_envs)
    sup = Supervisor(graph_processes(cfg, params, groups, respawn=False), env={BACKEND_ENV: backend},
                     log_dir=run / "logs")
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
        raise RuntimeError(f"the {backend} graph wrote no status in 180 s (logs: {run / 'logs'})")
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


def _rounds(backends: list[str], rounds: int) -> list[str]:
    """A B B A A B ...: each backend ``rounds`` times, alternating which goes first."""
    order: list[str] = []
    for r in range(rounds):
        order += backends if r % 2 == 0 else backends[::-1]
    return order


def _mean(values: list[float]) -> float:
    return round(sum(values) / len(values), 1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="training measurement per backend (acting: at most 20)")
    ap.add_argument("--rounds", type=int, default=2, help="acting measurements per backend and group count")
    ap.add_argument("--backends", default=None, help="comma-separated, of rclpy and cyclone (default: those installed)")
    ap.add_argument("--no-training", action="store_true", help="acting only")
    ap.add_argument("--no-acting", action="store_true", help="training only")
    ap.add_argument("--num-envs", default="1,16", help="comma-separated batch sizes for the training comparison")
    args = ap.parse_args()
    num_envs = [int(n) for n in args.num_envs.split(",")]
    backends = args.backends.split(",") if args.backends else ["rclpy", "cyclone"] if rclpy_available() else ["cyclone"]
    if not set(backends) <= {"rclpy", "cyclone"} or args.rounds < 1:
        ap.error(f"--backends must name rclpy and/or cyclone (got {args.backends!r}), --rounds >= 1")
    if "rclpy" in backends and not rclpy_available():
        ap.error("--backends rclpy: rclpy does not import here (pip install '.[ros]')")
    os.environ.setdefault("ROS_DOMAIN_ID", str(100 + os.getpid() % 100))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out: dict = {"machine_cores": os.cpu_count(), "seconds": args.seconds, "backends": backends}
        for groups in () if args.no_acting else (1, 2):
            samples: dict[str, list[float]] = {b: [] for b in backends}
            for k, backend in enumerate(_rounds(backends, args.rounds)):
                samples[backend].append(acting_rate(min(args.seconds, 20.0), tmp / f"acting{groups}-{k}", backend, groups))
                print(f"acting, {groups} group(s), {backend}: {samples[backend][-1]:.1f} steps/s", file=sys.stderr)
            out[f"acting_{groups}group_steps_per_s"] = {b: _mean(v) for b, v in samples.items()}
            out[f"acting_{groups}group_rounds"] = {b: [round(x, 1) for x in v] for b, v in samples.items()}
        if not args.no_acting:
            out["acting_target"] = 500
            best = max(max(out[f"acting_{g}group_steps_per_s"].values()) for g in (1, 2))
            out["acting_ratio"] = round(best / 500, 2)
        if len(backends) == 2 and not args.no_acting:
            for g in (1, 2):
                rate = out[f"acting_{g}group_steps_per_s"]
                out[f"rclpy_vs_cyclone_acting_{g}group"] = round(rate["rclpy"] / rate["cyclone"], 2)
            out["rclpy_vs_cyclone_target"] = 0.9
        if not args.no_training:
            inproc = {n: round(inprocess_training_rate(args.seconds, tmp, n), 1) for n in sorted({1, 16, *num_envs})}
            for n, rate in inproc.items():
                out[f"inprocess_n{n}_steps_per_s"] = rate
            graph = {n: {b: graph_training_rate(args.seconds, tmp, b, num_envs=n) for b in backends} for n in num_envs}
            for n, by_backend in graph.items():
                print(f"training, graph of {n} env(s): {by_backend}", file=sys.stderr)
            out["graph_steps_per_s"] = {f"n{n}": {b: g["steps_per_s"] for b, g in by.items()} for n, by in graph.items()}
            out["graph_updates_per_s"] = {f"n{n}": {b: g["updates_per_s"] for b, g in by.items()}
                                          for n, by in graph.items()}
            best_inproc = max(inproc[1], inproc[16])
            best_graph = {b: max(graph[n][b]["steps_per_s"] for n in num_envs) for b in backends}
            out["graph_vs_inprocess_best"] = {b: round(r / best_inproc, 2) for b, r in best_graph.items()}
            out["training_target"] = 0.9
            out["graph_vs_inprocess_same_n"] = {f"n{n}": {b: round(g["steps_per_s"] / inproc[n], 2) for b, g in by.items()}
                                                for n, by in graph.items()}
            out["same_n_target"] = 1.0
            if len(backends) == 2:
                out["rclpy_vs_cyclone_training"] = {f"n{n}": round(by["rclpy"]["steps_per_s"] / by["cyclone"]["steps_per_s"], 2)
                                                    for n, by in graph.items()}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
