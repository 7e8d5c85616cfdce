"""Offline training: a :class:`Learner` whose replay is filled once from recorded
episodes (e.g. read from bags) and then trained without an environment; greedy
evaluations in the environment measure the policy before, during and after."""
from __future__ import annotations

from typing import Iterable

from hdrqn_ros.training.episodes import FinishedEpisode
from hdrqn_ros.training.learner import Learner


class OfflineTrainer(Learner):
    """Trains ``cfg.algo`` from a fixed set of episodes into ``run_dir``."""

    EVAL_STEP = "updates"  # evaluations' x axis: there are no new episodes

    def fill(self, episodes: Iterable[FinishedEpisode]) -> int:
        """:meth:`~Learner.store` recorded episodes as this run's episodes and transitions
        (their steps count as env steps); returns how many."""
        n, steps = self.store(episodes)
        self.env_steps += steps
        return n

    def short_of_a_batch(self) -> list[str]:
        """The controllers whose replay holds fewer episodes than their ``batch_size`` (they
        cannot update offline), each as a sentence naming the counts."""
        section = {"meta": "meta", "sub": "sub" if self.agent.meta is not None else "flat"}
        return [f"the {ctrl.name} controller's replay holds {len(ctrl.replay)} episodes, fewer than its batch_size "
                f"{ctrl.cfg.batch_size}: it cannot update (record more episodes, or --set "
                f"{section[ctrl.name]}.batch_size={max(1, len(ctrl.replay))})"
                for ctrl in self.agent.controllers if not self._has_data(ctrl, offline=True)]

    def run(self, updates: int, evaluations: int = 5) -> dict:
        """``updates`` updates of each controller, with ``evaluations`` greedy evaluations
        spread over them (plus one before the first update); returns the summary written
        to ``summary.json``."""
        if self.episodes == 0:
            raise ValueError("no episodes to train on: the replay is empty")
        if updates < 1:
            raise ValueError(f"updates must be >= 1, got {updates}")
        if len(short := self.short_of_a_batch()) == len(self.agent.controllers):
            raise ValueError("no controller can update: " + "; ".join(short))
        self.begin()
        before = self.evaluate() if evaluations else None
        marks = {round(updates * (i + 1) / evaluations) for i in range(evaluations)} if evaluations else set()
        bar = self.progress_bar(updates, "upd", f"offline {self.cfg.algo}")
        final = before
        try:
            with self.saving_on_stop() as check_stop:
                for i in range(1, updates + 1):
                    self.update_once(offline=True)
                    if bar is not None:
                        bar.update(1)
                    if i in marks:
                        final = self.evaluate()
                        if bar is not None:
                            bar.set_postfix({"eval": f"{final['success']:.2f}"}, refresh=False)
                    check_stop()  # Ctrl-C / SIGTERM land here, between updates
        finally:
            if bar is not None:
                bar.close()
        self.save()
        summary = self.summary(final, offline=True, transitions=self.env_steps, before_eval=before)
        self.log.close()
        return summary
