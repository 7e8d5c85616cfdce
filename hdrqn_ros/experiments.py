"""The thesis's experiments 1-4 (chapter 4) as named sets of ``hdrqn train`` runs.

An :class:`Experiment` expands into :class:`RunSpec` rows (one per setting and seed);
:func:`run_experiment` runs them as ``hdrqn train`` subprocesses, ``jobs`` at a time,
skipping finished runs and resuming interrupted ones from their checkpoints, and writes
``experiment.json`` (what ``hdrqn plot`` reads to draw the figures and the table).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from hdrqn_ros.agents.specs import ALGOS

RUN_METRICS = ("train.csv", "eval.csv", "losses.csv", "visits.csv", "options.csv", "phase1.json", "phase1.md")
"""A run's metrics files (:mod:`hdrqn_ros.training.metrics`, the phase-1 report)."""


def config_dir() -> Path:
    """The experiment configs: the source tree's ``config/``, else the installed ``share/hdrqn_ros/config``."""
    for path in (Path(__file__).resolve().parents[1] / "config", Path(sys.prefix) / "share" / "hdrqn_ros" / "config"):
        if (path / "exp3_gridworld_2goals.yaml").exists():
            return path
    raise FileNotFoundError("the experiment configs (config/exp*.yaml) are neither in the source tree nor in "
                            f"{Path(sys.prefix) / 'share' / 'hdrqn_ros' / 'config'}")


@dataclass(frozen=True)
class RunSpec:
    """One training run: ``hdrqn train --config CONFIG --algo ALGO --seed SEED --set ...``."""

    name: str                       # run directory name, e.g. "hdrqn-v2-nS8-s0"
    label: str                      # curve label, the same for all seeds of a setting
    figures: tuple[str, ...]        # the figures the curve belongs to, e.g. ("fig4.7", "fig4.8")
    algo: str
    seed: int
    sets: tuple[str, ...] = ()      # --set KEY=VALUE items
    view: str | None = None         # --view

    def argv(self, config: Path, out: Path, episodes: int | None, extra_sets: tuple[str, ...] = ()) -> list[str]:
        """The ``hdrqn train`` command line of this run (without the program); ``extra_sets``
        are the user's ``--set`` items, applied after the setting's own."""
        argv = ["train", "--config", str(config), "--algo", self.algo, "--seed", str(self.seed),
                "--out", str(out), "--no-progress"]
        for item in (*self.sets, *extra_sets):
            argv += ["--set", item]
        if self.view is not None:
            argv += ["--view", self.view]
        if episodes is not None:
            argv += ["--episodes", str(episodes)]
        return argv


@dataclass(frozen=True)
class Experiment:
    """A thesis experiment: its config file, claim, and settings (label, figures, algo, sets, view);
    a setting shared by two figures is one run in both."""

    name: str
    title: str
    claim: str
    config: str
    settings: tuple[tuple[str, tuple[str, ...], str, tuple[str, ...], str | None], ...]
    figures: dict[str, str] = field(default_factory=dict)  # figure id -> title

    def runs(self, seeds: list[int], algos: list[str] | None = None) -> list[RunSpec]:
        """Every setting for every seed (settings of ``algos`` only, when given), seeds innermost."""
        out = []
        for label, figures, algo, sets, view in self.settings:
            if algos and algo not in algos:
                continue
            for seed in seeds:
                name = f"{label.replace(' ', '-').replace('=', '')}-s{seed}"
                out.append(RunSpec(name, label, figures, algo, seed, sets, view))
        return out


