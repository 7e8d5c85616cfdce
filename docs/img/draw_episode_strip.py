"""Draw one greedy hDRQNv2 episode on the two-goal gridworld (like thesis figure 4.14).

    .venv/bin/python docs/img/draw_episode_strip.py \
        --checkpoint runs/exp3-gridworld_2goals/hdrqn-v2-s1/checkpoints/last.pt --seed 12345

(seed 12345 solves the task in 5 steps, too short to show; the figures are of seed 12346.)
writes docs/img/episode_strip_gridworld.png (the map whenever the meta-controller picks a
subgoal and whenever an option ends) and docs/img/episode_gridworld.gif (every step, with
the sub-controller's inputs: the 5x5 observation and the subgoal image).

The episode is played by ``hdrqn_ros.training.learner.evaluate`` (what
``hdrqn eval --checkpoint CKPT --episodes 1 --seed S`` plays, epsilon 0 for both
controllers), for seeds S, S+1, ... until one collects every goal in order in at least
``--min-steps`` steps. Its actions are then replayed on a fresh batch reset with the same
seed (deterministic, checked) to render the map.
"""
import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # run from a checkout

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.patches as patches  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402

from hdrqn_ros.envs.gridworld import ACTIONS, GOAL_NAMES, MAP_SIZE  # noqa: E402
from hdrqn_ros.envs.registration import make_batch  # noqa: E402
from hdrqn_ros.training.learner import evaluate, load_trained_agent  # noqa: E402

IMG = Path(__file__).resolve().parent


class Steps(list):
    """``evaluate``'s sink: keeps env 0's row of every StepRecord."""

    def write(self, r):
        self.append(dict(obs=r.obs[0].copy(), new_option=bool(r.new_option[0]), subgoal=int(r.subgoal[0]),
                         sg_img=r.subgoal_image[0].copy(), action=int(r.action[0]), done=bool(r.option_done[0]),
                         at=int(r.env.at_subgoal[0]), extrinsic=float(r.env.extrinsic[0]),
                         pos=r.env.agent_pos[0].copy(), next_obs=r.env.obs[0].copy(),
                         truncated=bool(r.env.truncated[0])))


def play(cfg, agent, seed):
    """One greedy episode -> (steps, maps, positions, goal cells, success)."""
    steps = Steps()
    result = evaluate(agent, cfg, 1, seed, epsilon=0.0, sink=steps)
    batch = make_batch(cfg.env, 1, **cfg.env_kwargs)  # replay the actions to render the map
    batch.reset(seed=seed)
    maps, pos = [batch.render_map(0, cell_px=8)], [batch.agent_pos[0]]
    for s in steps:
        batch.step(np.array([s["action"]]))
        maps.append(batch.render_map(0, cell_px=8))
        pos.append(batch.agent_pos[0])
        assert (pos[-1] == s["pos"]).all() and (batch.render_obs()[0] == s["next_obs"]).all(), "replay diverged"
    return steps, maps, np.array(pos), batch.goal_pos[0], result["success"] == 1.0


def draw_map(ax, img, pos, t, goals, subgoal, view):
    """The map at step ``t``: path so far, the agent's view window, the subgoal outlined."""
    ax.imshow(img, extent=(-0.5, MAP_SIZE - 0.5, MAP_SIZE - 0.5, -0.5), interpolation="nearest")
    ax.plot(pos[:t + 1, 1], pos[:t + 1, 0], "-o", color="tab:orange", lw=2, ms=3)
    r, c = pos[t]
    h = view / 2
    ax.add_patch(patches.Rectangle((c - h, r - h), view, view, fill=False, ec="magenta", lw=2))
    gr, gc = goals[subgoal]
    ax.add_patch(patches.Rectangle((gc - 0.6, gr - 0.6), 1.2, 1.2, fill=False, ec="gold", lw=3.5))
    ax.set_xlim(-1.5, MAP_SIZE + 0.5)
    ax.set_ylim(MAP_SIZE + 0.5, -1.5)
    ax.set_xticks([])
    ax.set_yticks([])


