"""Run-directory metrics, written and read back: per-episode CSV, evaluation CSV, the controllers' update
statistics (``losses.csv``) and TensorBoard scalars; for domains with subgoals also
``visits.csv`` (per episode: steps at each subgoal's place) and ``options.csv`` (one row
per option of a hierarchical agent)."""
from __future__ import annotations

import csv
import warnings
from collections import defaultdict
from pathlib import Path

import numpy as np

TRAIN_COLUMNS = ["episode", "env_steps", "steps", "reward", "extrinsic", "intrinsic", "success",
                 "options", "eps_sub", "eps_meta", "wall_s"]
EVAL_COLUMNS = ["episode", "env_steps", "episodes", "success", "steps", "reward", "extrinsic",
                "intrinsic", "wall_s", "updates"]
OPTION_COLUMNS = ["episode", "start", "subgoal", "steps", "reached"]
UPDATE_STATS = ["td_loss", "q_taken", "target", "grad_norm"]
"""A controller's means over ``log_every_updates`` updates: TD loss, Q(s_t, a_t) of the taken
actions and target y_t on the loss steps, gradient norm before clipping."""
OPTION_INDEX_STATS = [f"{stat}_opt{i}" for stat in ("q", "return") for i in range(4)]
"""The meta-controller's mean Q(s_t, a_t) and the discounted return obtained from t, by its
option index t in the episode (``opt3``: the fourth option or later); empty for the sub."""
LOSS_COLUMNS = ["episode", "env_steps", "updates", "controller", *UPDATE_STATS, *OPTION_INDEX_STATS]
TRAIN_LOSS_STATS = ["td_loss", "q_taken"]
"""The latest of these per controller also go into ``train.csv``, as ``<controller>_<stat>``."""
NOT_SCALARS = {"episode", "env_steps", "wall_s", "updates", "controller"}


def train_loss_columns(controllers: tuple[str, ...]) -> list[str]:
    """``train.csv``'s columns of the latest update statistics of ``controllers``."""
    return [f"{c}_{stat}" for c in controllers for stat in TRAIN_LOSS_STATS]


class MetricsLog:
    """Appends rows to ``train.csv`` / ``eval.csv`` / ``losses.csv`` in ``run_dir`` and
    mirrors them to TensorBoard (``run_dir/tb``). Appending keeps earlier rows when a run is
    resumed; a table keeps the columns of its existing header (a run begun before a column
    was added goes on without it). ``subgoal_names``: the domain's subgoals, the columns of
    ``visits.csv``; ``options``: also write ``options.csv`` (hierarchical agents);
    ``controllers``: the agent's controllers ("sub", and "meta" for hierarchical agents)."""

    def __init__(self, run_dir: Path, tensorboard: bool = True, subgoal_names: tuple[str, ...] = (),
                 options: bool = False, controllers: tuple[str, ...] = ("sub",)):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.subgoal_names = tuple(subgoal_names)
        self._files = {}
        self._writers = {}
        tables = [("train", TRAIN_COLUMNS + train_loss_columns(controllers)), ("eval", EVAL_COLUMNS),
                  ("losses", LOSS_COLUMNS)]
        if self.subgoal_names:
            tables.append(("visits", ["episode", *self.subgoal_names]))
        if options:
            tables.append(("options", OPTION_COLUMNS))
        for name, cols in tables:
            path = self.run_dir / f"{name}.csv"
            new = not path.exists() or path.stat().st_size == 0
            if not new:
                with open(path, newline="", encoding="utf-8") as f:
                    cols = next(csv.reader(f))
            file = open(path, "a", newline="", encoding="utf-8")
            writer = csv.DictWriter(file, fieldnames=cols, extrasaction="ignore")
            if new:
                writer.writeheader()
            self._files[name], self._writers[name] = file, writer
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.tb = SummaryWriter(str(self.run_dir / "tb"))
            except ImportError as exc:  # tensorboard is optional at run time
                warnings.warn(f"TensorBoard logging disabled: {exc}")

    def _write(self, name: str, row: dict, scalars: dict[str, float], step: int) -> None:
        """``row`` into ``name.csv``; ``scalars`` (tag -> value) to TensorBoard at ``step``."""
        self._writers[name].writerow(row)
        self._files[name].flush()
        if self.tb is not None:
            for tag, value in scalars.items():
                self.tb.add_scalar(tag, float(value), step)

    def train(self, row: dict) -> None:
        """An episode's row (TensorBoard: ``train/<column>``, x axis the episode); its update
        statistics columns are in TensorBoard once already, as ``losses/...``."""
        scalars = {f"train/{key}": value for key, value in row.items()
                   if key not in NOT_SCALARS and key in TRAIN_COLUMNS}
        self._write("train", row, scalars, int(row["episode"]))

    def losses(self, row: dict) -> None:
        """A ``losses.csv`` row of one controller (:data:`LOSS_COLUMNS`); TensorBoard:
        ``losses/<controller>/<stat>``, x axis the controller's updates."""
        scalars = {f"losses/{row['controller']}/{stat}": row[stat] for stat in UPDATE_STATS + OPTION_INDEX_STATS
                   if stat in row and row[stat] == row[stat]}  # NaN: no loss step had that option index
        self._write("losses", row, scalars, int(row["updates"]))

    def subgoals(self, episode: int, visits: dict[int, int], options) -> None:
        """``visits.csv`` and ``options.csv`` rows of one episode (``options``: OptionOutcome list)."""
        if "visits" in self._writers:
            self._writers["visits"].writerow({"episode": episode, **{name: visits.get(g, 0)
                                                                     for g, name in enumerate(self.subgoal_names)}})
            self._files["visits"].flush()
        if "options" not in self._writers:
            return
        for o in options:
            self._writers["options"].writerow({"episode": episode, "start": o.start, "subgoal": o.subgoal,
                                               "steps": o.steps, "reached": int(o.reached)})
        if options:
            self._files["options"].flush()

    def eval(self, row: dict, step_key: str = "episode") -> None:
        """An evaluation row (TensorBoard: ``eval/<column>``); the x axis is ``row[step_key]``
        (offline runs: updates)."""
        scalars = {f"eval/{key}": value for key, value in row.items() if key not in NOT_SCALARS}
        self._write("eval", row, scalars, int(row[step_key]))

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        if self.tb is not None:
            self.tb.close()


def _rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _columns(rows: list[dict[str, str]], skip: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """``rows``' columns (but ``skip``) as float arrays; an empty cell is NaN."""
    return {k: np.array([float(r[k]) if r[k] else np.nan for r in rows]) for k in rows[0] if k not in skip}


def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Columns of a metrics CSV as float arrays, NaN for an empty cell (empty dict for a
    missing/empty file)."""
    rows = _rows(path)
    return _columns(rows) if rows else {}


def read_losses(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """``losses.csv``'s rows per controller: controller -> column -> float array (empty dict
    for a missing/empty file)."""
    rows = _rows(path)
    by_controller: dict[str, list] = defaultdict(list)
    for row in rows:
        by_controller[row["controller"]].append(row)
    return {name: _columns(mine, skip=("controller",)) for name, mine in by_controller.items()}
