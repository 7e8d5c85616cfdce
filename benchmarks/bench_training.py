"""Training-loop throughput with the thesis update ratio, against a naive reference loop.

Prints one JSON object: env steps/s of the project's trainer (hDRQNv2, two-goal 5x5
gridworld, one update of each controller every 5 env steps) for N=1 and N=16
environments, the same for a naive loop measured in the same run (one gym environment,
acting through ``nn.LSTM`` at batch 1, same networks, a straightforward update), their
ratios (target >= 1.3; issue 19's goal >= 4), and the time of one sub and one meta update
against the naive update's (goal: >= 2.5x faster each).

    python benchmarks/bench_training.py [--seconds 30] [--threads N]
"""
from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time

import gymnasium as gym
import numpy as np
import torch

import hdrqn_ros  # noqa: F401  (registers the ids)
from hdrqn_ros.agents.algorithms import stack_subgoal
from hdrqn_ros.agents.policy import epsilon_greedy
from hdrqn_ros.config import build_config
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.episodes import EpisodeBuilder
from hdrqn_ros.training.learner import build_agent
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.trainer import Trainer

TARGET_RATIO = 1.3
UPDATE_SPEEDUP_GOAL = 2.5
"""Issue 19: each controller's update >= 2.5x faster than :func:`naive_update`."""
LOOP_RATIO_GOAL = 4.0
"""Issue 19: the training loop at the thesis ratio >= 4x the naive loop (moonshot 6x)."""
ENV = "hdrqn/GridWorld-2Goals-v0"


def _config(num_envs: int):
    # learning starts at once, exploration mid-way: the regime the run spends its time in
    return build_config([], env=ENV, num_envs=num_envs, torch_threads=torch.get_num_threads(), learning_starts=0, eval_every=0,
                        checkpoint_every=10**9, episodes=10**9,
                        sub={"epsilon": {"start": 0.3, "end": 0.3}}, meta={"epsilon": {"start": 0.3, "end": 0.3}})


def _prefill(agent, cfg, episodes: int = 64) -> None:
    """Fill both replays with random-policy episodes so updates sample real data."""
    rollout = Rollout(make_batch(ENV, 16, **cfg.env_kwargs), agent, seed=99)
    builder = EpisodeBuilder(16, True)
    rng = np.random.default_rng(0)
    added = 0
    while added < episodes:
        for episode in builder.add(rollout.step(1.0, 1.0, rng)):
            agent.sub.replay.add(episode.sub)
            agent.meta.replay.add(episode.meta)
            added += 1


def bench_trainer(num_envs: int, seconds: float) -> float:
    """The project's loop body (:meth:`Trainer.step`): batched acting, recording, updates."""
    cfg = _config(num_envs)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(cfg, tmp, progress=False, tensorboard=False)
        _prefill(trainer.agent, cfg)
        return _timed(lambda: num_envs if trainer.step() is not None else 0, seconds)


def _plain_features(trunk, x: torch.Tensor) -> torch.Tensor:
    """The trunk as a direct port computes it: every conv through ``nn.Conv2d`` (an MLP trunk as is)."""
    if not hasattr(trunk, "convs"):
        return trunk(x)
    h = trunk._prepare(x)
    for conv in trunk.convs:
        h = torch.relu(conv(h))
    return h.flatten(1)


def _lstm_q(net, x: torch.Tensor, state=None):
    """Q-values (B, T, n) through ``nn.LSTM`` (the library kernel, as a direct port would)."""
    b, t = x.shape[:2]
    feats = _plain_features(net.trunk, x.reshape(b * t, *x.shape[2:])).view(b, t, -1)
    hc = None if state is None else tuple(s.unsqueeze(0) for s in state)
    out, (h, c) = net.lstm(feats, hc)
    return net.head(out), (h[0], c[0])


def naive_update(ctrl, optimizer) -> float:
    """A straightforward Double DQN update: three forward passes (online on s, online on
    s', target on s'), ``nn.LSTM`` sequences, per-parameter Adam and soft update."""
    batch = ctrl.replay.sample(ctrl.cfg.batch_size, ctrl.seq_len)
    x = torch.as_tensor(ctrl.build_input(batch))
    f = {k: torch.as_tensor(v) for k, v in batch.fields.items()}
    q = _lstm_q(ctrl.online, x[:, :-1])[0].gather(-1, f["action"].long().unsqueeze(-1)).squeeze(-1)
    with torch.no_grad():
        a2 = _lstm_q(ctrl.online, x[:, 1:])[0].argmax(-1, keepdim=True)
        v2 = _lstm_q(ctrl.target, x[:, 1:])[0].gather(-1, a2).squeeze(-1)
        y = f["reward"] + ctrl.cfg.gamma * (~f["terminal"]).float() * v2
    mask = torch.as_tensor(batch.loss_mask).float()
    loss = ((q - y).pow(2) * mask).sum() / mask.sum()
    optimizer.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(ctrl.online.parameters(), ctrl.cfg.grad_clip, foreach=False)
    optimizer.step()
    with torch.no_grad():
        for pt, p in zip(ctrl.target.parameters(), ctrl.online.parameters()):
            pt.mul_(1 - ctrl.cfg.tau).add_(ctrl.cfg.tau * p)
    return float(loss)


