"""``hdrqn experiment`` (a thesis experiment over seeds), ``hdrqn plot`` (its figures, or
runs' learning curves) and ``hdrqn envs``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hdrqn_ros.cli.common import UsageError


def add_experiment(sub) -> None:
    from hdrqn_ros.cluster import add_ray_arguments
    from hdrqn_ros.config import ALGOS
    from hdrqn_ros.experiments import EXPERIMENTS

    parser = sub.add_parser("experiment", help="run a thesis experiment (chapter 4) over several seeds, in parallel",
                            formatter_class=argparse.RawDescriptionHelpFormatter,
                            description="Runs every setting of the experiment for every seed as `hdrqn train` "
                                        "processes (JOBS at a time, or as tasks of a Ray cluster with --ray; logs in "
                                        "OUT/RUN.log). Finished runs are skipped "
                                        "and interrupted ones resumed, so the same command continues an experiment. "
                                        "Then `hdrqn plot OUT` draws its figures and table.",
                            epilog="experiments:\n" + "\n".join(f"  {e.name:24s} {e.title}"
                                                                 for e in EXPERIMENTS.values()))
    parser.add_argument("name", choices=list(EXPERIMENTS), metavar="NAME", help="experiment (listed below)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="seeds (default 0 1 2)")
    parser.add_argument("--algos", nargs="+", choices=ALGOS, help="run only the settings of these algorithms")
    parser.add_argument("--episodes", type=int, help="episodes per run (default: the config's, i.e. the thesis's)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key in every run, e.g. --set device=cuda --set num_envs=32")
    parser.add_argument("--jobs", type=int, help="runs at a time (default: one per core)")
    parser.add_argument("--out", metavar="DIR", help="experiment directory (default runs/NAME)")
    parser.add_argument("--dry-run", action="store_true", help="print the runs' commands and exit")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_ray_arguments(parser)


def add_plot(sub) -> None:
    parser = sub.add_parser("plot", help="draw learning curves of runs (thesis figures 4.6-4.11) to PNG",
                            description="Runs with the same label (default: the algorithm) are averaged: mean "
                                        "line and min-max band over seeds. Given one `hdrqn experiment` directory, "
                                        "draws each of its thesis figures and writes table.md (also printed).")
    parser.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories, or one experiment directory")
    parser.add_argument("--out", help="output PNG (default curves.png; for an experiment: the folder for its figures)")
    parser.add_argument("--window", type=int, default=200, help="moving-average window in episodes")
    parser.add_argument("--label", action="append", default=[], metavar="RUN_DIR=LABEL",
                        help="name a run's curve (default: its algorithm)")


def add_envs(sub) -> None:
    sub.add_parser("envs", help="list the environment ids and their default options",
                   description="Lists every registered environment id (gymnasium's hdrqn/... ids) with its "
                               "default options (view, step limit, ...), which --view and env_kwargs change.")


def cmd_experiment(args) -> int:
    import shlex

    from hdrqn_ros.cluster import ray_options, run_experiment_on_ray
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
    ray_kw = ray_options(args)  # {} without --ray
    out = Path(args.out or f"runs/{exp.name}")
    runs = exp.runs(args.seeds, args.algos)
    if not runs:
        raise UsageError(f"{exp.name} has no setting for {', '.join(args.algos)}")
    print(f"{exp.title}: {len(runs)} runs ({len(runs) // len(args.seeds)} settings x {len(args.seeds)} seeds), "
          + (f"as Ray tasks ({args.ray})" if args.ray is not None else f"{jobs} at a time") + f" -> {out}",
          file=sys.stderr)
    if args.dry_run:
        for run in manifest(exp, runs, out, args.episodes, sets)["runs"]:
            print(shlex.join(run["command"]))
        return 0
    if args.ray is not None:
        results = run_experiment_on_ray(exp, runs, out, args.episodes, extra_sets=sets,
                                        progress=not args.no_progress, **ray_kw)
    else:
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


def cmd_envs(args) -> int:
    import gymnasium as gym

    from hdrqn_ros.envs.registration import ENV_IDS

    for env_id in ENV_IDS:
        spec = gym.spec(env_id)
        print(f"{env_id:32s} {spec.kwargs}")
    return 0
