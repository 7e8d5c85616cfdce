"""Algorithm 1's learning part, shared by the in-process trainer and the learner node:
the agent and its replay, epsilon schedules, one update of each controller every
``update_every`` env steps, greedy evaluations, checkpoints and metrics (the updates'
losses among them)."""
from __future__ import annotations

import json
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
import yaml

from hdrqn_ros.agents.algorithms import Agent
from hdrqn_ros.agents.controller import Controller, UpdateStats
from hdrqn_ros.config import TrainConfig
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from hdrqn_ros.training.episodes import EpisodeBuilder, EpisodeStats, FinishedEpisode
from hdrqn_ros.training.interrupts import stop_between_steps
from hdrqn_ros.training.metrics import TRAIN_LOSS_STATS, MetricsLog
from hdrqn_ros.training.replay_snapshot import load_replay_snapshot, remove_other_snapshots, save_replay_snapshot
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.update_means import UpdateMeans

EVAL_SEED_OFFSET = 1_000_003
"""Evaluation environments use ``seed + EVAL_SEED_OFFSET``: the same held-out episodes
at every evaluation, never the training ones."""

MAX_EVAL_ENVS = 256
"""Default cap on the environments an evaluation plays in parallel."""


def build_agent(cfg: TrainConfig, probe=None) -> Agent:
    """The agent for ``cfg`` with the action/subgoal counts of its domain (read from
    ``probe``, a batch of ``cfg.env``, when the caller has one)."""
    probe = probe if probe is not None else make_batch(cfg.env, 1, **cfg.env_kwargs)
    return Agent(cfg, probe.num_actions, probe.num_subgoals)


def load_trained_agent(path: str | Path, device: str = "cpu") -> tuple[TrainConfig, Agent]:
    """The training config and the agent of checkpoint ``path``, on ``device``; raises
    :class:`CheckpointError` for a checkpoint that is unreadable or does not fit its config."""
    payload = load_checkpoint(path)
    try:
        cfg = TrainConfig.model_validate({**payload["config"], "device": device})
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path} holds no valid training config: {str(exc).splitlines()[0]}") from None
    agent = build_agent(cfg)
    try:
        agent.load_state_dict(payload["agent"])
    except (KeyError, RuntimeError) as exc:
        raise CheckpointError(f"{path} does not fit its {cfg.algo} agent: {str(exc).splitlines()[0]}") from None
    return cfg, agent


def eval_envs(episodes: int, num_envs: int | None = None) -> int:
    """How many environments :func:`play` steps for ``episodes`` episodes: ``num_envs``, which
    must divide ``episodes`` (every environment plays as many; a ValueError says what would),
    or by default the most that do, at most ``MAX_EVAL_ENVS``."""
    if num_envs is None:
        return max(n for n in range(1, min(episodes, MAX_EVAL_ENVS) + 1) if episodes % n == 0)
    if episodes % num_envs:
        fits = [n for n in range(1, min(episodes, MAX_EVAL_ENVS) + 1) if episodes % n == 0][-3:]
        raise ValueError(f"{episodes} episodes do not split evenly over {num_envs} environments (each plays as "
                         f"many): ask for {-(-episodes // num_envs) * num_envs} episodes, or "
                         f"{' / '.join(map(str, fits))} environments")
    return num_envs


def play(agent: Agent, cfg: TrainConfig, episodes: int, seed: int, epsilon: float = 0.0,
         meta_epsilon: float | None = None, sink=None, num_envs: int | None = None) -> list[EpisodeStats]:
    """Play exactly ``episodes`` episodes on :func:`eval_envs` parallel environments of a
    fresh batch, each playing the same number.
    ``epsilon``: the sub-controller's (and a flat agent's) exploration; ``meta_epsilon``:
    the meta-controller's (default ``epsilon``; 1 picks subgoals at random, as phase 1).
    ``sink``: also hand it every step (``write(StepRecord)``), e.g. to record them.
    Returns each episode's statistics (env 0's episodes first)."""
    n = eval_envs(episodes, num_envs)
    quota = episodes // n
    batch = make_batch(cfg.env, n, **cfg.env_kwargs)
    rollout = Rollout(batch, agent, seed=seed, meta_state=cfg.meta_state, record_subgoal_images=sink is not None)
    builder = EpisodeBuilder(n, agent.meta is not None)
    results: dict[tuple[int, int], EpisodeStats] = {}
    played = np.zeros(n, np.int64)
    rng = np.random.default_rng(seed)
    eps_meta = epsilon if meta_epsilon is None else meta_epsilon
    while len(results) < n * quota:
        record = rollout.step(epsilon, eps_meta, rng)
        if sink is not None:
            sink.write(record)
        for episode in builder.add(record):
            i = episode.group
            if played[i] < quota:
                results[(i, int(played[i]))] = episode.stats
            played[i] += 1
    return [results[k] for k in sorted(results)]


