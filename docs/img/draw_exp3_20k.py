"""Draw experiment 3 on two goals in the gridworld at the thesis's budget (figure 4.10, left,
20,000 episodes): each algorithm's greedy ordered success at every evaluation (100 episodes
every 500), mean over its seeds with a min-max band.

    .venv/bin/python docs/img/draw_exp3_20k.py

reads docs/results/exp3-20k/*/eval.csv and docs/results/exp3-20k-flat/*/eval.csv (the run
directories' metrics, copied there as the runs finished; run names ALGO-sSEED) and writes
docs/img/exp3-gridworld-2goals-20k_eval.png.
"""
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from a checkout

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hdrqn_ros.training.metrics import read_csv  # noqa: E402
from hdrqn_ros.training.plots import draw_mean_band  # noqa: E402

DOCS = Path(__file__).resolve().parents[1]
ORDER = ["hdrqn-v2", "hdrqn-v1", "hdqn", "drqn", "dqn"]


def main() -> None:
    runs = defaultdict(list)  # algo -> eval tables of its seeds
    for eval_csv in sorted(DOCS.glob("results/exp3-20k*/*/eval.csv")):
        algo = eval_csv.parent.name.rsplit("-s", 1)[0]
        runs[algo].append(read_csv(eval_csv))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i, algo in enumerate(a for a in ORDER if a in runs):
        tables = runs[algo]
        n = min(len(t["episode"]) for t in tables)
        success = np.stack([t["success"][:n] for t in tables])
        x = tables[0]["episode"][:n]
        draw_mean_band(ax, x, success, f"C{i}", f"{algo} (n={len(tables)})", "o-", ms=3)
    ax.set_xlabel("episode")
    ax.set_ylabel("greedy ordered success (100 episodes)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("Experiment 3, two goals, gridworld, 5x5 view, 20,000 episodes\n"
                 "mean over seeds; band: min-max", fontsize=10)
    fig.tight_layout()
    out = DOCS / "img" / "exp3-gridworld-2goals-20k_eval.png"
    fig.savefig(out, dpi=90)
    print(out)


if __name__ == "__main__":
    main()
