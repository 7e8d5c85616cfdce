"""Algorithm 1 over N vectorised environments: batched acting, episodic replay, one update
of each controller every ``update_every`` env steps, greedy evaluations, checkpoints."""
from __future__ import annotations

import json
import sys
from contextlib import suppress
from pathlib import Path
from typing import Protocol

import numpy as np

from hdrqn_ros.agents.policy import StepRecord
from hdrqn_ros.config import TrainConfig
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.episodes import EpisodeBuilder, EpisodeStats
from hdrqn_ros.training.learner import EVAL_SEED_OFFSET, Learner, play
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.subgoals import option_table, option_table_markdown, read_options

PHASE1_TRAINING_SHARE = 0.2
"""The phase-1 report's training table covers this last share of phase 1's episodes."""


class StepSink(Protocol):
    """Where every :class:`StepRecord` goes as well (a recorder of transitions)."""

    def write(self, record: StepRecord) -> None: ...

    def close(self) -> None: ...


class Trainer(Learner):
    """Trains ``cfg.algo`` on ``cfg.env`` in this process: a :class:`Learner` fed by a
    :class:`Rollout` over ``cfg.num_envs`` vectorised environments. ``sink``: also hand
    every step to it (e.g. :class:`~hdrqn_ros.recording.transitions.TransitionRecorder`);
    it is closed when :meth:`run` ends."""

    def __init__(self, cfg: TrainConfig, run_dir: str | Path, resume: bool = False, progress: bool = True,
                 tensorboard: bool = True, sink: StepSink | None = None):
        super().__init__(cfg, run_dir, resume=resume, progress=progress, tensorboard=tensorboard)
        self.batch = make_batch(cfg.env, cfg.num_envs, **cfg.env_kwargs)
        self.sink = sink
        self.rollout = Rollout(self.batch, self.agent, seed=cfg.seed + self.episodes, meta_state=cfg.meta_state,
                               record_subgoal_images=sink is not None)
        self.builder = EpisodeBuilder(cfg.num_envs, self.agent.meta is not None)

    # -- main loop -------------------------------------------------------------------------
    def step(self) -> list[tuple[EpisodeStats, float, float]]:
        """One primitive step of every environment, then the updates it is owed (one per
        controller every ``update_every`` env steps). Returns the finished episodes'
        statistics with the epsilons they were played with."""
        cfg = self.cfg
        eps_sub, eps_meta = self.epsilons()
        record = self.rollout.step(eps_sub, eps_meta, self.rng)
        if self.sink is not None:
            try:
                self.sink.write(record)
            except Exception:  # e.g. the disk is full: keep what was trained, then stop
                sink, self.sink = self.sink, None
                with suppress(Exception):
                    sink.close()
                with suppress(Exception):
                    self.save()
                raise
        self.add_steps(cfg.num_envs)
        done = self.builder.add(record)[: max(0, cfg.episodes - self.episodes)]  # none beyond cfg.episodes
        self.store(done)
        self.run_owed_updates()
        return [(episode.stats, eps_sub, eps_meta) for episode in done]

    def run(self) -> dict:
        """Train until ``cfg.episodes``; returns the summary written to ``summary.json``."""
        cfg = self.cfg
        self.begin()
        bar = self.progress_bar(cfg.episodes, "ep", f"{cfg.algo} {cfg.env.split('/')[-1]}", initial=self.episodes)
        phase1_pending = (cfg.sub_only_episodes > 0 and self.agent.meta is not None
                          and not (self.run_dir / "phase1.json").exists())
        try:
            with self.saving_on_stop() as check_stop:
                while self.episodes < cfg.episodes:
                    for i, (stats, eps_sub, eps_meta) in enumerate(finished := self.step()):
                        self.log_episode(stats, eps_sub, eps_meta, episode=self.episodes - len(finished) + i + 1)
                    if self.due("eval"):
                        self.evaluate()
                    if self.due("checkpoint"):
                        self.save()
                    if phase1_pending and self.episodes >= cfg.sub_only_episodes:
                        self.phase1_report()
                        phase1_pending = False
                    if bar is not None and finished:
                        bar.update(len(finished))
                        rate = (self.env_steps - self.start_steps) / max(self.wall_s, 1e-9)
                        post = {"steps/s": f"{rate:.0f}", "succ": f"{np.mean([r.success for r in self.recent]):.2f}",
                                "eps": f"{finished[-1][1]:.2f}/{finished[-1][2]:.2f}"}
                        if self.last_eval:
                            post["eval"] = f"{self.last_eval['success']:.2f}"
                        bar.set_postfix(post, refresh=False)
                    check_stop()  # Ctrl-C / SIGTERM land here, between steps
        finally:
            if bar is not None:
                bar.close()
            if self.sink is not None:
                self.sink.close()
        self.save()
        final = None
        if cfg.eval_every:
            done_now = self.last_eval is not None and self.last_eval.get("at") == self.episodes
            final = self.last_eval if done_now else self.evaluate()
        summary = self.summary(final)
        self.log.close()
        return summary

    def phase1_report(self) -> dict:
        """End of phase 1 (thesis section 4.5): how well the sub-controller moves between
        subgoals, as option tables (:func:`option_table`) of ``cfg.eval_episodes`` held-out
        episodes with the greedy sub-controller and subgoals at random, and of the last
        ``PHASE1_TRAINING_SHARE`` of phase 1's training episodes. Writes ``phase1.json`` and
        ``phase1.md``; returns the JSON's content."""
        cfg = self.cfg
        greedy = play(self.agent, cfg, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET, epsilon=0.0, meta_epsilon=1.0)
        first = int(cfg.sub_only_episodes * (1 - PHASE1_TRAINING_SHARE)) + 1
        training = read_options(self.run_dir / "options.csv", first, cfg.sub_only_episodes)
        tables = {"greedy": option_table([o for s in greedy for o in s.option_log], self.subgoal_names,
                                         self.subgoal_neighbours),
                  "training": option_table(training, self.subgoal_names, self.subgoal_neighbours)}
        report = {"phase1_episodes": cfg.sub_only_episodes, "env_steps": self.env_steps,
                  "greedy_episodes": len(greedy), "training_episodes": [first, cfg.sub_only_episodes], **tables}
        (self.run_dir / "phase1.json").write_text(json.dumps(report, indent=2))
        text = (f"# Phase 1 of {cfg.algo} on {cfg.env}: the sub-controller after {cfg.sub_only_episodes} episodes "
                f"({self.env_steps} env steps)\n\nGreedy sub-controller, subgoals at random, {len(greedy)} held-out "
                f"episodes:\n\n{option_table_markdown(tables['greedy'])}\n\nTraining (epsilon-greedy), episodes "
                f"{first}-{cfg.sub_only_episodes}:\n\n{option_table_markdown(tables['training'])}\n")
        (self.run_dir / "phase1.md").write_text(text)
        print(text, file=sys.stderr)
        return report


__all__ = ["Trainer", "StepSink", "PHASE1_TRAINING_SHARE"]
