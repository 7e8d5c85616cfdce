"""Learning curves like thesis figures 4.6-4.11: reward, steps, extrinsic and intrinsic
reward and success ratio per episode, as a moving average, and (runs with ``losses.csv``)
each controller's TD loss, mean Q and gradient norm, and the meta-controller's mean Q by
option index beside the return obtained and the domain's return bound; runs sharing a
label (seeds) are drawn as their mean with a min-max band."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import yaml

from hdrqn_ros.training.metrics import read_csv, read_losses

PANELS = [("reward", "reward (classical)"), ("steps", "steps per episode"), ("extrinsic", "extrinsic reward"),
          ("intrinsic", "intrinsic reward"), ("success", "ordered success ratio")]
LOSS_PANELS = [("td_loss", "TD loss"), ("q_taken", "mean Q of the taken actions"),
               ("grad_norm", "gradient norm before clipping")]
CONTROLLER_LINES = {"sub": "-", "meta": "--"}
"""Line style of each controller in the loss panels."""
OPTION_LINES = ("-", "--", "-.", ":")
"""Line style of option index 0, 1, 2 and 3+ in the meta-controller's value panels."""
VALUE_PANELS = [("q", "meta: mean Q by option index (-: 0, --: 1, -.: 2, :: 3+)"),
                ("return", "meta: discounted return obtained by option index"),
                ("over", "meta: Q - return obtained by option index")]


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over up to ``window`` values (same length as ``x``)."""
    c = np.cumsum(np.insert(x.astype(float), 0, 0.0))
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def draw_mean_band(ax, x: np.ndarray, curves: np.ndarray, color: str, label: str, fmt: str = "-", **kw) -> None:
    """Draw ``curves`` (runs x points, over ``x``) on ``ax`` as their mean line, with a min-max
    band when there are several runs (seeds)."""
    ax.plot(x, curves.mean(0), fmt, color=color, label=label, **kw)
    if len(curves) > 1:
        ax.fill_between(x, curves.min(0), curves.max(0), color=color, alpha=0.2)


def run_label(run: Path) -> str:
    cfg = run / "config.yaml"
    if cfg.exists():
        data = yaml.safe_load(cfg.read_text()) or {}
        return str(data.get("algo", run.name))
    return run.name


def plot_runs(runs: list[Path], out: Path, window: int = 200, labels: dict[str, str] | None = None,
              title: str = "") -> Path:
    """Draw the curves of ``runs`` into ``out`` (PNG); returns ``out``. ``title`` heads the figure.

    A third row of panels shows each controller's ``losses.csv`` (sub: solid, meta: dashed)
    when a run has one. Raises ``FileNotFoundError`` when a run has no ``train.csv``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = labels or {}
    groups: dict[str, list[dict]] = defaultdict(list)
    evals: dict[str, list[dict]] = defaultdict(list)
    losses: dict[str, list[dict]] = defaultdict(list)
    for run in runs:
        train = read_csv(run / "train.csv")
        if not train:
            raise FileNotFoundError(f"{run} has no train.csv with rows: is it a run directory?")
        label = labels.get(str(run), run_label(run))
        groups[label].append(train)
        ev = read_csv(run / "eval.csv")
        if ev:
            evals[label].append(ev)
        if run_losses := read_losses(run / "losses.csv"):
            losses[label].append(run_losses)

    values = {label: [run["meta"] for run in runs if "q_opt0" in run.get("meta", {})] for label, runs in losses.items()}
    values = {label: tables for label, tables in values.items() if tables}
    rows = 2 + bool(losses) + bool(values)
    fig, axes = plt.subplots(rows, 3, figsize=(15, 4 * rows))
    for ax, (key, panel) in zip(axes.flat, PANELS):
        for i, (label, tables) in enumerate(groups.items()):
            n = min(len(t["episode"]) for t in tables)
            skip = min(window // 10, n - 1)  # the first few averages are over a handful of episodes
            curves = np.stack([moving_average(t[key][:n], window)[skip:] for t in tables])
            x = tables[0]["episode"][skip:n]
            draw_mean_band(ax, x, curves, f"C{i}", f"{label} (n={len(tables)})")
        ax.set_title(panel)
        ax.set_xlabel("episode")
        ax.grid(alpha=0.3)
    ax = axes.flat[5]
    for i, (label, tables) in enumerate(evals.items()):
        n = min(len(t["episode"]) for t in tables)
        curves = np.stack([t["success"][:n] for t in tables])
        x = tables[0]["episode"][:n]
        draw_mean_band(ax, x, curves, f"C{list(groups).index(label)}", label, "o-")
    ax.set_title("greedy evaluation: success ratio")
    ax.set_xlabel("episode")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    axes.flat[0].legend(loc="best", fontsize=8)
    if losses:
        _draw_losses(axes[2], losses, list(groups))
    if values:
        _draw_values(axes[3], values, list(groups), _return_bound(runs[0]))
    fig.suptitle((f"{title}\n" if title else "") + f"moving average over {window} episodes"
                 + ("; losses: means of blocks of updates" if losses else "") + "; band: min-max over runs")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def _draw_losses(axes, losses: dict[str, list[dict]], labels: list[str]) -> None:
    """The loss panels: per label (its colour, as in the other panels) and controller, the
    mean over its runs of ``losses.csv``'s rows (each a mean over ``log_every_updates``
    updates) against env steps (rows are far apart in episodes where many end at once)."""
    for ax, (key, panel) in zip(axes, LOSS_PANELS):
        for label, runs in losses.items():
            for controller, line in CONTROLLER_LINES.items():
                tables = [run[controller] for run in runs if controller in run]
                if not tables:
                    continue
                n = min(len(t["env_steps"]) for t in tables)
                curves = np.stack([t[key][:n] for t in tables])
                draw_mean_band(ax, tables[0]["env_steps"][:n], curves, f"C{labels.index(label)}",
                               f"{label} {controller}", line)
        ax.set_title(panel)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    axes[0].set_yscale("log")
    axes[0].legend(loc="best", fontsize=8)


def _return_bound(run: Path) -> float | None:
    """The largest return an episode of ``run``'s domain can give (None when unknown)."""
    cfg = run / "config.yaml"
    if not cfg.exists():
        return None
    from hdrqn_ros.envs.registration import make_batch

    data = yaml.safe_load(cfg.read_text()) or {}
    try:
        return getattr(make_batch(data["env"], 1, **data.get("env_kwargs", {})), "return_bound", None)
    except (KeyError, TypeError, ValueError, ImportError):
        return None


def _draw_values(axes, values: dict[str, list[dict]], labels: list[str], bound: float | None) -> None:
    """The meta-controller's mean Q(s_t, a_t) and discounted return obtained by option index
    t (``losses.csv``'s ``q_opt<t>``, ``return_opt<t>``) and their difference, per label (its
    colour), against env steps; the return bound as a grey line."""
    for ax, (key, panel) in zip(axes, VALUE_PANELS):
        for label, tables in values.items():
            n = min(len(t["env_steps"]) for t in tables)
            for index, line in enumerate(OPTION_LINES):
                q, ret = (np.stack([t[f"{stat}_opt{index}"][:n] for t in tables]) for stat in ("q", "return"))
                curves = {"q": q, "return": ret, "over": q - ret}[key]
                if np.isnan(curves).all():
                    continue
                draw_mean_band(ax, tables[0]["env_steps"][:n], curves, f"C{labels.index(label)}",
                               f"{label} option {index}{'+' if index == len(OPTION_LINES) - 1 else ''}", line)
        if bound is not None and key != "over":
            ax.axhline(bound, color="grey", lw=1)
            ax.annotate(" return bound", (0.0, bound), xycoords=("axes fraction", "data"), fontsize=8, color="grey")
        ax.set_title(panel)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=7)


