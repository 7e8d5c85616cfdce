"""Draw the 7 subgoal boxes of Montezuma's Revenge on the first screen.

    python docs/img/draw_montezuma_subgoals.py [OUT.png]   # default runs/figures/montezuma_subgoals.png

Each rectangle is the set of screen pixels where the agent's *centre* lies when its RAM
position is inside the subgoal's box (``hdrqn_ros.envs.montezuma.SUBGOAL_BOXES``).
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from a checkout

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.patches as patches  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402

from hdrqn_ros.envs.montezuma import SUBGOAL_NAMES, MontezumaBatch, subgoal_box_pixels  # noqa: E402


def main(out="runs/figures/montezuma_subgoals.png"):
    batch = MontezumaBatch(num_envs=1)
    batch.reset(seed=0)
    frame = batch.frames[0]
    fig, ax = plt.subplots(figsize=(4.8, 6.3), dpi=100)
    ax.imshow(frame, interpolation="nearest")
    for g, (r0, r1, c0, c1) in enumerate(subgoal_box_pixels()):
        ax.add_patch(patches.Rectangle((c0 - 0.5, r0 - 0.5), c1 - c0 + 1, r1 - r0 + 1, fill=False, ec="white", lw=1.2))
        right = c1 > 140
        ax.text(c1 if right else c0, r0 - 1.5, f"{g} {SUBGOAL_NAMES[g]}", color="white", fontsize=6.5,
                va="bottom", ha="right" if right else "left",
                bbox=dict(facecolor="black", alpha=0.6, pad=0.5, lw=0))
    ax.set_xticks(range(0, 161, 40))
    ax.set_yticks(range(0, 211, 30))
    ax.tick_params(labelsize=6)
    ax.set_title("Montezuma's Revenge, first room: subgoal boxes (agent centre)", fontsize=7)
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    print(out)


if __name__ == "__main__":
    main(*sys.argv[1:])