def _exp1() -> Experiment:
    settings = []
    for algo, fig in (("hdrqn-v1", "fig4.6"), ("hdrqn-v2", "fig4.7")):
        for ns in (1, 4, 8, 12):
            # n^S = 8, n^M = 1 is also figure 4.8's n^M = 1 curve: one run for both
            label, figs = (f"{algo} nS=8 nM=1", (fig, "fig4.8")) if ns == 8 else (f"{algo} nS={ns}", (fig,))
            settings.append((label, figs, algo, (f"sub.seq_len={ns}", "meta.seq_len=1"), None))
    for algo in ("hdrqn-v1", "hdrqn-v2"):
        settings.append((f"{algo} nM=2", ("fig4.8",), algo, ("sub.seq_len=8", "meta.seq_len=2"), None))
    return Experiment(
        "exp1", "Experiment 1: lengths of sampled sub- and meta-transitions (two goals, gridworld, 5x5 view)",
        "n^S = 8 or 12 beat short sub-transitions (n^M = 1); with n^S = 8, hDRQNv1 does worse at n^M = 2 "
        "than at 1 while hDRQNv2 is the same at both, and hDRQNv2 beats hDRQNv1.",
        "exp1_sequence_length.yaml", tuple(settings),
        {"fig4.6": "hDRQNv1, n^M = 1, different n^S", "fig4.7": "hDRQNv2, n^M = 1, different n^S",
         "fig4.8": "n^S = 8, different n^M"})


def _exp2() -> Experiment:
    settings = tuple((f"{algo} view={view}", ("fig4.9",), algo, (), view)
                     for algo in ("hdrqn-v1", "hdrqn-v2") for view in ("3", "5", "full"))
    return Experiment(
        "exp2", "Experiment 2: levels of observation (two goals, gridworld)",
        "5x5 beats 3x3; the fully observable agent does best.", "exp2_observation.yaml", settings,
        {"fig4.9": "3x3, 5x5 and full observation"})


def _exp3(domain: str, goals: int) -> Experiment:
    fig = "fig4.10" if domain == "gridworld" else "fig4.11"
    return Experiment(
        f"exp3-{domain}-{goals}goals",
        f"Experiment 3: hDRQN against the baselines ({goals} goals, {domain}, 5x5 view)",
        "hDRQNv2 > hDRQNv1 > hDQN > DRQN / DQN.", f"exp3_{domain}_{goals}goals.yaml",
        tuple((algo, (fig,), algo, (), None) for algo in ALGOS), {fig: f"{goals} goals in {domain}"})


def _exp4() -> Experiment:
    return Experiment(
        "exp4-montezuma", "Experiment 4: Montezuma's Revenge, first room (phase 1: sub-controller only, then both)",
        "DQN and DRQN score 0; hDRQNv2 learns to pick up the key (figure 4.13a) and visits the subgoals on "
        "the way to it most (figure 4.13b); hDRQNv2 beats hDRQNv1 and hDQN.",
        "exp4_montezuma.yaml", tuple((algo, ("fig4.12",), algo, (), None) for algo in ALGOS),
        {"fig4.12": "Montezuma's Revenge, first room",
         "fig4.13a": "success ratio of picking up the key (training)",
         "fig4.13b": "steps at each subgoal per episode (phase 2)"})


META_TRAINING_CANDIDATES = (
    ("windows", ("meta.sampling=windows", "meta.time_limit=bootstrap")),
    ("whole", ("meta.sampling=whole", "meta.time_limit=bootstrap")),
    ("whole-tlterm", ("meta.sampling=whole", "meta.time_limit=terminal")),
    ("whole-lr1e-4", ("meta.sampling=whole", "meta.time_limit=bootstrap", "meta.lr=0.0001")),
    ("whole-smdp", ("meta.sampling=whole", "meta.time_limit=bootstrap", "smdp_discount=true")),
)
"""How hDRQNv2's meta-controller learns, the candidates screened on three goals (label, --set items):
the thesis's zero-state windows, whole episodes of options, and whole episodes with the time
limit terminal, Table 4.7's learning rate or the SMDP discount."""