def _figure(ncols: int = 1, width: float = 8.0):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(width, 4.5), squeeze=False)
    return plt, fig, axes[0]


def plot_success_ratio(groups: dict[str, list[Path]], out: Path, window: int = 200, title: str = "",
                       phase_end: int | None = None) -> Path:
    """Thesis figure 4.13a: the training success ratio (Montezuma: the key was picked up)
    per episode as a moving average over ``window`` episodes; ``groups``: label -> run
    directories (seeds: mean line, min-max band). ``phase_end``: draw the end of phase 1."""
    plt, fig, (ax,) = _figure()
    for i, (label, runs) in enumerate(groups.items()):
        tables = [t for t in (read_csv(r / "train.csv") for r in runs) if t]
        if not tables:
            continue
        n = min(len(t["episode"]) for t in tables)
        curves = np.stack([moving_average(t["success"][:n], window) for t in tables])
        x = tables[0]["episode"][:n]
        draw_mean_band(ax, x, curves, f"C{i}", f"{label} (n={len(tables)})")
    if phase_end:
        ax.axvline(phase_end, color="grey", ls="--", lw=1)
        ax.annotate(" end of phase 1", (phase_end, 0.95), xycoords=("data", "axes fraction"), fontsize=8, color="grey")
    ax.set_xlabel("episode")
    ax.set_ylabel(f"success ratio (moving average, {window} episodes)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def plot_subgoal_visits(groups: dict[str, list[Path]], out: Path, first_episode: int = 1, title: str = "") -> Path:
    """Thesis figure 4.13b: mean steps per episode the agent spent at each subgoal's place
    (``visits.csv``, episodes >= ``first_episode``), one bar per label (mean over seeds,
    whiskers min-max). Labels whose runs have no ``visits.csv`` are left out."""
    from hdrqn_ros.training.subgoals import visits_per_episode

    per_label = {}
    for label, runs in groups.items():
        seeds = [v for v in (visits_per_episode(r / "visits.csv", first_episode) for r in runs) if v]
        if seeds:
            per_label[label] = seeds
    if not per_label:
        raise FileNotFoundError(f"no run of {', '.join(groups)} has a visits.csv")
    names = list(next(iter(per_label.values()))[0])
    plt, fig, (ax,) = _figure(width=max(8.0, 1.3 * len(names)))
    width = 0.8 / len(per_label)
    x = np.arange(len(names))
    for i, (label, seeds) in enumerate(per_label.items()):
        values = np.array([[s[name] for name in names] for s in seeds])
        mean = values.mean(0)
        err = np.stack([mean - values.min(0), values.max(0) - mean])
        ax.bar(x + (i - (len(per_label) - 1) / 2) * width, mean, width, yerr=err if len(seeds) > 1 else None,
               color=f"C{i}", label=f"{label} (n={len(seeds)})", capsize=2)
    ax.set_xticks(x, names, rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("steps per episode at the subgoal")
    ax.set_yscale("symlog", linthresh=1.0)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title + (f" (episodes >= {first_episode})" if first_episode > 1 else ""), fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
