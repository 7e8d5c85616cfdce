"""The ``hdrqn`` command: train, evaluate, plot, and look at the environments.

Exit codes: 0 success, 1 a run failed (e.g. diverged), 2 misuse (bad arguments, config,
checkpoint or file), 130 interrupted.

One module per command group: :mod:`~hdrqn_ros.cli.train` (train, eval),
:mod:`~hdrqn_ros.cli.values` (values), :mod:`~hdrqn_ros.cli.graph` (up), :mod:`~hdrqn_ros.cli.experiment` (experiment, plot,
envs), :mod:`~hdrqn_ros.cli.bag` (bag info, repair, play), :mod:`~hdrqn_ros.cli.export`
(export); this module wires them into
one parser and runs a command with the exit codes above.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import threading

from hdrqn_ros import __version__
from hdrqn_ros.cli.bag import add_bag, cmd_bag
from hdrqn_ros.cli.common import UsageError
from hdrqn_ros.cli.experiment import add_envs, add_experiment, add_plot, cmd_envs, cmd_experiment, cmd_plot
from hdrqn_ros.cli.export import add_export, cmd_export
from hdrqn_ros.cli.graph import MAX_GROUPS, add_up, cmd_up
from hdrqn_ros.cli.robot import add_robot, cmd_robot
from hdrqn_ros.cli.train import add_eval, add_train, cmd_eval, cmd_train
from hdrqn_ros.cli.values import add_values, cmd_values

EPILOG = """examples:
  hdrqn train --algo hdrqn-v2 --env hdrqn/GridWorld-2Goals-v0 --episodes 2000 --out runs/v2
  hdrqn train --config config/exp3_gridworld_2goals.yaml --algo hdqn --seed 1 --out runs/hdqn-s1
  hdrqn up --episodes 300 --out runs/graph     # the same training over the ROS 2 node graph
  hdrqn eval --checkpoint runs/v2/checkpoints/last.pt --episodes 200
  hdrqn values runs/v2                         # Q where it acts vs. zero-state windows, vs. returns
  hdrqn export --checkpoint runs/v2/checkpoints/last.pt --out policy/   # ONNX, acting without torch
  hdrqn plot runs/v2 runs/hdqn-s1 --out curves.png
  hdrqn experiment exp3-gridworld-2goals --seeds 0 1 2 --episodes 5000   # a thesis experiment
  hdrqn plot runs/exp3-gridworld-2goals                                  # its figures and table
  hdrqn envs
"""

__all__ = ["main", "build_parser", "COMMANDS", "UsageError", "MAX_GROUPS"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hdrqn", formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
        description="Hierarchical deep recurrent Q-learning (hDRQN) on partially observable hierarchical tasks.")
    parser.add_argument("--version", action="version", version=f"hdrqn_ros {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in (add_train, add_up, add_eval, add_values, add_robot, add_export, add_experiment, add_plot, add_bag,
                add_envs):
        add(sub)
    return parser


COMMANDS = {"train": cmd_train, "up": cmd_up, "eval": cmd_eval, "export": cmd_export, "experiment": cmd_experiment,
            "plot": cmd_plot, "bag": cmd_bag, "envs": cmd_envs, "robot": cmd_robot, "values": cmd_values}


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def _parse(parser: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """``parser.parse_args(argv)``, but an unrecognised argument is reported by the (sub)command's
    own parser, with its usage line (``hdrqn eval: error: ...``), not the top-level one."""
    args, extra = parser.parse_known_args(argv)
    if extra:
        command = parser
        while (chosen := next((a for a in command._actions if isinstance(a, argparse._SubParsersAction)), None)) \
                and getattr(args, chosen.dest, None) in chosen.choices:
            command = chosen.choices[getattr(args, chosen.dest)]
        command.error(f"unrecognized arguments: {' '.join(extra)}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = _parse(build_parser(), argv)
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
    except BrokenPipeError:  # e.g. `hdrqn experiment NAME --dry-run | head`, `hdrqn values RUN | head`
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
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
