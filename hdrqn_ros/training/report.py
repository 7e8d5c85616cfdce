"""Figures and a results table for an experiment directory (what ``hdrqn experiment`` wrote).

The table has one row per setting (label): its seeds, the final greedy ordered success
(mean, standard deviation, min-max and each seed), the mean of the last three greedy
evaluations, the training success of the last 500 episodes, greedy steps, and the budget
(episodes, env steps, wall-clock per run).
"""
from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from hdrqn_ros.training.plots import plot_runs, read_csv


def load_manifest(exp_dir: Path) -> dict:
    path = Path(exp_dir) / "experiment.json"
    if not path.exists():
        raise FileNotFoundError(f"{exp_dir} has no experiment.json: is it an `hdrqn experiment` directory?")
    try:
        return json.loads(path.read_text())
    except ValueError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc}") from None


def _run_row(run_dir: Path) -> dict | None:
    """The figures of one finished (or partly finished) run; None without any training row."""
    train, ev = read_csv(run_dir / "train.csv"), read_csv(run_dir / "eval.csv")
    if not train:
        return None
    summary_path = run_dir / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    final = (summary.get("final_eval") or {}) if summary else {}
    row = {"episodes": int(train["episode"][-1]), "env_steps": int(train["env_steps"][-1]),
           "wall_min": float(train["wall_s"][-1]) / 60, "finished": bool(summary),
           "train_success_last500": float(train["success"][-500:].mean())}
    if ev:
        row["final_success"] = float(final.get("success", ev["success"][-1]))
        row["final_steps"] = float(final.get("steps", ev["steps"][-1]))
        row["last3_success"] = float(ev["success"][-3:].mean())
    return row


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
        rows.append({
            "label": label, "seeds": [s for s, _ in runs], "finished": sum(r["finished"] for _, r in runs),
            "final_success": finals,
            "final_mean": float(np.mean(finals)) if finals else None,
            "final_std": float(np.std(finals)) if finals else None,
            "last3_mean": float(np.mean([r["last3_success"] for _, r in runs if "last3_success" in r]))
            if finals else None,
            "train_last500": float(np.mean([r["train_success_last500"] for _, r in runs])) if runs else None,
            "steps": float(np.mean([r["final_steps"] for _, r in runs if "final_steps" in r])) if finals else None,
            "episodes": min((r["episodes"] for _, r in runs), default=0),
            "env_steps": int(np.mean([r["env_steps"] for _, r in runs])) if runs else 0,
            "wall_min": float(np.mean([r["wall_min"] for _, r in runs])) if runs else 0.0})
    return rows


def _fmt(x: float | None, digits: int = 2) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def markdown_table(rows: list[dict]) -> str:
    """The rows as a Markdown table (success figures are greedy, ordered, over 100 held-out episodes)."""
    lines = ["| setting | seeds (finished) | final greedy success: mean ± sd [min, max] | per seed | "
             "last 3 evals | training success (last 500) | greedy steps | episodes / env steps per run | "
             "wall-clock per run (min) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        finals = r["final_success"]
        spread = (f"**{r['final_mean']:.2f}** ± {r['final_std']:.2f} [{min(finals):.2f}, {max(finals):.2f}]"
                  if finals else "-")
        lines.append(f"| {r['label']} | {len(r['seeds'])} ({r['finished']}) | {spread} | "
                     f"{', '.join(f'{x:.2f}' for x in finals) or '-'} | {_fmt(r['last3_mean'])} | "
                     f"{_fmt(r['train_last500'])} | {_fmt(r['steps'], 1)} | {r['episodes']} / {r['env_steps']} | "
                     f"{r['wall_min']:.1f} |")
    return "\n".join(lines)


def report_experiment(exp_dir: Path, out_dir: Path | None = None, window: int = 200) -> tuple[list[Path], str]:
    """Draw one figure per thesis figure of the experiment and write ``exp_dir/table.md``.

    Returns (figure paths, the Markdown table). Figures go to ``out_dir`` (default ``exp_dir``).
    """
    exp_dir = Path(exp_dir)
    out_dir = Path(out_dir) if out_dir is not None else exp_dir
    manifest = load_manifest(exp_dir)
    figures: dict[str, list[dict]] = defaultdict(list)
    for run in manifest["runs"]:
        if read_csv(exp_dir / run["dir"] / "train.csv"):
            figures[run["figure"]].append(run)
    paths = []
    for figure, runs in figures.items():
        labels = {str(exp_dir / r["dir"]): r["label"] for r in runs}
        title = manifest.get("figures", {}).get(figure, "")
        out = out_dir / f"{manifest['experiment']}_{figure.replace('.', '_')}.png"
        paths.append(plot_runs([exp_dir / r["dir"] for r in runs], out, window=window, labels=labels,
                               title=f"{figure}: {title}" if title else figure))
    table = markdown_table(experiment_rows(exp_dir))
    (exp_dir / "table.md").write_text(f"# {manifest['title']}\n\n{table}\n")
    return paths, table
