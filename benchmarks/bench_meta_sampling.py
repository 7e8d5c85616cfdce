"""The cost of training the meta-controller on whole episodes of options instead of the
thesis's zero-state windows of n^M + 1 = 3 inputs.

Prints one JSON object: per algorithm (hDRQNv2: an MLP on the sub LSTM state; hDRQNv1: a
conv trunk on the observation) and episode length (3 options: an ordered three-goal
episode; 8: the failing seeds' shuttling; 50: one option per step, the longest), the mean
seconds of one meta update with ``meta.sampling`` ``windows`` and ``whole``, measured in
the same run on the same replay (batch 12; meta inputs of a random policy on the three-goal
gridworld, 5x5 view, drawn into episodes of that many options), and ``whole_over_windows``,
the ratio of the two update times.

    python benchmarks/bench_meta_sampling.py [--updates 200]
"""
from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import torch

from hdrqn_ros.agents.replay import Episode
from hdrqn_ros.config import build_config
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.episodes import EpisodeBuilder
from hdrqn_ros.training.learner import build_agent
from hdrqn_ros.training.rollout import Rollout

ENV = "hdrqn/GridWorld-3Goals-v0"


def _meta_inputs(cfg, count: int = 200) -> np.ndarray:
    """``count`` meta inputs (decisions) of a random policy, (count, ...)."""
    agent = build_agent(cfg)
    rollout = Rollout(make_batch(ENV, 16, view=5), agent, seed=7)
    builder, rng, frames = EpisodeBuilder(16, True), np.random.default_rng(0), []
    while len(frames) < count:
        frames += [f for episode in builder.add(rollout.step(1.0, 1.0, rng)) for f in episode.meta.frames]
    return np.stack(frames[:count])


def _episodes(inputs: np.ndarray, options: int, count: int = 100) -> list[Episode]:
    """``count`` meta episodes of ``options`` options, their inputs drawn from ``inputs``."""
    rng = np.random.default_rng(1)
    terminal = np.zeros(options, bool)
    terminal[-1] = True
    return [Episode(frames=inputs[rng.integers(len(inputs), size=options + 1)],
                    fields={"action": rng.integers(0, 3, options).astype(np.uint8),
                            "reward": np.zeros(options, np.float32), "option_steps": np.full(options, 5, np.int32),
                            "terminal": terminal, "next_invalid": np.full(options, -1, np.int8)})
            for _ in range(count)]


def _update_seconds(algo: str, sampling: str, episodes: list, updates: int) -> float:
    cfg = build_config([], algo=algo, env=ENV, env_kwargs={"view": 5}, meta={"sampling": sampling})
    meta = build_agent(cfg).meta
    for episode in episodes:
        meta.replay.add(episode)
    for _ in range(10):  # warm-up
        meta.update()
    start = time.perf_counter()
    for _ in range(updates):
        meta.update()
    return (time.perf_counter() - start) / updates


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    result = {"python": platform.python_version(), "torch": torch.__version__, "env": ENV, "batch_size": 12}
    for algo in ("hdrqn-v2", "hdrqn-v1"):
        inputs = _meta_inputs(build_config([], algo=algo, env=ENV, env_kwargs={"view": 5}))
        for options in (3, 8, 50):
            episodes = _episodes(inputs, options)
            seconds = {sampling: _update_seconds(algo, sampling, episodes, args.updates)
                       for sampling in ("windows", "whole")}
            result[f"{algo}, {options} options"] = {
                "windows_s": round(seconds["windows"], 6), "whole_s": round(seconds["whole"], 6),
                "whole_over_windows": round(seconds["whole"] / seconds["windows"], 2)}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