def _meta_screen() -> Experiment:
    return Experiment(
        "meta-training-screen", "hDRQNv2's meta-controller: zero-state windows against whole episodes "
        "(three goals, gridworld, 5x5 view)",
        "Trained on whole episodes of options, hDRQNv2 learns the three-goal order on every seed and its meta "
        "Q-values stay within the return bound; on zero-state windows it does not.",
        "exp3_gridworld_3goals.yaml",
        tuple((label, ("screen",), "hdrqn-v2", sets, None) for label, sets in META_TRAINING_CANDIDATES),
        {"screen": "hDRQNv2, three goals: how the meta-controller learns"})


EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (
    _exp1(), _exp2(), _exp3("gridworld", 2), _exp3("gridworld", 3), _exp3("fourrooms", 2),
    _exp3("fourrooms", 3), _exp4(), _meta_screen())}


def run_done(run_dir: Path, episodes: int | None) -> bool:
    """Whether ``run_dir`` holds a finished run (of at least ``episodes`` episodes, when given)."""
    summary = run_dir / "summary.json"
    if not summary.exists():
        return False
    try:
        done = json.loads(summary.read_text())["episodes"]
    except (ValueError, KeyError, TypeError):
        return False
    return episodes is None or done >= episodes


def episodes_logged(run_dir: Path) -> int:
    """Training episodes in ``run_dir/train.csv`` (rows), 0 when there is none yet."""
    path = run_dir / "train.csv"
    if not path.exists():
        return 0
    with open(path, "rb") as f:
        return max(0, sum(1 for _ in f) - 1)


def manifest(exp: Experiment, runs: list[RunSpec], out: Path, episodes: int | None,
             extra_sets: tuple[str, ...] = ()) -> dict:
    """What ``experiment.json`` holds: the experiment, its budget, and each run's label, figures and command."""
    config = config_dir() / exp.config
    return {"experiment": exp.name, "title": exp.title, "claim": exp.claim, "config": str(config),
           "episodes": episodes, "sets": list(extra_sets), "figures": exp.figures,
           "runs": [{**asdict(r), "dir": r.name,
                     "command": ["hdrqn", *r.argv(config, out / r.name, episodes, extra_sets)]}
                    for r in runs]}


def write_manifest(exp: Experiment, runs: list[RunSpec], out: Path, episodes: int | None,
                   extra_sets: tuple[str, ...] = ()) -> Path:
    """Write ``out/experiment.json`` (see :func:`manifest`) and return its path. Runs an
    earlier invocation listed there with the same budget and ``--set`` items (e.g. other
    ``--algos`` or ``--seeds``) stay listed, in the experiment's order, so that ``hdrqn
    plot`` shows the whole experiment."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "experiment.json"
    data = manifest(exp, runs, out, episodes, extra_sets)
    try:
        earlier = json.loads(path.read_text()) if path.exists() else {}
    except ValueError:
        earlier = {}
    same = isinstance(earlier, dict) and all(earlier.get(k) == data[k] for k in ("experiment", "episodes", "sets"))
    if same and isinstance(earlier.get("runs"), list):
        listed = {r["dir"] for r in data["runs"]}
        merged = data["runs"] + [r for r in earlier["runs"] if isinstance(r, dict) and r.get("dir") not in listed
                                 and isinstance(r.get("seed"), int)]
        order = {spec.name: i for i, spec in enumerate(exp.runs(sorted({r["seed"] for r in merged})))}
        data["runs"] = sorted(merged, key=lambda r: order.get(r["dir"], len(order)))
    path.write_text(json.dumps(data, indent=2))
    return path


def set_aside(run_dir: Path) -> Path | None:
    """Move the metrics files of a run that left no checkpoint into ``run_dir/stale-<time>/``
    (a restart writes new ones from episode 1; nothing is deleted). Returns that folder, or
    None when there was nothing to move."""
    found = [run_dir / name for name in RUN_METRICS if (run_dir / name).exists()]
    if not found:
        return None
    folder = run_dir / time.strftime("stale-%Y%m%d-%H%M%S")
    folder.mkdir(exist_ok=True)
    for path in found:
        path.rename(folder / path.name)
    print(f"{run_dir} has no checkpoint: its earlier metrics are kept in {folder}; the run starts again",
          file=sys.stderr)
    return folder


INTERRUPTED = 130
"""``hdrqn train``'s exit code when Ctrl-C or SIGTERM stopped it (after its checkpoint)."""


