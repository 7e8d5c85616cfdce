"""Figures and a results table for an experiment directory (what ``hdrqn experiment`` wrote).

The table has one row per setting (label): its seeds, the final greedy ordered success
(mean, standard deviation, min-max and each seed), the mean of the last three greedy
evaluations, the training success of the last 500 episodes, greedy steps, the largest mean Q
of the meta-controller over its ``losses.csv`` rows (hierarchical agents; the largest return
an episode can give bounds it, docs/training.md "Value bound"), and the budget (episodes,
env steps, wall-clock per run).
"""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from hdrqn_ros.training.metrics import read_csv, read_losses
from hdrqn_ros.training.plots import plot_runs, plot_subgoal_visits, plot_success_ratio
from hdrqn_ros.training.subgoals import option_table_markdown


def load_manifest(exp_dir: Path) -> dict:
    path = Path(exp_dir) / "experiment.json"
    if not path.exists():
        raise FileNotFoundError(f"{exp_dir} has no experiment.json: is it an `hdrqn experiment` directory?")
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None


def training_seconds(wall_s: np.ndarray) -> float:
    """Wall-clock of a run from its ``train.csv`` ``wall_s`` column: each resumed part
    counts from 0 again, so the parts' last values add up."""
    ends = np.flatnonzero(np.diff(wall_s) < 0)
    return float(wall_s[ends].sum() + wall_s[-1])


def _run_row(run_dir: Path) -> dict | None:
    """The figures of one finished (or partly finished) run; None without any training row."""
    train, ev = read_csv(run_dir / "train.csv"), read_csv(run_dir / "eval.csv")
    if not train:
        return None
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    final = (summary.get("final_eval") or {}) if summary else {}
    row = {"episodes": int(train["episode"][-1]), "env_steps": int(train["env_steps"][-1]),
           "wall_min": training_seconds(train["wall_s"]) / 60, "finished": bool(summary),
           "train_success_last500": float(train["success"][-500:].mean())}
    meta = read_losses(run_dir / "losses.csv").get("meta")
    if meta is not None and len(meta["q_taken"]):
        row["meta_q_max"] = float(np.nanmax(meta["q_taken"]))
    if ev:
        row["final_success"] = float(final.get("success", ev["success"][-1]))
        row["final_steps"] = float(final.get("steps", ev["steps"][-1]))
        row["last3_success"] = float(ev["success"][-3:].mean())
    return row


def seed_spread(values: list[float]) -> tuple[float | None, float | None]:
    """(mean, sample standard deviation: n - 1 in the denominator) of one setting's per-seed
    results; sd 0 for one seed, both None for none."""
    if not values:
        return None, None
    return float(np.mean(values)), float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


def experiment_rows(exp_dir: Path) -> list[dict]:
    """One dict per setting (label, in the manifest's order) with per-seed and aggregate figures."""
    exp_dir = Path(exp_dir)
    manifest = load_manifest(exp_dir)
    by_label: dict[str, list[tuple[int, dict]]] = defaultdict(list)
    order: list[str] = []
    for run in manifest["runs"]:
        if run["label"] not in order:
            order.append(run["label"])
        row = _run_row(exp_dir / run["dir"])
        if row is not None:
            by_label[run["label"]].append((run["seed"], row))
    rows = []
    for label in order:
        runs = by_label.get(label, [])
        finals = [r["final_success"] for _, r in runs if "final_success" in r]
        final_mean, final_std = seed_spread(finals)
        rows.append({
            "label": label, "seeds": [s for s, _ in runs], "finished": sum(r["finished"] for _, r in runs),
            "final_success": finals,
            "final_mean": final_mean, "final_std": final_std,
            "last3_mean": float(np.mean([r["last3_success"] for _, r in runs if "last3_success" in r]))
            if finals else None,
            "train_last500": float(np.mean([r["train_success_last500"] for _, r in runs])) if runs else None,
            "steps": float(np.mean([r["final_steps"] for _, r in runs if "final_steps" in r])) if finals else None,
            "meta_q_max": [r["meta_q_max"] for _, r in runs if "meta_q_max" in r],
            "episodes": min((r["episodes"] for _, r in runs), default=0),
            "env_steps": int(np.mean([r["env_steps"] for _, r in runs])) if runs else 0,
            "wall_min": float(np.mean([r["wall_min"] for _, r in runs])) if runs else 0.0})
    return rows