def key_moments(steps):
    """(t, subgoal, caption) for every option start and option end, numbered."""
    out = []
    for t, s in enumerate(steps):
        name = f"{GOAL_NAMES[s['subgoal']]} goal"
        if s["new_option"]:
            out.append((t, s["subgoal"], f"picks {name} (step {t})"))
        if s["done"]:
            how = (f"reaches {name}" + (f", +{s['extrinsic']:g}" if s["extrinsic"] else "")
                   if s["at"] == s["subgoal"] else "option ends at the step limit")
            out.append((t + 1, s["subgoal"], f"{how} (step {t + 1})"))
    return [(t, g, f"({i}) {text}") for i, (t, g, text) in enumerate(out, 1)]


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--checkpoint", default="runs/exp3-gridworld_2goals/hdrqn-v2-s1/checkpoints/last.pt")
    p.add_argument("--seed", type=int, default=12345, help="first evaluation seed tried (hdrqn eval's default)")
    p.add_argument("--episodes-to-try", type=int, default=20)
    p.add_argument("--min-steps", type=int, default=12, help="skip shorter episodes (goals next to the agent)")
    p.add_argument("--out-png", default=str(IMG / "episode_strip_gridworld.png"))
    p.add_argument("--out-gif", default=str(IMG / "episode_gridworld.gif"))
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg, agent = load_trained_agent(args.checkpoint)
    view = cfg.env_kwargs.get("view", 5)
    for seed in range(args.seed, args.seed + args.episodes_to_try):
        steps, maps, pos, goals, success = play(cfg, agent, seed)
        print(f"seed {seed}: {len(steps)} steps, success {success}")
        if success and len(steps) >= args.min_steps:
            break
    else:
        sys.exit(f"no seed in [{args.seed}, {seed}] collects every goal in order in >= {args.min_steps} steps")
    T = len(steps)
    run = f"{cfg.algo} ({Path(args.checkpoint).resolve().parent.parent.name}), {cfg.env}, view {view}"

    moments = key_moments(steps)
    ncols = 2 if len(moments) % 2 == 0 and len(moments) <= 6 else 4
    nrows = -(-len(moments) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.1 * ncols, 3.3 * nrows + 0.6), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (t, g, caption) in zip(axes.flat, moments):
        ax.axis("on")
        draw_map(ax, maps[t], pos, t, goals, g, view)
        ax.set_title(caption, fontsize=9)
    fig.suptitle(f"{run}\ngreedy episode, seed {seed} (hdrqn eval --episodes 1 --seed {seed}): {T} steps\n"
                 f"path orange, {view}x{view} view magenta, current subgoal gold", fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out_png, dpi=90)
    plt.close(fig)
    print(args.out_png)

    frames = []
    fig, axes = plt.subplots(1, 3, figsize=(6.6, 2.9), gridspec_kw={"width_ratios": [2.2, 1, 1]})
    for t in range(T + 1):
        s = steps[min(t, T - 1)]
        for ax in axes:
            ax.clear()
        draw_map(axes[0], maps[t], pos, t, goals, s["subgoal"], view, )
        axes[1].imshow(s["obs"] if t < T else s["next_obs"], interpolation="nearest")
        axes[1].set_title(f"observation ({view}x{view})", fontsize=8)
        axes[2].imshow(s["sg_img"], interpolation="nearest")
        axes[2].set_title(f"subgoal image ({GOAL_NAMES[s['subgoal']]})", fontsize=8)
        for ax in axes[1:]:
            ax.set_xticks([])
            ax.set_yticks([])
        what = f"next action: {ACTIONS[s['action']]}" if t < T else "done: both goals collected in order"
        sub = "meta-controller picks" if t < T and s["new_option"] else "subgoal"
        fig.suptitle(f"seed {seed}, step {t}/{T}: {sub} {GOAL_NAMES[s['subgoal']]} goal; {what}", fontsize=9)
        fig.tight_layout()
        fig.canvas.draw()
        frames.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).quantize(128))
    plt.close(fig)
    frames[0].save(args.out_gif, save_all=True, append_images=frames[1:], loop=0, optimize=True,
                   duration=[400] * T + [2000])
    print(args.out_gif)


if __name__ == "__main__":
    main()