def bench_naive(seconds: float) -> float:
    """One gym env, acting through ``nn.LSTM`` at batch 1, :func:`naive_update` every 5 steps."""
    cfg = _config(1)
    agent = build_agent(cfg)
    _prefill(agent, cfg)
    opts = {c.name: torch.optim.Adam(c.online.parameters(), lr=c.cfg.lr, foreach=False) for c in agent.controllers}
    env = gym.make(ENV)
    rng = np.random.default_rng(0)
    state = {"obs": env.reset(seed=0)[0], "need_meta": True, "meta_in": np.zeros((1, 256), np.float32),
             "g": 0, "img": None, "sub_state": None, "meta_state": None, "count": 0}

    def step() -> int:
        with torch.no_grad():
            if state["need_meta"]:
                q, state["meta_state"] = _lstm_q(agent.meta.online, torch.as_tensor(state["meta_in"][:, None]),
                                                 state["meta_state"])
                state["g"] = int(epsilon_greedy(q[:, 0].numpy(), 0.3, rng)[0])
                env.unwrapped.set_subgoal(state["g"])
                state["img"] = env.unwrapped.subgoal_image(state["g"])
                state["sub_state"], state["need_meta"] = None, False
            x = stack_subgoal(state["obs"], state["img"])[None, None]
            q, state["sub_state"] = _lstm_q(agent.sub.online, torch.as_tensor(x), state["sub_state"])
            a = int(epsilon_greedy(q[:, 0].numpy(), 0.3, rng)[0])
        obs, _, term, trunc, info = env.step(a)
        if info["subgoal_reached"] or term or trunc:
            state["need_meta"] = True
            state["meta_in"] = state["sub_state"][1].numpy()
        if term or trunc:
            obs, _ = env.reset()
            state["meta_state"], state["meta_in"] = None, np.zeros((1, 256), np.float32)
        state["obs"] = obs
        state["count"] += 1
        if state["count"] % cfg.update_every == 0:
            for c in agent.controllers:
                naive_update(c, opts[c.name])
        return 1

    return _timed(step, seconds)


def bench_updates(repeats: int = 200) -> dict:
    cfg = _config(1)
    agent = build_agent(cfg)
    _prefill(agent, cfg)
    out = {}
    for ctrl in (agent.sub, agent.meta):
        for _ in range(10):
            ctrl.update()
        t0 = time.perf_counter()
        for _ in range(repeats):
            ctrl.update()
        out[f"{ctrl.name}_update_ms"] = round((time.perf_counter() - t0) / repeats * 1e3, 2)
        opt = torch.optim.Adam(ctrl.online.parameters(), lr=ctrl.cfg.lr, foreach=False)
        t0 = time.perf_counter()
        for _ in range(repeats):
            naive_update(ctrl, opt)
        out[f"naive_{ctrl.name}_update_ms"] = round((time.perf_counter() - t0) / repeats * 1e3, 2)
    return out


def _timed(step, seconds: float) -> float:
    for _ in range(20):  # warm-up
        step()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        n += step()
    return n / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0, help="measuring time per loop")
    parser.add_argument("--threads", type=int, default=1, help="torch threads for every loop (the trainer's default is 1)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    naive = bench_naive(args.seconds)
    n1 = bench_trainer(1, args.seconds)
    n16 = bench_trainer(16, args.seconds)
    result = {
        "benchmark": "training_loop", "env": ENV, "algo": "hdrqn-v2", "update_every": 5,
        "naive_steps_per_s": round(naive, 1), "trainer_n1_steps_per_s": round(n1, 1),
        "trainer_n16_steps_per_s": round(n16, 1),
        "ratio_n1": round(n1 / naive, 3), "ratio_n16": round(n16 / naive, 3), "target_ratio": TARGET_RATIO,
        **bench_updates(),
        "torch_threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
    }
    result["pass"] = result["ratio_n1"] >= TARGET_RATIO and result["ratio_n16"] >= TARGET_RATIO
    for role in ("sub", "meta"):
        result[f"{role}_update_speedup"] = round(result[f"naive_{role}_update_ms"] / result[f"{role}_update_ms"], 2)
    result["update_speedup_goal"] = UPDATE_SPEEDUP_GOAL
    result["loop_ratio_goal"] = LOOP_RATIO_GOAL
    result["issue19_goals_met"] = {
        "updates": min(result["sub_update_speedup"], result["meta_update_speedup"]) >= UPDATE_SPEEDUP_GOAL,
        "loop": max(result["ratio_n1"], result["ratio_n16"]) >= LOOP_RATIO_GOAL}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