def run_experiment(exp: Experiment, runs: list[RunSpec], out: Path, episodes: int | None, jobs: int,
                   extra_sets: tuple[str, ...] = (), progress: bool = True, poll_s: float = 2.0) -> dict[str, int]:
    """Run ``runs`` as ``hdrqn train`` subprocesses, ``jobs`` at a time; logs go to ``out/NAME.log``.

    Finished runs are skipped, interrupted ones continue with ``--resume``; a run stopped
    before its first checkpoint starts again (its partial metrics files are set aside,
    :func:`set_aside`).
    Returns each run's exit code (0 for skipped ones). Ctrl-C or SIGTERM stops the children
    (they checkpoint first), and so does a run interrupted on its own (exit :data:`INTERRUPTED`:
    Ctrl-C sent to a background job's process group, whose driver ignores SIGINT): no further run starts.
    """
    config = config_dir() / exp.config
    write_manifest(exp, runs, out, episodes, extra_sets)
    results, pending = split_finished(runs, out, episodes)
    target = target_episodes(config, episodes)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=target * len(runs), unit="ep", dynamic_ncols=True, desc=exp.name)
    running: dict[str, subprocess.Popen] = {}

    def show() -> None:
        if bar is not None:
            bar.n = sum(min(target, episodes_logged(out / r.name)) for r in runs)
            bar.set_postfix_str(f"running: {', '.join(running) or '-'}; done {len(results)}/{len(runs)}",
                                refresh=False)
            bar.refresh()

    try:
        show()
        while pending or running:
            while pending and len(running) < jobs:
                run = pending.pop(0)
                run_dir = out / run.name
                argv = run.argv(config, run_dir, episodes, extra_sets)
                if (run_dir / "checkpoints" / "last.pt").exists():
                    argv.append("--resume")
                else:
                    set_aside(run_dir)
                with open(out / f"{run.name}.log", "ab") as log:
                    running[run.name] = subprocess.Popen([sys.executable, "-m", "hdrqn_ros.cli", *argv],
                                                         stdout=log, stderr=subprocess.STDOUT,
                                                         stdin=subprocess.DEVNULL)
            for name, p in list(running.items()):
                if p.poll() is not None:
                    results[name] = p.returncode
                    del running[name]
                    if p.returncode == INTERRUPTED:  # a Ctrl-C or SIGTERM the driver itself did not get
                        raise KeyboardInterrupt(f"run {name} was interrupted")
                    if p.returncode != 0:
                        print(f"{exp.name}: run {name} failed (exit {p.returncode}); see {out / name}.log",
                              file=sys.stderr)
            show()
            if running:
                time.sleep(poll_s)
    except KeyboardInterrupt:
        for p in running.values():
            p.terminate()  # SIGTERM: hdrqn train saves a checkpoint, --resume continues
        for p in running.values():
            p.wait()
        raise
    finally:
        if bar is not None:
            bar.close()
    return results


def split_finished(runs: list[RunSpec], out: Path, episodes: int | None) -> tuple[dict[str, int], list[RunSpec]]:
    """({name: 0} of the runs already finished in ``out``, the runs still to do, in order)."""
    finished = {run.name: 0 for run in runs if run_done(out / run.name, episodes)}
    return finished, [run for run in runs if run.name not in finished]


def target_episodes(config: Path, episodes: int | None) -> int:
    """Episodes per run: ``episodes``, else the experiment config's."""
    if episodes is not None:
        return episodes
    from hdrqn_ros.config import build_config

    return build_config([config]).episodes


def default_jobs() -> int:
    """Runs at a time: one per core (each run uses one torch thread)."""
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
