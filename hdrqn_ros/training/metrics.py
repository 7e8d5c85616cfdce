"""Run-directory metrics: per-episode CSV, evaluation CSV and TensorBoard scalars."""
from __future__ import annotations

import csv
import warnings
from pathlib import Path

TRAIN_COLUMNS = ["episode", "env_steps", "steps", "reward", "extrinsic", "intrinsic", "success",
                 "options", "eps_sub", "eps_meta", "wall_s"]
EVAL_COLUMNS = ["episode", "env_steps", "episodes", "success", "steps", "reward", "extrinsic",
                "intrinsic", "wall_s", "updates"]


class MetricsLog:
    """Appends rows to ``train.csv`` / ``eval.csv`` in ``run_dir`` and mirrors them to
    TensorBoard (``run_dir/tb``). Appending keeps earlier rows when a run is resumed."""

    def __init__(self, run_dir: Path, tensorboard: bool = True):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._files = {}
        self._writers = {}
        for name, cols in (("train", TRAIN_COLUMNS), ("eval", EVAL_COLUMNS)):
            path = self.run_dir / f"{name}.csv"
            new = not path.exists() or path.stat().st_size == 0
            f = open(path, "a", newline="", encoding="utf-8")
            w = csv.DictWriter(f, fieldnames=cols)
            if new:
                w.writeheader()
            self._files[name], self._writers[name] = f, w
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

    def eval(self, row: dict, step_key: str = "episode") -> None:
        """An evaluation row; TensorBoard's x axis is ``row[step_key]`` (offline runs: updates)."""
        self._write("eval", row, step_key)

    def close(self) -> None:
        for f in self._files.values():
            f.close()
        if self.tb is not None:
            self.tb.close()
