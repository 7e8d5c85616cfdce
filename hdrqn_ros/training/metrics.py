"""Run-directory metrics: per-episode CSV, evaluation CSV and TensorBoard scalars; for
domains with subgoals also ``visits.csv`` (per episode: steps at each subgoal's place) and
``options.csv`` (one row per option of a hierarchical agent)."""
from __future__ import annotations

import csv
import warnings
from pathlib import Path

TRAIN_COLUMNS = ["episode", "env_steps", "steps", "reward", "extrinsic", "intrinsic", "success",
                 "options", "eps_sub", "eps_meta", "wall_s"]
EVAL_COLUMNS = ["episode", "env_steps", "episodes", "success", "steps", "reward", "extrinsic",
                "intrinsic", "wall_s", "updates"]
OPTION_COLUMNS = ["episode", "start", "subgoal", "steps", "reached"]


class MetricsLog:
    """Appends rows to ``train.csv`` / ``eval.csv`` in ``run_dir`` and mirrors them to
    TensorBoard (``run_dir/tb``). Appending keeps earlier rows when a run is resumed.
    ``subgoal_names``: the domain's subgoals, the columns of ``visits.csv``; ``options``:
    also write ``options.csv`` (hierarchical agents)."""

    def __init__(self, run_dir: Path, tensorboard: bool = True, subgoal_names: tuple[str, ...] = (),
                 options: bool = False):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.subgoal_names = tuple(subgoal_names)
        self._files = {}
        self._writers = {}
        tables = [("train", TRAIN_COLUMNS), ("eval", EVAL_COLUMNS)]
        if self.subgoal_names:
            tables.append(("visits", ["episode", *self.subgoal_names]))
        if options:
            tables.append(("options", OPTION_COLUMNS))
        for name, cols in tables:
            path = self.run_dir / f"{name}.csv"
            new = not path.exists() or path.stat().st_size == 0
            file = open(path, "a", newline="", encoding="utf-8")
            writer = csv.DictWriter(file, fieldnames=cols)
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

    def _write(self, name: str, row: dict, step_key: str) -> None:
        self._writers[name].writerow(row)
        self._files[name].flush()
        if self.tb is not None:
            for key, value in row.items():
                if key not in ("episode", "env_steps", "wall_s", "updates"):
                    self.tb.add_scalar(f"{name}/{key}", float(value), int(row[step_key]))

    def train(self, row: dict) -> None:
        self._write("train", row, "episode")

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
        """An evaluation row; TensorBoard's x axis is ``row[step_key]`` (offline runs: updates)."""
        self._write("eval", row, step_key)

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        if self.tb is not None:
            self.tb.close()
