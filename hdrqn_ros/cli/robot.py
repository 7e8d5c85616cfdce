"""``hdrqn robot``: a trained agent drives the loopback robot through the standard topics."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from hdrqn_ros.cli.common import UsageError, given_paths


def add_robot(sub) -> None:
    from hdrqn_ros.robot_graph import MODES

    parser = sub.add_parser("robot", help="a trained agent drives the loopback robot (as Nav2 ships a robot: tf, odom, "
                                          "costmaps, navigate_to_pose, cmd_vel), episode by episode",
                            description="Starts the loopback robot (a kinematic robot on the gridworld map, on "
                                        "simulated time), the robot-side environment, the critic and the trained "
                                        "controllers as node processes, prints each episode's visits and the running "
                                        "success, and stops after --episodes. The layouts are the simulator's for "
                                        "--seed without fire: compare with `hdrqn eval --checkpoint C (or "
                                        "--policy P) --no-fire --num-envs 1 --seed S`. Node logs and episodes.jsonl go to --out.")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", help="trained weights (RUN_DIR/checkpoints/last.pt)")
    source.add_argument("--policy", help="an exported policy directory (hdrqn export; no torch in the controllers)")
    parser.add_argument("--mode", choices=MODES, default="sub-drives",
                        help="sub-drives: each action is a closed-loop motion primitive the sub-controller "
                             "streams on cmd_vel; meta-only: the meta-controller sends each option's place as a "
                             "navigate_to_pose goal and the robot's navigator drives (default sub-drives)")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to run (default 10)")
    parser.add_argument("--seed", type=int, default=0, help="layouts: the simulator's for this seed (default 0)")
    parser.add_argument("--real-time-factor", type=float, default=20.0,
                        help="simulated seconds per wall second (0: as fast as possible; default 20)")
    parser.add_argument("--out", metavar="DIR", help="where params.yaml, logs/ and episodes.jsonl go "
                                                     "(default runs/robot-<mode>-<time>)")
    parser.add_argument("--record", metavar="BAG_DIR",
                        help="also record the episodes to this new rosbag2 MCAP bag (a learner node; needs --policy): "
                             "hdrqn train --from-bag BAG_DIR trains on it")


def _agent_settings(args) -> tuple[str, str, str]:
    """(algo, env, view) of the checkpoint or exported policy."""
    if args.policy:
        from hdrqn_ros.extras import require

        require("deploy", "hdrqn robot --policy", ("onnxruntime",))
        from hdrqn_ros.deploy.onnx_policy import OnnxPolicy

        policy = OnnxPolicy.load(args.policy)
        return policy.algo, policy.env, str(policy.env_kwargs.get("view", 5))
    from hdrqn_ros.training.learner import load_trained_agent

    cfg, _ = load_trained_agent(args.checkpoint)
    return cfg.algo, cfg.env, str(cfg.env_kwargs.get("view", 5))


def cmd_robot(args) -> int:
    import time

    from hdrqn_ros.agents.specs import ALGO_SPECS
    from hdrqn_ros.envs.registration import GRID_IDS
    from hdrqn_ros.nodes.ros_packages import RosNotInstalled, require_rclpy
    from hdrqn_ros.robot_graph import RobotRun, robot_processes, write_params
    from hdrqn_ros.supervisor import Supervisor

    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    if not args.real_time_factor >= 0:
        raise UsageError(f"--real-time-factor must be >= 0, got {args.real_time_factor}")
    try:
        require_rclpy()
    except RosNotInstalled as exc:
        raise UsageError(str(exc)) from None
    given_paths(checkpoint=args.checkpoint, policy=args.policy, record=args.record, out=args.out)
    if args.record and not args.policy:
        raise UsageError("--record needs --policy (an exported, frozen policy: hdrqn export): the recording "
                         "learner's weights would replace a checkpoint's")
    if args.record and Path(args.record).exists():
        raise UsageError(f"{args.record} already exists; refusing to overwrite a recording")
    algo, env, view = _agent_settings(args)
    if env not in GRID_IDS:
        raise UsageError(f"the loopback robot drives the gridworld maps; this agent was trained on {env!r}")
    out = Path(args.out or f"runs/robot-{args.mode}-{time.strftime('%Y%m%d-%H%M%S')}")
    out.mkdir(parents=True, exist_ok=True)
    episodes_path = out / "episodes.jsonl"
    episodes_path.unlink(missing_ok=True)
    run = RobotRun(algo=algo, env=env, view=view, checkpoint=str(Path(args.checkpoint).resolve()) if args.checkpoint
                   else "", policy=str(Path(args.policy).resolve()) if args.policy else "", mode=args.mode,
                   episodes=args.episodes, seed=args.seed, real_time_factor=args.real_time_factor,
                   episode_log=str(episodes_path.resolve()),
                   record=str(Path(args.record).resolve()) if args.record else "", learner_dir=str(out / "learner"))
    specs = robot_processes(run, write_params(run, out / "params.yaml"), ALGO_SPECS[algo].hierarchical)
    print(f"starting the loopback robot and {len(specs) - 1} nodes for {algo} on {env}, {args.mode}, "
          f"{args.episodes} episodes at {args.real_time_factor:g}x real time -> {out}", file=sys.stderr)
    rows: list[dict] = []

    def follow() -> bool:
        """Print the episodes finished since the last call; true once all are."""
        lines = episodes_path.read_text().splitlines() if episodes_path.exists() else []
        for line in lines[len(rows):]:
            row = json.loads(line)
            rows.append(row)
            visits = ", ".join(("blue", "green", "cyan")[g] for g in row["visits"]) or "nothing"
            print(f"episode {row['episode']:4d}: visited {visits:20s} {'in order' if row['success'] else '        '} "
                  f"{row['steps']:3d} steps, {row['decision_ms']:6.1f} ms/decision | success "
                  f"{sum(r['success'] for r in rows)}/{len(rows)} = {row['success_rate']:.2f}", flush=True)
        return len(rows) >= args.episodes

    start = time.monotonic()
    supervisor = Supervisor(specs, log_dir=out / "logs",
                            status=lambda: f"{len(rows)}/{args.episodes} episodes")
    finished_at: list[float] = []

    def done() -> bool:
        """All episodes ran, and a recording learner has written them (it exits after them; 60 s at most)."""
        if not follow():
            return False
        finished_at[:] = finished_at or [time.monotonic()]
        return not args.record or supervisor.returncodes["learner"] is not None or \
            time.monotonic() - finished_at[0] > 60

    rc = supervisor.run(until=done)
    follow()
    if not rows:
        print(f"hdrqn robot: no episode finished (exit {rc}); see the node logs in {out / 'logs'}", file=sys.stderr)
        return rc or 1
    summary = {"algo": algo, "env": env, "mode": args.mode, "policy": "onnx" if args.policy else "torch",
               "episodes": len(rows), "success": sum(r["success"] for r in rows) / len(rows),
               "steps": sum(r["steps"] for r in rows) / len(rows),
               "decision_ms_median": sorted(r["decision_ms"] for r in rows)[len(rows) // 2],
               "wall_s": round(time.monotonic() - start, 1)}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"done: {len(rows)} episodes, ordered success {summary['success']:.2f}, {summary['steps']:.1f} steps per "
          f"episode, {summary['decision_ms_median']:.1f} ms per decision (median), {summary['wall_s']} s -> "
          f"{out / 'summary.json'}")
    return 0 if len(rows) >= args.episodes else (rc or 1)
