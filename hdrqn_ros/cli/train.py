"""``hdrqn train`` (in-process, or offline from bags) and ``hdrqn eval``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from hdrqn_ros.cli.common import UsageError, config_from_args, done_line, given_paths


def add_train(sub) -> None:
    from hdrqn_ros.config import ALGOS
    from hdrqn_ros.envs.registration import ENV_IDS

    parser = sub.add_parser("train", help="train an agent in-process on N vectorised environments",
                            description="Train hDRQNv1/v2 or a baseline (thesis Algorithm 1). RUN_DIR receives "
                                        "checkpoints/, train.csv, eval.csv, losses.csv (TD loss, Q, gradient norm), "
                                        "tb/ (TensorBoard), curves.png and "
                                        "summary.json.")
    parser.add_argument("--algo", choices=ALGOS, help="algorithm (default hdrqn-v2)")
    parser.add_argument("--env", choices=ENV_IDS, metavar="ENV_ID",
                        help=f"environment id, one of: {', '.join(ENV_IDS)}")
    parser.add_argument("--episodes", type=int, help="training episodes (default 10000)")
    parser.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory")
    parser.add_argument("--config", action="append", default=[], metavar="FILE",
                        help="YAML config (repeatable; later files override earlier ones; flags override files)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override any config key, e.g. --set sub.seq_len=12 --set meta.epsilon.steps=20000")
    parser.add_argument("--seed", type=int, help="seed of environments, networks and exploration (default 0)")
    parser.add_argument("--num-envs", type=int, help="environments stepped together (default 16)")
    parser.add_argument("--view", help="observation window: 3, 5, 11 or full (gridworld domains)")
    parser.add_argument("--device", help="torch device, e.g. cpu or cuda")
    parser.add_argument("--eval-every", type=int, help="episodes between greedy evaluations (0: never)")
    parser.add_argument("--resume", action="store_true", help="continue the run in RUN_DIR from its last checkpoint")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    recording = parser.add_argument_group("recording and offline training (rosbag2 MCAP bags)")
    recording.add_argument("--record", metavar="BAG_DIR",
                           help="also record every transition to this new bag (the graph's topics, one group per env)")
    recording.add_argument("--record-split-mb", type=float, default=256.0, metavar="MB",
                           help="start a new bag file after this many MB (default 256)")
    recording.add_argument("--from-bag", nargs="+", metavar="BAG_DIR",
                           help="train offline: fill the replay from these bags (ours, or ros2 bag record -s mcap of "
                                "the graph's topics), train without an environment, then evaluate in it (5 greedy "
                                "evaluations, none with --eval-every 0); the config defaults to "
                                "the first bag's recorded one")
    recording.add_argument("--updates", type=int, metavar="N",
                           help="offline updates of each controller (default: 10 per update_every transitions)")


def add_eval(sub) -> None:
    parser = sub.add_parser("eval", help="run greedy evaluation episodes of a checkpoint or an exported policy "
                                         "(and record them)",
                            description="Plays --episodes episodes of a trained agent (a checkpoint, or an exported "
                                        "ONNX policy acting without torch) on held-out environments and prints "
                                        "their mean success, steps and rewards as JSON; --record writes them as an "
                                        "MCAP bag, --subgoals adds the meta-controller's options.")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", help="path to a checkpoint (RUN_DIR/checkpoints/last.pt)")
    source.add_argument("--policy", help="an exported policy directory (hdrqn export), acting with onnxruntime: "
                                         "the same episodes as its checkpoint")
    parser.add_argument("--episodes", type=int, default=100, help="episodes played, exactly (default 100)")
    parser.add_argument("--seed", type=int, default=12345,
                        help="seeds the environments (env i: seed + i) and the exploration (default 12345)")
    parser.add_argument("--num-envs", type=int, help="environments played in parallel, each the same number of "
                                                     "episodes: it must divide --episodes (default: one per episode, "
                                                     "at most 256)")
    parser.add_argument("--epsilon", type=float, default=0.0,
                        help="exploration of both controllers (default 0: greedy)")
    parser.add_argument("--meta-epsilon", type=float, metavar="E",
                        help="the meta-controller's exploration (default: --epsilon; 1: subgoals at random, "
                             "as phase 1)")
    parser.add_argument("--subgoals", action="store_true",
                        help="also report, per subgoal, how often the options aimed at it reached it (from its "
                             "neighbours and from anywhere) and the steps spent at each subgoal")
    parser.add_argument("--no-fire", action="store_true",
                        help="gridworld domains: no fire (the layouts of agent and goals stay the seed's), as on "
                             "the loopback robot (`hdrqn robot`)")
    parser.add_argument("--record", metavar="BAG_DIR",
                        help="record the episodes' transitions to this new bag (needs --checkpoint)")


def cmd_train(args) -> int:
    from hdrqn_ros.training.plots import plot_runs
    from hdrqn_ros.training.trainer import Trainer

    if args.from_bag:
        return _train_offline(args)
    if args.updates is not None:
        raise UsageError("--updates is for offline training (--from-bag)")
    run_dir = Path(args.out)
    cfg = config_from_args(args, num_envs=args.num_envs, device=args.device, eval_every=args.eval_every)
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
    if args.resume:
        print(trainer.resumed_line(), file=sys.stderr)
    summary = trainer.run()
    if sink is not None:
        print(f"recorded {sink.bag.messages} messages to {sink.path}", file=sys.stderr)
    plot_runs([run_dir], run_dir / "curves.png")
    print(done_line(summary, run_dir, ""))
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
    cfg = config_from_args(args, base=base, num_envs=args.num_envs, device=args.device,
                            eval_every=args.eval_every)
    origin = "the bag's recorded config" if base else "defaults (the bag has no recorded config)"
    print(f"offline {cfg.algo} on {cfg.env} {cfg.env_kwargs} from {len(args.from_bag)} bag(s), config from "
          f"{origin} -> {run_dir}", file=sys.stderr)
    trainer = OfflineTrainer(cfg, run_dir, progress=not args.no_progress)
    stats = BagReadStats()
    num_episodes = trainer.fill(read_episodes(args.from_bag, cfg, trainer.agent.num_subgoals, stats))
    for bag in args.from_bag:
        key = str(Path(bag))
        print(f"  {bag}: {stats.episodes.get(key, 0)} episodes ({stats.incomplete_episodes.get(key, 0)} "
              f"incomplete ones left out)", file=sys.stderr)
    if num_episodes == 0:
        raise UsageError(f"no complete episode for {cfg.algo} in {', '.join(args.from_bag)}")
    short = trainer.short_of_a_batch()
    if len(short) < len(trainer.agent.controllers):  # with none left, run() says so and exits 2
        for sentence in short:
            print(f"  warning: {sentence}", file=sys.stderr)
    updates = args.updates or max(1, 10 * trainer.env_steps // cfg.update_every)
    summary = trainer.run(updates, evaluations=0 if args.eval_every == 0 else 5)
    before, final = summary["before_eval"] or {}, summary["final_eval"] or {}
    print(f"done: {summary['updates']} updates on {num_episodes} episodes ({summary['transitions']} transitions) in "
          f"{summary['wall_s']} s; greedy eval success {before.get('success', float('nan')):.2f} before -> "
          f"{final.get('success', float('nan')):.2f} after, steps {before.get('steps', float('nan')):.1f} -> "
          f"{final.get('steps', float('nan')):.1f}; run in {run_dir}")
    return 0


def cmd_eval(args) -> int:
    from collections import Counter

    from hdrqn_ros.config import MAX_ENVS
    from hdrqn_ros.envs.registration import GRID_IDS, make_batch
    from hdrqn_ros.training.learner import eval_envs, load_trained_agent, play, summarise
    from hdrqn_ros.training.subgoals import option_table, option_table_markdown

    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    if args.num_envs is not None and not 1 <= args.num_envs <= MAX_ENVS:
        raise UsageError(f"--num-envs must be in 1..{MAX_ENVS}, got {args.num_envs}")
    try:
        num_envs = eval_envs(args.episodes, args.num_envs)
    except ValueError as exc:
        raise UsageError(f"--episodes {args.episodes} with --num-envs {args.num_envs}: {exc}") from None
    for flag, value in (("--epsilon", args.epsilon), ("--meta-epsilon", args.meta_epsilon)):
        if value is not None and not 0.0 <= value <= 1.0:  # also NaN
            raise UsageError(f"{flag} must be in [0, 1], got {value}")
    given_paths(checkpoint=args.checkpoint, policy=args.policy)
    if args.record and args.policy is not None:
        raise UsageError("--record needs --checkpoint: a bag keeps the training config, which an exported "
                         "policy does not carry")
    no_fire = {"obstacles": False} if args.no_fire else {}
    if args.policy is not None:
        from hdrqn_ros.extras import require

        require("deploy", "hdrqn eval --policy", ("onnxruntime",))
        from hdrqn_ros.deploy.onnx_agent import OnnxAgent
        from hdrqn_ros.deploy.onnx_policy import OnnxPolicy

        agent = OnnxAgent(OnnxPolicy.load(args.policy))
        cfg = agent.settings(**no_fire)
    else:
        cfg, agent = load_trained_agent(args.checkpoint)
        cfg = cfg.model_copy(update={"env_kwargs": {**cfg.env_kwargs, **no_fire}})
    if args.no_fire and cfg.env not in GRID_IDS:
        raise UsageError(f"--no-fire is for the gridworld domains; this agent was trained on {cfg.env}")
    sink = None
    if args.record:
        from hdrqn_ros.recording.transitions import TransitionRecorder

        sink = TransitionRecorder(args.record, cfg, num_envs,
                                  source=f"hdrqn eval --checkpoint {args.checkpoint} --epsilon {args.epsilon}")
    try:
        episodes = play(agent, cfg, args.episodes, args.seed, epsilon=args.epsilon, meta_epsilon=args.meta_epsilon,
                        sink=sink, num_envs=num_envs)
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