def _fmt(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def markdown_table(rows: list[dict]) -> str:
    """The rows as a Markdown table (success figures are greedy, ordered, over 100 held-out episodes;
    sd is the sample standard deviation over the seeds, n - 1 in the denominator)."""
    lines = ["| setting | seeds (finished) | final greedy success: mean ± sd [min, max] | per seed | "
             "last 3 evals | training success (last 500) | greedy steps | largest meta mean Q per seed | "
             "episodes / env steps per run | wall-clock per run (min) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        finals = r["final_success"]
        spread = (f"**{r['final_mean']:.2f}** ± {r['final_std']:.2f} [{min(finals):.2f}, {max(finals):.2f}]"
                  if finals else "-")
        lines.append(f"| {r['label']} | {len(r['seeds'])} ({r['finished']}) | {spread} | "
                     f"{', '.join(f'{x:.2f}' for x in finals) or '-'} | {_fmt(r['last3_mean'])} | "
                     f"{_fmt(r['train_last500'])} | {_fmt(r['steps'], 1)} | "
                     f"{', '.join(f'{q:.3g}' for q in r['meta_q_max']) or '-'} | {r['episodes']} / {r['env_steps']} | "
                     f"{r['wall_min']:.1f} |")
    return "\n".join(lines)


def _phase1_end(run_dir: Path) -> int:
    """The run's ``sub_only_episodes`` (0: one phase), from its ``config.yaml``."""
    import yaml

    path = run_dir / "config.yaml"
    data = yaml.safe_load(path.read_text()) if path.exists() else None
    return int((data or {}).get("sub_only_episodes") or 0)


def phase1_sections(exp_dir: Path, runs: list[dict]) -> str:
    """Markdown of the phase-1 option tables (``phase1.json``) of the runs that have one."""
    parts = []
    for run in runs:
        path = Path(exp_dir) / run["dir"] / "phase1.json"
        if not path.exists():
            continue
        phase1 = json.loads(path.read_text())
        first, last = phase1["training_episodes"]
        parts.append(f"## Phase 1 of {run['dir']}: the sub-controller after {phase1['phase1_episodes']} episodes "
                     f"({phase1['env_steps']} env steps)\n\nGreedy sub-controller, subgoals at random, "
                     f"{phase1['greedy_episodes']} held-out episodes:\n\n{option_table_markdown(phase1['greedy'])}\n\n"
                     f"Training (epsilon-greedy), episodes {first}-{last}:\n\n"
                     f"{option_table_markdown(phase1['training'])}")
    return "\n\n".join(parts)


def report_experiment(exp_dir: Path, out_dir: Path | None = None, window: int = 200) -> tuple[list[Path], str]:
    """Draw one figure per thesis figure of the experiment and write ``exp_dir/table.md``.

    Curve figures (4.6-4.12) show the runs whose ``figure`` they are; the Montezuma figures
    4.13a (success ratio over training) and 4.13b (steps at each subgoal in phase 2) show
    every run. ``table.md`` also has the phase-1 tables of two-phase runs.
    Returns (figure paths, the Markdown text). Figures go to ``out_dir`` (default ``exp_dir``).
    """
    exp_dir = Path(exp_dir)
    out_dir = Path(out_dir) if out_dir is not None else exp_dir
    manifest = load_manifest(exp_dir)
    figures: dict[str, list[dict]] = defaultdict(list)
    started = [run for run in manifest["runs"] if read_csv(exp_dir / run["dir"] / "train.csv")]
    for run in started:
        for figure in run.get("figures") or [run["figure"]]:  # "figure": manifests before shared runs
            figures[figure].append(run)
    groups: dict[str, list[Path]] = defaultdict(list)
    for run in started:
        groups[run["label"]].append(exp_dir / run["dir"])
    phase_end = max((_phase1_end(exp_dir / r["dir"]) for r in started), default=0)
    paths = []
    for figure, title in manifest.get("figures", {}).items():
        out = out_dir / f"{manifest['experiment']}_{figure.replace('.', '_')}.png"
        heading = f"{figure}: {title}"
        if figure == "fig4.13a" and started:
            paths.append(plot_success_ratio(groups, out, window=window, title=heading, phase_end=phase_end or None))
        elif figure == "fig4.13b" and started:
            paths.append(plot_subgoal_visits(groups, out, first_episode=phase_end + 1, title=heading))
        elif figures.get(figure):
            runs = figures[figure]
            labels = {str(exp_dir / r["dir"]): r["label"] for r in runs}
            paths.append(plot_runs([exp_dir / r["dir"] for r in runs], out, window=window, labels=labels,
                                   title=heading))
    table = markdown_table(experiment_rows(exp_dir))
    phase1 = phase1_sections(exp_dir, started)
    text = table + (f"\n\n{phase1}" if phase1 else "")
    (exp_dir / "table.md").write_text(f"# {manifest['title']}\n\n{text}\n")
    return paths, text
