"""Draw one four-rooms state seen through every view (docs/img/gridworld_views.png).

    python docs/img/draw_gridworld_views.py [OUT.png]   # default runs/figures/gridworld_views.png
"""
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import gymnasium as gym
import matplotlib.pyplot as plt

import hdrqn_ros  # noqa: F401  (registers the ids)


def main(out: str = "runs/figures/gridworld_views.png") -> None:
    panels = []
    for view in (3, 5, 11, "full"):
        env = gym.make("hdrqn/FourRooms-3Goals-v0", view=view, render_mode="rgb_array").unwrapped
        obs, _ = env.reset(seed=4)
        if not panels:
            panels.append(("the map (render)", env.render()))
        panels.append((f"observation, view={view}", obs))
        if view == 5:
            panels.append(("subgoal image (blue goal), view=5", env.subgoal_image(0)))
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.3))
    for ax, (title, img) in zip(axes, panels):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    print(out)


if __name__ == "__main__":
    main(*sys.argv[1:])
