"""Subgoal statistics of a run: how often each subgoal is reached, and from where.

- The *option table* (thesis section 4.5, phase 1): for each subgoal, how many options
  aimed at it and how many reached it, overall and from its neighbours (the subgoals
  directly connected to it, ``DomainBatch.subgoal_neighbours``), with the median length
  of the successful ones.
- *Visits* (thesis figure 4.13b): primitive steps the agent spent at each subgoal's place.

The trainer writes both per episode (``options.csv``, ``visits.csv``; :mod:`metrics`);
the functions here aggregate them.
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from hdrqn_ros.training.episodes import OptionOutcome
from hdrqn_ros.training.metrics import read_csv

START_NAME = "elsewhere"
"""Label of options that began outside every subgoal's place (episode start, after a death)."""


def option_table(outcomes: Iterable[OptionOutcome], names: tuple[str, ...],
                 neighbours: tuple[tuple[int, ...], ...]) -> list[dict]:
    """One row per subgoal: ``attempts``/``reached``/``rate`` from its neighbours and from
    anywhere, and ``median_steps`` of the options that reached it (None without any)."""
    outcomes = list(outcomes)
    rows = []
    for g, name in enumerate(names):
        aimed = [o for o in outcomes if o.subgoal == g]
        near = [o for o in aimed if o.start in neighbours[g]]
        hit_steps = [o.steps for o in aimed if o.reached]
        rows.append({"subgoal": g, "name": name, "neighbours": [names[h] for h in neighbours[g]],
                     **_rate("neighbour", near), **_rate("all", aimed),
                     "median_steps": float(np.median(hit_steps)) if hit_steps else None})
    return rows


def _rate(prefix: str, options: list[OptionOutcome]) -> dict:
    reached = sum(o.reached for o in options)
    return {f"{prefix}_attempts": len(options), f"{prefix}_reached": reached,
            f"{prefix}_rate": reached / len(options) if options else None}


def option_table_markdown(rows: list[dict]) -> str:
    """The option table as Markdown (rates with their counts)."""

    def cell(row: dict, prefix: str) -> str:
        attempts = row[f"{prefix}_attempts"]
        return f"{row[f'{prefix}_rate']:.2f} ({row[f'{prefix}_reached']}/{attempts})" if attempts else "- (0)"

    lines = ["| subgoal | from its neighbours | reached from neighbours | reached from anywhere | "
             "median steps when reached |", "|---|---|---|---|---|"]
    for r in rows:
        steps = "-" if r["median_steps"] is None else f"{r['median_steps']:.0f}"
        lines.append(f"| {r['subgoal']} {r['name']} | {', '.join(r['neighbours'])} | **{cell(r, 'neighbour')}** | "
                     f"{cell(r, 'all')} | {steps} |")
    return "\n".join(lines)


def read_options(path: str | Path, first_episode: int = 1, last_episode: int | None = None) -> list[OptionOutcome]:
    """The options of episodes ``first_episode..last_episode`` from an ``options.csv``."""
    table = read_csv(Path(path))
    if not table:
        return []
    keep = table["episode"] >= first_episode
    if last_episode is not None:
        keep &= table["episode"] <= last_episode
    return [OptionOutcome(int(s), int(g), int(k), bool(r)) for s, g, k, r in
            zip(table["start"][keep], table["subgoal"][keep], table["steps"][keep], table["reached"][keep])]


def visits_per_episode(path: str | Path, first_episode: int = 1) -> dict[str, float]:
    """Mean steps per episode at each subgoal's place, from a ``visits.csv`` (episodes >= ``first_episode``)."""
    table = read_csv(Path(path))
    if not table:
        return {}
    keep = table["episode"] >= first_episode
    return {name: float(col[keep].mean()) if keep.any() else 0.0 for name, col in table.items() if name != "episode"}
