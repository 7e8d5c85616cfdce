"""``hdrqn values``: a run's Q-values where each recurrent controller acts, against where
its zero-state training windows put them, beside the return obtained
(:mod:`hdrqn_ros.training.value_audit`; docs/training.md, "Value bound")."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from hdrqn_ros.cli.common import UsageError, given_paths


def add_values(sub) -> None:
    parser = sub.add_parser(
        "values", help="a run's Q-values at its acting states against zero-state windows, beside the returns",
        description="Loads RUN's last checkpoint and its replay snapshot and runs each recurrent controller over the "
                    "newest stored episodes twice: unrolled from each segment's start (as it acts) and from a zero "
                    "state at every window start (as the thesis's random updates train it). Prints, by position in "
                    "the segment (the meta-controller's option index), the return obtained, the acting Q and the "
                    "zero-state Q at each window position.")
    parser.add_argument("run", metavar="RUN", help="a run directory of hdrqn train (with checkpoints/last.pt)")
    parser.add_argument("--episodes", type=int, default=200, metavar="N", help="the newest N episodes (default 200)")
    parser.add_argument("--json", metavar="FILE", help="also write the tables as JSON")


def cmd_values(args) -> int:
    given_paths(run=args.run, json=args.json)
    if args.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {args.episodes}")
    from hdrqn_ros.training.value_audit import audit_markdown, audit_run

    tables = audit_run(args.run, args.episodes)
    if not tables:
        print(f"hdrqn values: {args.run} has no recurrent controller", file=sys.stderr)
    for table in tables:
        print(audit_markdown(table), end="\n\n")
    if args.json:
        Path(args.json).write_text(json.dumps(tables, indent=2))
    return 0
