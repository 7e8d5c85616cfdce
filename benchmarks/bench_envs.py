"""Environment throughput: single gym env steps/s and vectorised env-steps/s.

Prints one JSON object. Targets: >= 50k single-env steps/s (``GridWorldEnv.step`` via
``gym.make(...).unwrapped``, observation rendering included, auto reset on done) and
>= 100k env-steps/s for a batch of 64 (``GridWorldBatch.step`` + ``reset_where``).

    python benchmarks/bench_envs.py [--env-id ID] [--view 5] [--seconds 2] [--repeats 3]
"""
from __future__ import annotations

import argparse
import json
import platform
import time

import gymnasium as gym
import numpy as np

import hdrqn_ros  # noqa: F401  (registers the ids)
from hdrqn_ros.envs.registration import make_batch

SINGLE_TARGET = 50_000.0
VECTOR_TARGET = 100_000.0


def bench_single(env_id: str, view, seconds: float) -> float:
    env = gym.make(env_id, view=view).unwrapped
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, size=100_000).tolist()  # Python ints, like a policy's argmax
    n, i, t0 = 0, 0, time.perf_counter()
    deadline = t0 + seconds
    step, reset = env.step, env.reset
    while True:
        for _ in range(1000):
            _, _, term, trunc, _ = step(actions[i])
            i = (i + 1) % len(actions)
            if term or trunc:
                reset()
        n += 1000
        now = time.perf_counter()
        if now >= deadline:
            return n / (now - t0)


def bench_vector(env_id: str, view, num_envs: int, seconds: float) -> float:
    batch = make_batch(env_id, num_envs=num_envs, view=view)
    batch.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 4, size=(1000, num_envs))
    n, k, t0 = 0, 0, time.perf_counter()
    deadline = t0 + seconds
    while True:
        for _ in range(100):
            s = batch.step(actions[k])
            k = (k + 1) % len(actions)
            done = s.terminated | s.truncated
            if done.any():
                batch.reset_where(done)
        n += 100 * num_envs
        now = time.perf_counter()
        if now >= deadline:
            return n / (now - t0)


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env-id", default="hdrqn/GridWorld-2Goals-v0")
    p.add_argument("--view", default="5", help="3, 5, 11 or full")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--seconds", type=float, default=2.0, help="per measurement")
    p.add_argument("--repeats", type=int, default=3, help="best of this many measurements")
    args = p.parse_args(argv)
    view = args.view if args.view == "full" else int(args.view)
    single = max(bench_single(args.env_id, view, args.seconds) for _ in range(args.repeats))
    vector = max(bench_vector(args.env_id, view, args.num_envs, args.seconds) for _ in range(args.repeats))
    result = {
        "env_id": args.env_id,
        "view": view,
        "single_steps_per_s": round(single),
        "single_target": SINGLE_TARGET,
        "single_ratio": round(single / SINGLE_TARGET, 3),
        "num_envs": args.num_envs,
        "vector_env_steps_per_s": round(vector),
        "vector_target": VECTOR_TARGET,
        "vector_ratio": round(vector / VECTOR_TARGET, 3),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "machine": platform.machine(),
    }
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
