"""What the ``hdrqn`` commands share: the usage error and the training config of a command line."""
from __future__ import annotations

from pathlib import Path


class UsageError(Exception):
    """Misuse of the command line: printed without a traceback, exit code 2."""


def given_paths(**paths: str | None) -> None:
    """Refuse a path option given as an empty string (``flag=value``; ``None``: not given)."""
    for flag, value in paths.items():
        if value is not None and not value.strip():
            raise UsageError(f"--{flag.replace('_', '-')} is empty: give a path")


def config_from_args(args, base: dict | None = None, **flags):
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


def done_line(summary: dict, run_dir: Path, how: str) -> str:
    ev = summary.get("final_eval") or {}
    return (f"done: {summary['episodes']} episodes, {summary['env_steps']} env steps in {summary['wall_s']} s "
            f"({summary['env_steps_per_s']} steps/s{how}); greedy eval: success {ev.get('success', float('nan')):.2f}, "
            f"steps {ev.get('steps', float('nan')):.1f}, reward {ev.get('reward', float('nan')):.2f}; "
            f"curves: {run_dir / 'curves.png'}")


def _int(text: str, flag: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise UsageError(f"{flag} must be an integer or 'full', got {text!r}") from None
