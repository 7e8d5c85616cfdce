"""``hdrqn up``: the same training over the ROS 2 node graph, each node a process."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from hdrqn_ros.cli.common import UsageError, config_from_args, done_line
from hdrqn_ros.protocol.wire import MAX_ENVS

MAX_GROUPS = 64
"""Most environment/controller groups ``hdrqn up`` starts (each is 4 node processes)."""


def add_up(sub) -> None:
    from hdrqn_ros.config import ALGOS
    from hdrqn_ros.envs.registration import ENV_IDS

    parser = sub.add_parser("up",
                            help="train over the ROS 2 node graph: each node a separate rclpy process",
                            description="Start the environment, critic, meta-controller, sub-controller and learner "
                                        "nodes as OS processes (rclpy nodes: they need ROS 2 Jazzy, the 'ros' extra "
                                        "on Linux x86-64), show a live status line, and "
                                        "stop them all when the learner finishes or on Ctrl-C. DDS stays on the "
                                        "loopback interface unless --interface is given. "
                                        "Node logs go to RUN_DIR/logs/.")
    parser.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory")
    parser.add_argument("--config", action="append", default=[], metavar="FILE",
                        help="YAML training config (repeatable)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override any config key")
    parser.add_argument("--algo", choices=ALGOS, help="algorithm (default hdrqn-v2)")
    parser.add_argument("--env", choices=ENV_IDS, metavar="ENV_ID", help="environment id")
    parser.add_argument("--episodes", type=int, help="training episodes")
    parser.add_argument("--seed", type=int, help="seed (group i's environment uses seed + 1000 i)")
    parser.add_argument("--view", help="observation window: 3, 5, 11 or full (gridworld domains)")
    parser.add_argument("--groups", type=int, default=1, help="environment/controller groups feeding the learner")
    parser.add_argument("--num-envs", type=int, default=1,
                        help=f"environments each environment node steps as one batch (1..{MAX_ENVS}; the "
                             "controllers act on the whole batch in one forward pass; default 1)")
    parser.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)")
    parser.add_argument("--interface", help="network interface for DDS (default: loopback only)")
    parser.add_argument("--no-respawn", action="store_true", help="do not restart nodes that exit unexpectedly")
    parser.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    parser.add_argument("--record", metavar="BAG_DIR",
                        help="the learner records every message it takes from the groups to this new bag "
                             "(rosbag2 MCAP)")


def cmd_up(args) -> int:
    import yaml

    from hdrqn_ros.graph import graph_processes, write_params
    from hdrqn_ros.dds import INTERFACE_ENV, NetworkConfigError, check_user_fastdds_profile, interface_address
    from hdrqn_ros.nodes.ros_packages import RosNotInstalled, require_rclpy
    from hdrqn_ros.supervisor import Supervisor
    from hdrqn_ros.training.plots import plot_runs

    run_dir = Path(args.out)
    try:
        require_rclpy()
        if args.interface:
            interface_address(args.interface)
        else:
            check_user_fastdds_profile()
    except (RosNotInstalled, NetworkConfigError) as exc:
        raise UsageError(str(exc)) from None
    if not 1 <= args.groups <= MAX_GROUPS:
        raise UsageError(f"--groups must be in 1..{MAX_GROUPS} (4 node processes each), got {args.groups}")
    if not 1 <= args.num_envs <= MAX_ENVS:
        raise UsageError(f"--num-envs must be in 1..{MAX_ENVS}, got {args.num_envs}")
    if (run_dir / "checkpoints" / "last.pt").exists() and not args.resume:
        raise UsageError(f"{run_dir} already holds a run; pass --resume to continue it or choose another --out")
    cfg = config_from_args(args)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "summary.json").unlink(missing_ok=True)
    config_file = run_dir / "graph-config.yaml"
    config_file.write_text(yaml.safe_dump(cfg.model_dump(), sort_keys=False))
    if args.record and os.path.lexists(args.record):
        raise UsageError(f"{args.record} already exists; refusing to overwrite a recording")
    extra = {"learner": {"record": str(Path(args.record).resolve())}} if args.record else None
    params = write_params(cfg, run_dir, args.groups, config_file, extra=extra, num_envs=args.num_envs)
    env = {INTERFACE_ENV: args.interface} if args.interface else {}
    if args.domain_id is not None:
        if not 0 <= args.domain_id <= 232:
            raise UsageError(f"--domain-id must be in 0..232, got {args.domain_id}")
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    specs = graph_processes(cfg, params, args.groups, respawn=not args.no_respawn)
    print(f"starting {len(specs)} rclpy node processes for {cfg.algo} on {cfg.env} {cfg.env_kwargs} "
          f"({args.groups} group(s) of {args.num_envs} env(s), {cfg.episodes} episodes, DDS on {args.interface or 'loopback'}) -> {run_dir}; "
          f"node logs in {run_dir / 'logs'}", file=sys.stderr)
    summary_path = run_dir / "summary.json"
    supervisor = Supervisor(specs, env=env, log_dir=run_dir / "logs", status=lambda: _graph_status(run_dir))
    rc = supervisor.run(until=summary_path.exists)
    if not summary_path.exists():
        print(f"hdrqn up: stopped before the learner finished (exit {rc}); the last checkpoint is in "
              f"{run_dir / 'checkpoints'}; continue with --resume", file=sys.stderr)
        return rc or 1
    summary = json.loads(summary_path.read_text())
    plot_runs([run_dir], run_dir / "curves.png")
    print(done_line(summary, run_dir, f" over {len(specs)} node processes, {summary.get('updates', 0)} updates"))
    return 0


def _graph_status(run_dir: Path) -> str:
    try:
        status = json.loads((run_dir / "status.json").read_text())
    except (OSError, ValueError):
        return "waiting for the learner"
    succ = "-" if status.get("success_last100") is None else f"{status['success_last100']:.2f}"
    return (f"episode {status['episodes']}/{status['target_episodes']} steps {status['env_steps']} "
            f"({status['steps_per_s']:.0f}/s) "
            f"updates {status['updates']} success {succ} eps {status['eps_sub']:.2f}/{status['eps_meta']:.2f}")
