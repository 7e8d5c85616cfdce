"""The ``hdrqn`` command: train, evaluate, plot, and look at the environments.

Exit codes: 0 success, 1 a run failed (e.g. diverged), 2 misuse (bad arguments, config,
checkpoint or file), 130 interrupted.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
from pathlib import Path

from hdrqn_ros import __version__

EPILOG = """examples:
  hdrqn train --algo hdrqn-v2 --env hdrqn/GridWorld-2Goals-v0 --episodes 2000 --out runs/v2
  hdrqn train --config config/exp3_gridworld_2goals.yaml --algo hdqn --seed 1 --out runs/hdqn-s1
  hdrqn up --episodes 300 --out runs/graph     # the same training over the ROS 2 node graph
  hdrqn eval --checkpoint runs/v2/checkpoints/last.pt --episodes 200
  hdrqn plot runs/v2 runs/hdqn-s1 --out curves.png
  hdrqn experiment exp3-gridworld-2goals --seeds 0 1 2 --episodes 5000   # a thesis experiment
  hdrqn plot runs/exp3-gridworld-2goals                                  # its figures and table
  hdrqn envs
"""


MAX_GROUPS = 64
"""Most environment/controller groups ``hdrqn up`` starts (each is 4 node processes)."""


class UsageError(Exception):
    """Misuse of the command line: printed without a traceback, exit code 2."""


def _add_train(sub) -> None:
    from hdrqn_ros.config import ALGOS
    from hdrqn_ros.envs.registration import ENV_IDS

    p = sub.add_parser("train", help="train an agent in-process on N vectorised environments",
                       description="Train hDRQNv1/v2 or a baseline (thesis Algorithm 1). RUN_DIR receives "
                                   "checkpoints/, train.csv, eval.csv, tb/ (TensorBoard), curves.png and summary.json.")
    p.add_argument("--algo", choices=ALGOS, help="algorithm (default hdrqn-v2)")
    p.add_argument("--env", choices=ENV_IDS, metavar="ENV_ID", help=f"environment id, one of: {', '.join(ENV_IDS)}")
    p.add_argument("--episodes", type=int, help="training episodes (default 10000)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory")
    p.add_argument("--config", action="append", default=[], metavar="FILE",
                   help="YAML config (repeatable; later files override earlier ones; flags override files)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config key, e.g. --set sub.seq_len=12 --set meta.epsilon.steps=20000")
    p.add_argument("--seed", type=int, help="seed of environments, networks and exploration (default 0)")
    p.add_argument("--num-envs", type=int, help="environments stepped together (default 16)")
    p.add_argument("--view", help="observation window: 3, 5, 11 or full (gridworld domains)")
    p.add_argument("--device", help="torch device, e.g. cpu or cuda")
    p.add_argument("--eval-every", type=int, help="episodes between greedy evaluations (0: never)")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    rec = p.add_argument_group("recording and offline training (rosbag2 MCAP bags)")
    rec.add_argument("--record", metavar="BAG_DIR",
                     help="also record every transition to this new bag (the graph's topics, one group per env)")
    rec.add_argument("--record-split-mb", type=float, default=256.0, metavar="MB",
                     help="start a new bag file after this many MB (default 256)")
    rec.add_argument("--from-bag", nargs="+", metavar="BAG_DIR",
                     help="train offline: fill the replay from these bags (ours, or ros2 bag record -s mcap of "
                          "the graph's topics), train without an environment, then evaluate in it (5 greedy "
                          "evaluations, none with --eval-every 0); the config defaults to the first bag's recorded one")
    rec.add_argument("--updates", type=int, metavar="N",
                     help="offline updates of each controller (default: 10 per update_every transitions)")


def _add_up(sub) -> None:
    from hdrqn_ros.config import ALGOS
    from hdrqn_ros.envs.registration import ENV_IDS
    from hdrqn_ros.middleware import BACKENDS

    p = sub.add_parser("up", help="train over the ROS 2 node graph: each node a separate process (rclpy or Cyclone DDS)",
                       description="Start the environment, critic, meta-controller, sub-controller and learner "
                                   "nodes as OS processes (real rclpy nodes where rclpy is installed, else the "
                                   "Cyclone DDS backend; no ROS install needed), show a live status line, and "
                                   "stop them all when the learner finishes or on Ctrl-C. DDS stays on the "
                                   "loopback interface unless --interface is given. Node logs go to RUN_DIR/logs/.")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory")
    p.add_argument("--config", action="append", default=[], metavar="FILE", help="YAML training config (repeatable)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override any config key")
    p.add_argument("--algo", choices=ALGOS, help="algorithm (default hdrqn-v2)")
    p.add_argument("--env", choices=ENV_IDS, metavar="ENV_ID", help="environment id")
    p.add_argument("--episodes", type=int, help="training episodes")
    p.add_argument("--seed", type=int, help="seed (group i's environment uses seed + 1000 i)")
    p.add_argument("--view", help="observation window: 3, 5, 11 or full (gridworld domains)")
    p.add_argument("--groups", type=int, default=1, help="environment/controller groups feeding the learner")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)")
    p.add_argument("--interface", help="network interface for DDS (default: loopback only)")
    p.add_argument("--middleware", choices=BACKENDS, default=None,
                   help="node backend: rclpy (real ROS 2 nodes), cyclone (Cyclone DDS with ROS 2's wire "
                        "conventions) or auto: rclpy where it can be imported (default: $HDRQN_MIDDLEWARE or auto)")
    p.add_argument("--no-respawn", action="store_true", help="do not restart nodes that exit unexpectedly")
    p.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    p.add_argument("--record", metavar="BAG_DIR",
                   help="the learner records every message it takes from the groups to this new bag (rosbag2 MCAP)")


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="run greedy evaluation episodes of a checkpoint (and record them)")
    p.add_argument("--checkpoint", required=True, help="path to a checkpoint (RUN_DIR/checkpoints/last.pt)")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--num-envs", type=int, help="environments played in parallel (default: one per episode)")
    p.add_argument("--epsilon", type=float, default=0.0, help="exploration of both controllers (default 0: greedy)")
    p.add_argument("--meta-epsilon", type=float, metavar="E",
                   help="the meta-controller's exploration (default: --epsilon; 1: subgoals at random, as phase 1)")
    p.add_argument("--subgoals", action="store_true",
                   help="also report, per subgoal, how often the options aimed at it reached it (from its "
                        "neighbours and from anywhere) and the steps spent at each subgoal")
    p.add_argument("--record", metavar="BAG_DIR", help="record the episodes' transitions to this new bag")


def _add_experiment(sub) -> None:
    from hdrqn_ros.config import ALGOS
    from hdrqn_ros.experiments import EXPERIMENTS

    p = sub.add_parser("experiment", help="run a thesis experiment (chapter 4) over several seeds, in parallel",
                       formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Runs every setting of the experiment for every seed as `hdrqn train` "
                                   "processes (JOBS at a time; logs in OUT/RUN.log). Finished runs are skipped "
                                   "and interrupted ones resumed, so the same command continues an experiment. "
                                   "Then `hdrqn plot OUT` draws its figures and table.",
                       epilog="experiments:\n" + "\n".join(f"  {e.name:24s} {e.title}" for e in EXPERIMENTS.values()))
    p.add_argument("name", choices=list(EXPERIMENTS), metavar="NAME", help="experiment (listed below)")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="seeds (default 0 1 2)")
    p.add_argument("--algos", nargs="+", choices=ALGOS, help="run only the settings of these algorithms")
    p.add_argument("--episodes", type=int, help="episodes per run (default: the config's, i.e. the thesis's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key in every run, e.g. --set device=cuda --set num_envs=32")
    p.add_argument("--jobs", type=int, help="runs at a time (default: one per core)")
    p.add_argument("--out", metavar="DIR", help="experiment directory (default runs/NAME)")
    p.add_argument("--dry-run", action="store_true", help="print the runs' commands and exit")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_plot(sub) -> None:
    p = sub.add_parser("plot", help="draw learning curves of runs (thesis figures 4.6-4.11) to PNG",
                       description="Runs with the same label (default: the algorithm) are averaged: mean "
                                   "line and min-max band over seeds. Given one `hdrqn experiment` directory, "
                                   "draws each of its thesis figures and writes table.md (also printed).")
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories, or one experiment directory")
    p.add_argument("--out", help="output PNG (default curves.png; for an experiment: the folder for its figures)")
    p.add_argument("--window", type=int, default=200, help="moving-average window in episodes")
    p.add_argument("--label", action="append", default=[], metavar="RUN_DIR=LABEL",
                   help="name a run's curve (default: its algorithm)")


def _add_bag(sub) -> None:
    p = sub.add_parser("bag", help="inspect and repair rosbag2 (MCAP) bags",
                       description="rosbag2 bags with MCAP storage (what ros2 bag record -s mcap writes).")
    bag_sub = p.add_subparsers(dest="bag_command", metavar="BAG_COMMAND", required=True)
    info = bag_sub.add_parser("info", help="topics, types, message counts, time span and files of a bag")
    info.add_argument("bag", metavar="BAG_DIR")
    info.add_argument("--json", action="store_true", help="print JSON")
    repair = bag_sub.add_parser("repair", help="recover a bag whose recorder was killed (complete chunks are kept)")
    repair.add_argument("bag", metavar="BAG_DIR")
    play = bag_sub.add_parser(
        "play", help="publish a bag's messages on their recorded topics, paced by their timestamps (ros2 bag play)",
        description="Runs the player node (hdrqn_ros/nodes/player.py) in this process: each message goes out on its "
                    "recorded topic with the recorded QoS, /clock carries the bag time. The node runs on rclpy "
                    "where it can be imported, else on Cyclone DDS (--middleware); DDS stays on the loopback "
                    "interface unless --interface is given. Put --topics after the bag directories.")
    play.add_argument("bags", nargs="+", metavar="BAG_DIR", help="bag directories, played together in timestamp order")
    play.add_argument("--rate", type=float, default=1.0, help="playback speed: bag seconds per second (default 1.0)")
    play.add_argument("--loop", action="store_true", help="start over at the end, until Ctrl-C")
    play.add_argument("--topics", nargs="+", default=[], metavar="T", help="play only these topics (default: all)")
    play.add_argument("--no-clock", action="store_true", help="do not publish /clock")
    play.add_argument("--delay", type=float, default=1.0,
                      help="seconds between creating the publishers and the first message, for DDS discovery (default 1.0)")
    play.add_argument("--wait-for-subscribers", type=int, default=0, metavar="N",
                      help="before playing, wait until every topic has at least N subscribers (default 0: no wait)")
    play.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (default: $ROS_DOMAIN_ID or 0)")
    play.add_argument("--interface", help="network interface for DDS (default: loopback only)")
    play.add_argument("--middleware", choices=("auto", "rclpy", "cyclone"), default=None,
                      help="node backend (default: $HDRQN_MIDDLEWARE or auto: rclpy where it can be imported)")


def _add_envs(sub) -> None:
    sub.add_parser("envs", help="list the environment ids and their default options")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hdrqn", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Hierarchical deep recurrent Q-learning (hDRQN) on partially observable hierarchical tasks.")
    parser.add_argument("--version", action="version", version=f"hdrqn_ros {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in (_add_train, _add_up, _add_eval, _add_experiment, _add_plot, _add_bag, _add_envs):
        add(sub)
    return parser


# -- commands -----------------------------------------------------------------------------
def _config_from_args(args, base: dict | None = None, **flags):
    """The TrainConfig of a ``train``/``up`` command line: ``base``, files, then --set, then flags."""
    from hdrqn_ros.config import build_config, parse_set

    overrides = parse_set(args.set)
    if args.view is not None:
        view = args.view if args.view == "full" else _int(args.view, "--view")
        env_kwargs = overrides.setdefault("env_kwargs", {})
        if not isinstance(env_kwargs, dict):
            raise UsageError(f"--view needs env_kwargs to be a mapping, got env_kwargs={env_kwargs!r}")
        env_kwargs["view"] = view
    files = list(args.config)
    run_dir = Path(args.out)
    if args.resume and not files and (run_dir / "config.yaml").exists():
        files = [run_dir / "config.yaml"]
    flags.update(algo=args.algo, env=args.env, episodes=args.episodes, seed=args.seed)
    return build_config(files, base=base, **{**overrides, **{k: v for k, v in flags.items() if v is not None}})


def _done_line(summary: dict, run_dir: Path, how: str) -> str:
    ev = summary.get("final_eval") or {}
    return (f"done: {summary['episodes']} episodes, {summary['env_steps']} env steps in {summary['wall_s']} s "
            f"({summary['env_steps_per_s']} steps/s{how}); greedy eval: success {ev.get('success', float('nan')):.2f}, "
            f"steps {ev.get('steps', float('nan')):.1f}, reward {ev.get('reward', float('nan')):.2f}; "
            f"curves: {run_dir / 'curves.png'}")


def cmd_train(args) -> int:
    from hdrqn_ros.training.plots import plot_runs
    from hdrqn_ros.training.trainer import Trainer

    if args.from_bag:
        return _train_offline(args)
    if args.updates is not None:
        raise UsageError("--updates is for offline training (--from-bag)")
    run_dir = Path(args.out)
    cfg = _config_from_args(args, num_envs=args.num_envs, device=args.device, eval_every=args.eval_every)
    print(f"training {cfg.algo} on {cfg.env} {cfg.env_kwargs} for {cfg.episodes} episodes "
          f"({cfg.num_envs} envs, seed {cfg.seed}) -> {run_dir}", file=sys.stderr)
    sink = None
    if args.record:
        from hdrqn_ros.recording.transitions import TransitionRecorder

        if not 0 < args.record_split_mb < 2**20:  # also NaN and inf
            raise UsageError(f"--record-split-mb must be > 0 and < 1048576 (1 TiB), got {args.record_split_mb}")
        sink = TransitionRecorder(args.record, cfg, cfg.num_envs, split_bytes=int(args.record_split_mb * 2**20),
                                  source="hdrqn train")
        print(f"recording transitions to {sink.path}", file=sys.stderr)
    try:
        trainer = Trainer(cfg, run_dir, resume=args.resume, progress=not args.no_progress, sink=sink)
    except BaseException:
        if sink is not None:
            sink.close()
        raise
    summary = trainer.run()
    if sink is not None:
        print(f"recorded {sink.bag.messages} messages to {sink.path}", file=sys.stderr)
    plot_runs([run_dir], run_dir / "curves.png")
    print(_done_line(summary, run_dir, ""))
    return 0


def _train_offline(args) -> int:
    from hdrqn_ros.recording.transitions import BagReadStats, bag_config, read_episodes
    from hdrqn_ros.training.offline import OfflineTrainer

    if args.record or args.resume:
        raise UsageError("--from-bag cannot be combined with --record or --resume")
    if args.updates is not None and args.updates < 1:
        raise UsageError(f"--updates must be >= 1, got {args.updates}")
    run_dir = Path(args.out)
    base = bag_config(args.from_bag[0])
    cfg = _config_from_args(args, base=base, num_envs=args.num_envs, device=args.device,
                            eval_every=args.eval_every)
    origin = "the bag's recorded config" if base else "defaults (the bag has no recorded config)"
    print(f"offline {cfg.algo} on {cfg.env} {cfg.env_kwargs} from {len(args.from_bag)} bag(s), config from "
          f"{origin} -> {run_dir}", file=sys.stderr)
    trainer = OfflineTrainer(cfg, run_dir, progress=not args.no_progress)
    stats = BagReadStats()
    n = trainer.fill(read_episodes(args.from_bag, cfg, trainer.agent.num_subgoals, stats))
    for bag in args.from_bag:
        key = str(Path(bag))
        print(f"  {bag}: {stats.episodes.get(key, 0)} episodes ({stats.incomplete_episodes.get(key, 0)} "
              f"incomplete ones left out)", file=sys.stderr)
    if n == 0:
        raise UsageError(f"no complete episode for {cfg.algo} in {', '.join(args.from_bag)}")
    updates = args.updates or max(1, 10 * trainer.env_steps // cfg.update_every)
    summary = trainer.run(updates, evaluations=0 if args.eval_every == 0 else 5)
    before, final = summary["before_eval"] or {}, summary["final_eval"] or {}
    print(f"done: {summary['updates']} updates on {n} episodes ({summary['transitions']} transitions) in "
          f"{summary['wall_s']} s; greedy eval success {before.get('success', float('nan')):.2f} before -> "
          f"{final.get('success', float('nan')):.2f} after, steps {before.get('steps', float('nan')):.1f} -> "
          f"{final.get('steps', float('nan')):.1f}; run in {run_dir}")
    return 0


def cmd_up(args) -> int:
    import yaml

    from hdrqn_ros.graph import graph_processes, write_params
    from hdrqn_ros.middleware import BACKEND_ENV, BackendError, ParameterError, chosen_backend
    from hdrqn_ros.middleware.network import check_user_fastdds_profile
    from hdrqn_ros.supervisor import Supervisor
    from hdrqn_ros.training.plots import plot_runs

    run_dir = Path(args.out)
    try:
        backend = chosen_backend(args.middleware)
        if backend == "rclpy" and not args.interface:
            check_user_fastdds_profile()
    except (BackendError, ParameterError) as exc:
        raise UsageError(str(exc)) from None
    if not 1 <= args.groups <= MAX_GROUPS:
        raise UsageError(f"--groups must be in 1..{MAX_GROUPS} (4 node processes each), got {args.groups}")
    if (run_dir / "checkpoints" / "last.pt").exists() and not args.resume:
        raise UsageError(f"{run_dir} already holds a run; pass --resume to continue it or choose another --out")
    cfg = _config_from_args(args)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "summary.json").unlink(missing_ok=True)
    config_file = run_dir / "graph-config.yaml"
    config_file.write_text(yaml.safe_dump(cfg.model_dump(), sort_keys=False))
    if args.record and os.path.lexists(args.record):
        raise UsageError(f"{args.record} already exists; refusing to overwrite a recording")
    extra = {"learner": {"record": str(Path(args.record).resolve())}} if args.record else None
    params = write_params(cfg, run_dir, args.groups, config_file, interface=args.interface, extra=extra)
    env = {BACKEND_ENV: backend}
    if args.domain_id is not None:
        if not 0 <= args.domain_id <= 232:
            raise UsageError(f"--domain-id must be in 0..232, got {args.domain_id}")
        env["ROS_DOMAIN_ID"] = str(args.domain_id)
    specs = graph_processes(cfg, params, args.groups, respawn=not args.no_respawn)
    nodes = "rclpy (ROS 2 Jazzy, Fast DDS)" if backend == "rclpy" else "Cyclone DDS"
    print(f"starting {len(specs)} {nodes} node processes for {cfg.algo} on {cfg.env} {cfg.env_kwargs} "
          f"({args.groups} group(s), {cfg.episodes} episodes, DDS on {args.interface or 'loopback'}) -> {run_dir}; "
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
    print(_done_line(summary, run_dir, f" over {len(specs)} node processes, {summary.get('updates', 0)} updates"))
    return 0


def _graph_status(run_dir: Path) -> str:
    try:
        s = json.loads((run_dir / "status.json").read_text())
    except (OSError, ValueError):
        return "waiting for the learner"
    succ = "-" if s.get("success_last100") is None else f"{s['success_last100']:.2f}"
    return (f"episode {s['episodes']}/{s['target_episodes']} steps {s['env_steps']} ({s['steps_per_s']:.0f}/s) "
            f"updates {s['updates']} success {succ} eps {s['eps_sub']:.2f}/{s['eps_meta']:.2f}")


def cmd_eval(args) -> int:
    from collections import Counter

    from hdrqn_ros.config import MAX_ENVS
    from hdrqn_ros.envs.registration import make_batch
    from hdrqn_ros.training.learner import load_trained_agent, play, summarise
    from hdrqn_ros.training.subgoals import option_table, option_table_markdown

    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    if args.num_envs is not None and not 1 <= args.num_envs <= MAX_ENVS:
        raise UsageError(f"--num-envs must be in 1..{MAX_ENVS}, got {args.num_envs}")
    for flag, value in (("--epsilon", args.epsilon), ("--meta-epsilon", args.meta_epsilon)):
        if value is not None and not 0.0 <= value <= 1.0:  # also NaN
            raise UsageError(f"{flag} must be in [0, 1], got {value}")
    cfg, agent = load_trained_agent(args.checkpoint)
    sink = None
    if args.record:
        from hdrqn_ros.recording.transitions import TransitionRecorder

        sink = TransitionRecorder(args.record, cfg, min(args.num_envs or args.episodes, args.episodes),
                                  source=f"hdrqn eval --checkpoint {args.checkpoint} --epsilon {args.epsilon}")
    try:
        episodes = play(agent, cfg, args.episodes, args.seed, epsilon=args.epsilon, meta_epsilon=args.meta_epsilon,
                        sink=sink, num_envs=args.num_envs)
    finally:
        if sink is not None:
            sink.close()
    result = {"algo": cfg.algo, "env": cfg.env, **summarise(episodes)}
    if args.subgoals:
        domain = make_batch(cfg.env, 1, **cfg.env_kwargs)
        visits = sum((e.visits for e in episodes), Counter())
        result["steps_at_subgoal"] = {name: visits[g] / len(episodes) for g, name in enumerate(domain.subgoal_names)}
        if agent.meta is not None:
            rows = option_table([o for e in episodes for o in e.option_log], domain.subgoal_names,
                                domain.subgoal_neighbours)
            result["options"] = rows
            print(option_table_markdown(rows), file=sys.stderr)
    print(json.dumps(result, indent=2))
    if sink is not None:
        print(f"recorded {sink.bag.messages} messages to {sink.path}", file=sys.stderr)
    return 0


def cmd_experiment(args) -> int:
    import shlex

    from hdrqn_ros.config import parse_set
    from hdrqn_ros.experiments import EXPERIMENTS, default_jobs, manifest, run_experiment

    exp = EXPERIMENTS[args.name]
    parse_set(args.set)  # KEY=VALUE syntax, before any run starts
    sets = tuple(args.set)
    if args.episodes is not None and args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    jobs = args.jobs if args.jobs is not None else default_jobs()
    if jobs < 1:
        raise UsageError(f"--jobs must be >= 1, got {jobs}")
    out = Path(args.out or f"runs/{exp.name}")
    runs = exp.runs(args.seeds, args.algos)
    if not runs:
        raise UsageError(f"{exp.name} has no setting for {', '.join(args.algos)}")
    print(f"{exp.title}: {len(runs)} runs ({len(runs) // len(args.seeds)} settings x {len(args.seeds)} seeds), "
          f"{jobs} at a time -> {out}", file=sys.stderr)
    if args.dry_run:
        for run in manifest(exp, runs, out, args.episodes, sets)["runs"]:
            print(shlex.join(run["command"]))
        return 0
    results = run_experiment(exp, runs, out, args.episodes, jobs, sets, progress=not args.no_progress)
    failed = sorted(name for name, code in results.items() if code != 0)
    print(f"{exp.name}: {len(results) - len(failed)}/{len(runs)} runs finished"
          + (f"; failed: {', '.join(failed)}" if failed else "") + f"; next: hdrqn plot {out}")
    return 1 if failed else 0


def cmd_plot(args) -> int:
    from hdrqn_ros.training.plots import plot_runs

    if len(args.runs) == 1 and (Path(args.runs[0]) / "experiment.json").exists():
        from hdrqn_ros.training.report import report_experiment

        if args.label:
            raise UsageError("--label is for run directories; an experiment's labels come from experiment.json")
        paths, table = report_experiment(Path(args.runs[0]), Path(args.out) if args.out else None, args.window)
        print(table)
        for path in paths:
            print(path)
        return 0
    labels = {}
    for item in args.label:
        run, sep, label = item.partition("=")
        if not sep:
            raise UsageError(f"--label must be RUN_DIR=LABEL, got {item!r}")
        labels[str(Path(run))] = label
    out = plot_runs([Path(r) for r in args.runs], Path(args.out or "curves.png"), window=args.window, labels=labels)
    print(out)
    return 0


def _bag_play(args) -> int:
    """``hdrqn bag play``: the player node in this process."""
    import math

    from hdrqn_ros.middleware import BACKEND_ENV, BackendError, chosen_backend
    from hdrqn_ros.nodes.common import run_node
    from hdrqn_ros.nodes.player import PlayerNode

    if not (math.isfinite(args.rate) and args.rate > 0):
        raise UsageError(f"--rate must be > 0, got {args.rate}")
    if not (math.isfinite(args.delay) and args.delay >= 0):
        raise UsageError(f"--delay must be >= 0, got {args.delay}")
    if args.wait_for_subscribers < 0:
        raise UsageError(f"--wait-for-subscribers must be >= 0, got {args.wait_for_subscribers}")
    if args.domain_id is not None:
        if not 0 <= args.domain_id <= 232:
            raise UsageError(f"--domain-id must be in 0..232, got {args.domain_id}")
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)

    def yaml_float(x: float) -> str:  # "1e-05" is a string in YAML 1.1; "1.0e-05" a float
        mantissa, e, exponent = repr(float(x)).partition("e")
        return mantissa + ("" if "." in mantissa else ".0") + e + exponent

    ros = ["-p", f"bag:={json.dumps(args.bags)}", "-p", f"rate:={yaml_float(args.rate)}",
           "-p", f"loop:={str(args.loop).lower()}", "-p", f"topics:={json.dumps(args.topics or [''])}",
           "-p", f"clock:={str(not args.no_clock).lower()}", "-p", f"delay:={yaml_float(args.delay)}",
           "-p", f"wait_for_subscribers:={args.wait_for_subscribers}"]
    if args.interface:
        ros += ["-p", f"dds_interface:={json.dumps(args.interface)}"]
    try:
        os.environ[BACKEND_ENV] = chosen_backend(args.middleware)
    except BackendError as exc:
        raise UsageError(str(exc)) from None

    def progress(player) -> None:
        if player.bag_time_ns is None or player.start_ns is None:
            return
        done = max(0, player.published - (player.passes - 1) * player.total)
        print(f"bag play: pass {player.passes}, {done}/{player.total} messages, bag time "
              f"{(player.bag_time_ns - player.start_ns) / 1e9:.2f}/{(player.end_ns - player.start_ns) / 1e9:.2f} s",
              file=sys.stderr, flush=True)

    return run_node(lambda mw: PlayerNode(mw, progress=progress), ["hdrqn bag play", "--ros-args", *ros])


def cmd_bag(args) -> int:
    from hdrqn_ros.recording.bag import BagError, bag_summary, repair_bag
    from hdrqn_ros.recording.transitions import episode_summary

    if args.bag_command == "play":
        return _bag_play(args)
    try:
        if args.bag_command == "repair":
            report = repair_bag(args.bag)
            print(f"{report.path}: {report.message_count} messages in {len(report.files)} file(s); repaired "
                  f"{len(report.repaired)} file(s), recovering {report.messages_recovered} messages and dropping "
                  f"{report.bytes_dropped} bytes of incomplete data")
            return 0
        summary = bag_summary(args.bag)
    except BagError as exc:
        raise UsageError(str(exc)) from None
    try:
        summary["episodes"] = episode_summary(args.bag)
    except BagError as exc:  # env_step topics of another layout: the rest of the summary still holds
        summary["episodes"], summary["episodes_error"] = {}, str(exc)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"bag:      {summary['path']}\nfiles:    {len(summary['files'])}\nmessages: {summary['message_count']}\n"
          f"duration: {summary['duration_s']:.3f} s")
    width = max((len(t) for t in summary["topics"]), default=5)
    for topic, entry in sorted(summary["topics"].items()):
        print(f"  {topic:{width}s}  {entry['count']:8d}  {entry['type']}")
    groups = summary["episodes"]
    if "episodes_error" in summary:
        print(f"episodes: not readable as hdrqn transitions ({summary['episodes_error']})")
    if groups:
        print("episodes (complete; mean return, success rate, mean steps; incomplete):")
        width = max(len(g) for g in groups)
        for group, e in sorted(groups.items()):
            stats = ("-" if not e["episodes"] else
                     f"return {e['mean_return']:7.3f}  success {e['success_rate']:.2f}  steps {e['mean_steps']:6.1f}")
            print(f"  {group:{width}s}  {e['episodes']:6d}  {stats}  ({e['incomplete']} incomplete)")
        n = sum(e["episodes"] for e in groups.values())
        if len(groups) > 1 and n:
            ret = sum(e["mean_return"] * e["episodes"] for e in groups.values() if e["episodes"]) / n
            succ = sum(e["success_rate"] * e["episodes"] for e in groups.values() if e["episodes"]) / n
            print(f"  {'all':{width}s}  {n:6d}  return {ret:7.3f}  success {succ:.2f}")
    return 0


def cmd_envs(args) -> int:
    import gymnasium as gym

    from hdrqn_ros.envs.registration import ENV_IDS

    for env_id in ENV_IDS:
        spec = gym.spec(env_id)
        print(f"{env_id:32s} {spec.kwargs}")
    return 0


def _int(text: str, flag: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise UsageError(f"{flag} must be an integer or 'full', got {text!r}") from None


COMMANDS = {"train": cmd_train, "up": cmd_up, "eval": cmd_eval, "experiment": cmd_experiment, "plot": cmd_plot, "bag": cmd_bag, "envs": cmd_envs}


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # SIGTERM (kill, a job scheduler, `hdrqn experiment` stopping its runs) stops like Ctrl-C:
    # training saves its checkpoint first. SIGINT alone does not reach background jobs.
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _interrupt) if main_thread else None
    try:
        return _run(args)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, previous)


def _run(args) -> int:
    from hdrqn_ros.agents.controller import TrainingDiverged
    from hdrqn_ros.config import ConfigError
    from hdrqn_ros.recording.bag import BagError
    from hdrqn_ros.training.checkpoint import CheckpointError

    try:
        return COMMANDS[args.command](args)
    except (UsageError, ConfigError, CheckpointError, BagError, ValueError, OSError) as exc:
        if os.environ.get("HDRQN_DEBUG"):
            raise
        print(f"hdrqn {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except TrainingDiverged as exc:
        print(f"hdrqn {args.command}: training diverged: {exc}; the last good checkpoint is kept", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hdrqn {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `hdrqn experiment NAME --dry-run | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