def evaluate(agent: Agent, cfg: TrainConfig, episodes: int, seed: int, epsilon: float = 0.0, sink=None,
             num_envs: int | None = None) -> dict:
    """Greedy (``epsilon`` 0) episodes (see :func:`play`), summarised by :func:`summarise`."""
    return summarise(play(agent, cfg, episodes, seed, epsilon, sink=sink, num_envs=num_envs))


def summarise(rows: list[EpisodeStats]) -> dict:
    """The means of success (ordered success / key), steps and rewards over episodes."""
    return {"episodes": len(rows), "success": float(np.mean([r.success for r in rows])),
            "steps": float(np.mean([r.steps for r in rows])), "reward": float(np.mean([r.classical for r in rows])),
            "extrinsic": float(np.mean([r.extrinsic for r in rows])),
            "intrinsic": float(np.mean([r.intrinsic for r in rows]))}


class Learner:
    """Learns ``cfg.algo`` from finished episodes into ``run_dir`` (checkpoints, CSV, TensorBoard).

    The surface a training loop uses (the in-process :class:`~hdrqn_ros.training.trainer.Trainer`,
    the :class:`~hdrqn_ros.training.offline.OfflineTrainer`, the learner node): :meth:`store`
    episodes in replay, count env steps (:meth:`add_steps`) and run the updates they are owed
    (:meth:`run_owed_updates`, or :meth:`update_once`), :meth:`log_episode`; :meth:`begin`
    the loop, ask whether an evaluation or a checkpoint is :meth:`due`, :meth:`evaluate`,
    :meth:`save`, and end with :meth:`summary`.
    """

    EVAL_STEP = "episode"
    """TensorBoard's x axis for evaluations."""

    def __init__(self, cfg: TrainConfig, run_dir: str | Path, resume: bool = False, progress: bool = True,
                 tensorboard: bool = True, warn: Callable[[str], None] | None = None):
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.checkpoint_path = self.run_dir / "checkpoints" / "last.pt"
        self.progress = progress
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        probe = make_batch(cfg.env, 1, **cfg.env_kwargs)
        self.agent = build_agent(cfg, probe)
        self.subgoal_names, self.subgoal_neighbours = probe.subgoal_names, probe.subgoal_neighbours
        self.return_bound: float | None = getattr(probe, "return_bound", None)
        self.bound_exceeded: dict | None = None  # the first losses.csv row whose meta mean Q passed return_bound
        self.warn = warn or (lambda text: print(f"warning: {text}", file=sys.stderr, flush=True))
        self.episodes = 0
        self.env_steps = 0
        self.meta_begin: int | None = None  # env step at which the meta-controller starts learning
        self.replay_restored = False  # whether --resume refilled the replay from its snapshot
        self.changed_settings: list[str] = []  # what --resume runs with that the checkpoint did not
        if resume:
            self._resume()
        elif self.checkpoint_path.exists():
            raise CheckpointError(f"{self.run_dir} already holds a run; pass --resume to continue it "
                                  f"or choose another --out")
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "config.yaml").write_text(yaml.safe_dump(cfg.model_dump(), sort_keys=False))
        self.log = MetricsLog(self.run_dir, tensorboard=tensorboard, subgoal_names=self.subgoal_names,
                              options=self.agent.meta is not None, controllers=tuple(self.replays()))
        self.update_means = UpdateMeans(cfg.log_every_updates)
        self.latest_losses: dict[str, float] = {}  # train.csv's <controller>_<stat>: losses.csv's latest
        self.last_eval: dict | None = None
        self.recent: deque[EpisodeStats] = deque(maxlen=100)  # the last training episodes
        self._pending_updates = 0
        self.begin()
        self._meta_thread = ThreadPoolExecutor(1, thread_name_prefix="meta-update") if cfg.parallel_updates else None

    # -- schedules -----------------------------------------------------------------------
    def epsilons(self) -> tuple[float, float]:
        cfg = self.cfg
        if self.env_steps < cfg.learning_starts:
            return 1.0, 1.0
        eps_sub = cfg.controller("sub").epsilon.value(self.env_steps - cfg.learning_starts)
        if self.episodes < cfg.sub_only_episodes:  # phase 1: subgoals at random
            return eps_sub, 1.0
        if self.meta_begin is None:
            self.meta_begin = self.env_steps
        return eps_sub, cfg.meta.epsilon.value(self.env_steps - self.meta_begin)

    # -- checkpoints ---------------------------------------------------------------------
    def _resume(self) -> None:
        payload = load_checkpoint(self.checkpoint_path, map_location=self.cfg.device)
        saved = payload["config"]
        for key in ("algo", "env"):
            if saved.get(key) != getattr(self.cfg, key):
                raise CheckpointError(f"{self.checkpoint_path} was trained with {key}={saved.get(key)!r}, "
                                      f"not {getattr(self.cfg, key)!r}")
        try:
            self.agent.load_state_dict(payload["agent"])
        except (KeyError, RuntimeError) as exc:
            raise CheckpointError(f"{self.checkpoint_path} does not fit this agent: {str(exc).splitlines()[0]}") from None
        self.changed_settings = self.cfg.changes_since(saved)
        prog = payload["progress"]
        self.episodes, self.env_steps = int(prog["episodes"]), int(prog["env_steps"])
        self.meta_begin = prog.get("meta_begin")
        snapshot = prog.get("replay")
        self.replay_restored = bool(snapshot) and self.cfg.save_replay
        if self.replay_restored:
            load_replay_snapshot(self.checkpoint_path.parent / snapshot["file"], self.replays(), snapshot,
                                 self._run_id(), written_with=saved)

    def resumed_line(self) -> str:
        """One line on what ``--resume`` restored: where the run continues, and its replay."""
        held = ", ".join(f"{role} {len(replay)} episodes" for role, replay in self.replays().items())
        replay = f"replay restored ({held})" if self.replay_restored else \
            "no replay snapshot: the replay refills before updates resume"
        changed = (f"; settings changed since the run started: {', '.join(self.changed_settings)}"
                   if self.changed_settings else "")
        return f"resumed {self.checkpoint_path} at episode {self.episodes} ({self.env_steps} env steps); {replay}{changed}"

    def replays(self) -> dict:
        """The agent's replays by role: ``sub`` (a flat agent's one controller) and ``meta``."""
        out = {"sub": self.agent.sub.replay}
        if self.agent.meta is not None:
            out["meta"] = self.agent.meta.replay
        return out

    def _run_id(self) -> dict:
        return {"algo": self.cfg.algo, "env": self.cfg.env, "env_kwargs": self.cfg.env_kwargs}

    def save(self) -> None:
        """Write the checkpoint and, with ``save_replay``, first the replay snapshot it names
        (:mod:`~hdrqn_ros.training.replay_snapshot`); older snapshots go once it is written."""
        progress = {"episodes": self.episodes, "env_steps": self.env_steps, "meta_begin": self.meta_begin}
        directory = self.checkpoint_path.parent
        if self.cfg.save_replay:
            progress["replay"] = save_replay_snapshot(directory, self.replays(), self._run_id())
        try:
            save_checkpoint(self.checkpoint_path, config=self.cfg.model_dump(), agent_state=self.agent.state_dict(),
                            progress=progress)
        except BaseException:
            if "replay" in progress:  # the snapshot no checkpoint names
                (directory / progress["replay"]["file"]).unlink(missing_ok=True)
            raise
        remove_other_snapshots(directory, progress.get("replay", {}).get("file"))

    @contextmanager
    def saving_on_stop(self) -> Iterator[Callable[[], None]]:
        """A training loop's stop: Ctrl-C / SIGTERM take effect at the yielded ``check()``
        (the loop calls it between steps, :func:`stop_between_steps`), and the
        ``KeyboardInterrupt`` leaves with a checkpoint saved (``--resume`` continues)."""
        try:
            with stop_between_steps() as check:
                yield check
        except KeyboardInterrupt:
            self.save()
            raise

    # -- replay ------------------------------------------------------------------------------
    def store(self, items: Iterable[FinishedEpisode], counted: bool = True) -> tuple[int, int]:
        """The one way into replay: store finished episodes (the oldest are dropped beyond
        the replay capacity).
        ``counted``: they are this run's episodes (``episodes`` grows; env steps are counted
        by :meth:`add_steps` as they are played); otherwise, e.g. episodes recorded earlier,
        they only fill the replay. Returns (episodes, steps) stored."""
        episodes = steps = 0
        sub, meta = self.agent.sub.replay, self.agent.meta.replay if self.agent.meta is not None else None
        for episode in items:
            sub.add(episode.sub)
            if episode.meta is not None:
                meta.add(episode.meta)
            episodes, steps = episodes + 1, steps + episode.stats.steps
        if counted:
            self.episodes += episodes
        return episodes, steps

    def log_episode(self, stats: EpisodeStats, eps_sub: float, eps_meta: float, episode: int | None = None) -> None:
        """One row of ``train.csv`` / TensorBoard (and of ``visits.csv``, ``options.csv``) for
        a finished episode, with the latest TD loss and Q of each controller (empty before its
        first ``losses.csv`` row); it also joins the last 100 (``train_success_last100``)."""
        episode = self.episodes if episode is None else episode
        self.recent.append(stats)
        self.log.subgoals(episode, stats.visits, stats.option_log)
        self.log.train({"episode": episode, "env_steps": self.env_steps,
                        "steps": stats.steps, "reward": stats.classical, "extrinsic": stats.extrinsic,
                        "intrinsic": stats.intrinsic, "success": int(stats.success), "options": stats.options,
                        "eps_sub": round(eps_sub, 4), "eps_meta": round(eps_meta, 4), "wall_s": round(self.wall_s, 2),
                        **self.latest_losses})

    # -- updates ---------------------------------------------------------------------------
    def add_steps(self, n: int) -> None:
        """Count ``n`` env steps; every ``update_every`` of them is owed one update."""
        self.env_steps += n
        self._pending_updates += n

    @property
    def owed_updates(self) -> int:
        return self._pending_updates // self.cfg.update_every

    def run_owed_updates(self, limit: int | None = None) -> int:
        """Run the updates owed (at most ``limit``) with :meth:`update_once`; returns how many ran."""
        count = self.owed_updates if limit is None else min(limit, self.owed_updates)
        for _ in range(count):
            self._pending_updates -= self.cfg.update_every
            self.update_once()
        return count

    def update_once(self, offline: bool = False) -> None:
        """One update (:meth:`~hdrqn_ros.agents.controller.Controller.update`) of each
        controller whose turn it is:

        * a controller learns once its replay holds ``batch_size`` episodes and, online,
          after the ``learning_starts`` env steps of random play (``offline``: from replay
          filled beforehand, at once);
        * the meta-controller only in phase 2, after ``sub_only_episodes`` episodes (in
          phase 1 it picks subgoals at random and does not learn).

        The meta update runs in a second thread beside the sub update (torch releases the
        GIL in its kernels) when ``parallel_updates``. Each update's statistics go to
        ``losses.csv`` (:meth:`_record`)."""
        meta, sub = self.agent.meta, self.agent.sub
        phase2 = self.episodes >= self.cfg.sub_only_episodes
        meta_due = meta is not None and phase2 and self._has_data(meta, offline)
        pending = self._meta_thread.submit(meta.update) if meta_due and self._meta_thread else None
        if self._has_data(sub, offline):
            self._record(sub, sub.update())
        if pending is not None:
            self._record(meta, pending.result())
        elif meta_due:
            self._record(meta, meta.update())

    def _record(self, ctrl: Controller, stats: UpdateStats) -> None:
        """Add one update of ``ctrl``; every ``log_every_updates`` of its updates, a row of
        their means to ``losses.csv`` / TensorBoard, and the latest into ``train.csv``."""
        means = self.update_means.add(ctrl.name, stats)
        if means is None:
            return
        means = {stat: float(f"{value:.6g}") for stat, value in means.items()}
        self.log.losses({"episode": self.episodes, "env_steps": self.env_steps, "updates": ctrl.updates,
                         "controller": ctrl.name, **means})
        self.latest_losses.update({f"{ctrl.name}_{stat}": means[stat] for stat in TRAIN_LOSS_STATS})
        if ctrl.name == "meta":
            self._check_value_bound(means["q_taken"])

    def _check_value_bound(self, mean_q: float) -> None:
        """Warn once when the meta-controller's mean Q(s_t, a_t) over a ``losses.csv`` row
        exceeds the largest return an episode can give (the domain's ``return_bound``): its
        values have diverged; ``summary.json`` keeps where."""
        if self.return_bound is None or self.bound_exceeded is not None or not mean_q > self.return_bound:
            return
        self.bound_exceeded = {"episode": self.episodes, "updates": self.agent.meta.updates, "mean_q": mean_q,
                               "return_bound": self.return_bound}
        self.warn(f"the meta-controller's mean Q is {mean_q:.4g} at episode {self.episodes} "
                  f"(update {self.agent.meta.updates}), above {self.return_bound:g}, the largest return an episode "
                  f"of {self.cfg.env} can give: its values are diverging (losses.csv: q_taken, q_opt*; "
                  f"docs/training.md, 'Value bound')")

    def _has_data(self, ctrl, offline: bool) -> bool:
        return len(ctrl.replay) >= ctrl.cfg.batch_size and (offline or self.env_steps >= self.cfg.learning_starts)

    # -- the loop's schedule, evaluations, summary -----------------------------------------
    def begin(self) -> None:
        """A training loop starts: its clock and env-step count (for ``wall_s`` and rates),
        and the next evaluation and checkpoint (:meth:`due`) after the episodes so far."""
        self.started = time.perf_counter()
        self.start_steps = self.env_steps
        self._next_due = {what: self._next_multiple(self._every(what)) for what in ("eval", "checkpoint")}

    def due(self, what: str) -> bool:
        """Whether the ``eval`` (every ``eval_every`` episodes, 0: never) or ``checkpoint``
        (every ``checkpoint_every``) is due now; once it is, the next one is scheduled."""
        mark = self._next_due[what]
        if not mark or self.episodes < mark:
            return False
        self._next_due[what] = self._next_multiple(self._every(what))
        return True

    def _every(self, what: str) -> int:
        return {"eval": self.cfg.eval_every, "checkpoint": self.cfg.checkpoint_every}[what]

    def _next_multiple(self, every: int) -> int:
        return (self.episodes // every + 1) * every if every else 0

    @property
    def wall_s(self) -> float:
        """Seconds since :meth:`begin`."""
        return time.perf_counter() - self.started

    def evaluate(self, log: bool = True) -> dict:
        """Greedy evaluation on the held-out episodes (``cfg.eval_episodes``, seed
        ``seed + EVAL_SEED_OFFSET``); kept as ``last_eval`` and, with ``log``, written to
        ``eval.csv`` / TensorBoard (x axis :attr:`EVAL_STEP`). Returns the summary."""
        result = evaluate(self.agent, self.cfg, self.cfg.eval_episodes, self.cfg.seed + EVAL_SEED_OFFSET)
        self.last_eval = {**result, "at": self.episodes}
        if log:
            self.log.eval({"episode": self.episodes, "env_steps": self.env_steps, **result,
                           "wall_s": round(self.wall_s, 2), "updates": self.agent.sub.updates}, step_key=self.EVAL_STEP)
        return result

    def summary(self, final_eval: dict | None, wall_s: float | None = None, **extra) -> dict:
        """The run's summary, written to ``summary.json``: algo, env, episodes, env steps
        (and their rate over ``wall_s``, default the time since :meth:`begin`), updates, the
        success of the last 100 training episodes, then ``extra``, then ``final_eval``."""
        wall = self.wall_s if wall_s is None else wall_s
        summary = {"algo": self.cfg.algo, "env": self.cfg.env, "episodes": self.episodes,
                   "env_steps": self.env_steps, "wall_s": round(wall, 1),
                   "env_steps_per_s": round((self.env_steps - self.start_steps) / max(wall, 1e-9), 1),
                   "updates": self.agent.sub.updates,
                   "train_success_last100": float(np.mean([r.success for r in self.recent])) if self.recent else None,
                   "meta_q_above_bound": self.bound_exceeded, **extra, "final_eval": final_eval}
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        return summary

    def progress_bar(self, total: int, unit: str, desc: str, initial: int = 0):
        """A tqdm bar when ``progress``, else None."""
        if not self.progress:
            return None
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, unit=unit, dynamic_ncols=True, desc=desc)


__all__ = ["Learner", "evaluate", "eval_envs", "play", "summarise", "build_agent", "load_trained_agent", "EVAL_SEED_OFFSET"]
