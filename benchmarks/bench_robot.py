"""A trained agent on the loopback robot against the same agent in the simulator (issue 26).

For a checkpoint (and its ONNX export), runs ``hdrqn robot`` in both modes (sub-drives:
the sub-controller's ``cmd_vel``; meta-only: ``goal_pose`` per option, the robot's
navigator drives) for ``--episodes`` episodes on the simulator's layouts of ``--seed``
without fire, and the simulator itself on the same layouts (greedy, ``play`` with
``obstacles=False``, one environment: the layouts in the same order). Prints one JSON
object: per run the ordered success, steps per episode, per-decision latency (median wall
ms from a robot step's publication to its action) and wall time, and the differences
robot - simulator (goals: sub-drives within 0.05 of the simulator; meta-only at least the
simulator's). Run dirs go to ``--out``.

    python benchmarks/bench_robot.py --checkpoint runs/v2/checkpoints/last.pt [--episodes 100] [--seed 0]
                                     [--modes sub-drives meta-only] [--kinds torch onnx] [--out runs/bench_robot]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hdrqn_ros.training.export import export_policy
from hdrqn_ros.training.learner import load_trained_agent, play


def simulator(checkpoint: Path, episodes: int, seed: int) -> dict:
    cfg, agent = load_trained_agent(checkpoint)
    cfg = cfg.model_copy(update={"env_kwargs": {**cfg.env_kwargs, "obstacles": False}})
    start = time.monotonic()
    rows = play(agent, cfg, episodes, seed, num_envs=1)
    return {"episodes": len(rows), "success": float(np.mean([r.success for r in rows])),
            "steps": float(np.mean([r.steps for r in rows])), "wall_s": round(time.monotonic() - start, 1)}


def robot(source: list[str], mode: str, episodes: int, seed: int, rtf: float, out: Path) -> dict:
    cmd = [sys.executable, "-m", "hdrqn_ros.cli", "robot", *source, "--mode", mode, "--episodes", str(episodes),
           "--seed", str(seed), "--real-time-factor", str(rtf), "--out", str(out)]
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    summary = json.loads((out / "summary.json").read_text())
    return {key: summary[key] for key in ("episodes", "success", "steps", "decision_ms_median", "wall_s")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True, type=Path)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--modes", nargs="+", default=["sub-drives", "meta-only"])
    parser.add_argument("--kinds", nargs="+", default=["torch", "onnx"])
    parser.add_argument("--real-time-factor", type=float, default=40.0)
    parser.add_argument("--out", type=Path, default=Path("runs/bench_robot"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    result = {"checkpoint": str(args.checkpoint), "episodes": args.episodes, "seed": args.seed,
              "simulator": simulator(args.checkpoint, args.episodes, args.seed), "robot": []}
    sources = {"torch": ["--checkpoint", str(args.checkpoint)]}
    if "onnx" in args.kinds:
        sources["onnx"] = ["--policy", str(export_policy(args.checkpoint, args.out / "policy"))]
    for mode in args.modes:
        for kind in args.kinds:
            run = robot(sources[kind], mode, args.episodes, args.seed, args.real_time_factor,
                        args.out / f"{mode}-{kind}")
            run.update(mode=mode, policy=kind, success_minus_simulator=round(
                run["success"] - result["simulator"]["success"], 4))
            result["robot"].append(run)
            print(json.dumps(run), file=sys.stderr, flush=True)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
