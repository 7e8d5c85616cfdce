"""A trained agent on the Nav2-like loopback robot against the same agent in the simulator (issues 26, 38).

For a checkpoint (and its ONNX export), or an exported policy directory (ONNX only), runs
``hdrqn robot`` in both modes (sub-drives: the sub-controller's motion primitives on
``cmd_vel``; meta-only: one ``navigate_to_pose`` goal per option, the robot's navigator drives) for ``--episodes`` episodes on the
simulator's layouts of ``--seed`` without fire, and the simulator itself on the same layouts
(greedy, ``play`` with ``obstacles=False``, one environment: the layouts in the same order;
a policy plays through :class:`~hdrqn_ros.deploy.onnx_agent.OnnxAgent`). Prints one JSON
object: per run the ordered success, steps per episode, per-decision latency (median wall
ms from a robot step's publication to its action) and wall time, the differences robot -
simulator (goals: sub-drives within 0.05 of the simulator; meta-only at least the
simulator's) and ``equal_episodes``, how many robot episodes have the (steps, success) of
the simulator's episode of the same index (the run's ``episodes.jsonl``; a meta-only step is
one ``step_period`` of navigation, not a cell, so meta-only episodes rarely match). Run dirs
go to ``--out``.

    python benchmarks/bench_robot.py (--checkpoint runs/v2/checkpoints/last.pt | --policy POLICY_DIR)
                                     [--episodes 100] [--seed 0] [--modes sub-drives meta-only]
                                     [--kinds torch onnx] [--out runs/bench_robot]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hdrqn_ros.deploy.onnx_agent import OnnxAgent
from hdrqn_ros.deploy.onnx_policy import OnnxPolicy
from hdrqn_ros.training.export import export_policy
from hdrqn_ros.training.learner import load_trained_agent, play


def simulator(checkpoint: Path | None, policy: Path | None, episodes: int, seed: int) -> tuple[dict, list[tuple]]:
    """The summary row and each episode's (steps, success) in the simulator."""
    if policy is not None:
        agent = OnnxAgent(OnnxPolicy.load(policy))
        cfg = agent.settings(obstacles=False)
    else:
        cfg, agent = load_trained_agent(checkpoint)
        cfg = cfg.model_copy(update={"env_kwargs": {**cfg.env_kwargs, "obstacles": False}})
    start = time.monotonic()
    rows = play(agent, cfg, episodes, seed, num_envs=1)
    return ({"episodes": len(rows), "success": float(np.mean([r.success for r in rows])),
             "steps": float(np.mean([r.steps for r in rows])), "wall_s": round(time.monotonic() - start, 1)},
            [(r.steps, bool(r.success)) for r in rows])


def robot(source: list[str], mode: str, episodes: int, seed: int, rtf: float, out: Path) -> tuple[dict, list[tuple]]:
    """``hdrqn robot`` into ``out``: its summary row and each episode's (steps, success)."""
    cmd = [sys.executable, "-m", "hdrqn_ros.cli", "robot", *source, "--mode", mode, "--episodes", str(episodes),
           "--seed", str(seed), "--real-time-factor", str(rtf), "--out", str(out)]
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    summary = json.loads((out / "summary.json").read_text())
    rows = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    return ({key: summary[key] for key in ("episodes", "success", "steps", "decision_ms_median", "wall_s")},
            [(int(r["steps"]), bool(r["success"])) for r in rows])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", type=Path)
    source.add_argument("--policy", type=Path, help="an exported policy directory: only the onnx kind")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--modes", nargs="+", default=["sub-drives", "meta-only"])
    parser.add_argument("--kinds", nargs="+", choices=("torch", "onnx"),
                        help="the controllers' kind (default both; onnx with --policy)")
    parser.add_argument("--real-time-factor", type=float, default=40.0)
    parser.add_argument("--out", type=Path, default=Path("runs/bench_robot"))
    args = parser.parse_args()
    kinds = args.kinds or (["onnx"] if args.policy else ["torch", "onnx"])
    if args.policy and kinds != ["onnx"]:
        parser.error(f"--policy runs the onnx kind only, got --kinds {' '.join(kinds)}")
    args.out.mkdir(parents=True, exist_ok=True)
    sim, sim_episodes = simulator(args.checkpoint, args.policy, args.episodes, args.seed)
    source = {"policy": str(args.policy)} if args.policy else {"checkpoint": str(args.checkpoint)}
    result = {**source, "episodes": args.episodes, "seed": args.seed, "simulator": sim, "robot": []}
    if args.policy:
        sources = {"onnx": ["--policy", str(args.policy)]}
    else:
        sources = {"torch": ["--checkpoint", str(args.checkpoint)]}
        if "onnx" in kinds:
            sources["onnx"] = ["--policy", str(export_policy(args.checkpoint, args.out / "policy"))]
    for mode in args.modes:
        for kind in kinds:
            run, episodes = robot(sources[kind], mode, args.episodes, args.seed, args.real_time_factor,
                                  args.out / f"{mode}-{kind}")
            run.update(mode=mode, policy=kind,
                       equal_episodes=sum(r == s for r, s in zip(episodes, sim_episodes)),
                       success_minus_simulator=round(run["success"] - sim["success"], 4),
                       steps_minus_simulator=round(run["steps"] - sim["steps"], 4))
            result["robot"].append(run)
            print(json.dumps(run), file=sys.stderr, flush=True)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
