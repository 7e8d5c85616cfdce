"""Offline training: a :class:`Learner` whose replay is filled once from recorded
episodes (e.g. read from bags) and then trained without an environment; greedy
evaluations in the environment measure the policy before, during and after."""
from __future__ import annotations

import json
import time
from typing import Iterable

from hdrqn_ros.training.learner import EVAL_SEED_OFFSET, Learner, evaluate


class OfflineTrainer(Learner):
    """Trains ``cfg.algo`` from a fixed set of episodes into ``run_dir``."""

    def fill(self, episodes: Iterable[tuple]) -> int:
        """Store ``(group, sub Episode, meta Episode or None, EpisodeStats)`` items in
        replay (the oldest are dropped beyond the replay capacity); returns how many."""
        n, steps = self.prefill(episodes)
        self.episodes, self.env_steps = self.episodes + n, self.env_steps + steps
        return n

    def _eval_row(self, start: float) -> dict:
        result = evaluate(self.agent, self.cfg, self.cfg.eval_episodes, self.cfg.seed + EVAL_SEED_OFFSET)
        self.log.eval({"episode": self.episodes, "env_steps": self.env_steps, **result,
                       "wall_s": round(time.perf_counter() - start, 2), "updates": self.agent.sub.updates},
                      step_key="updates")
        return result

    def run(self, updates: int, evaluations: int = 5) -> dict:
        """``updates`` updates of each controller, with ``evaluations`` greedy evaluations
        spread over them (plus one before the first update); returns the summary written
        to ``summary.json``."""
        if self.episodes == 0:
            raise ValueError("no episodes to train on: the replay is empty")
        if updates < 1:
            raise ValueError(f"updates must be >= 1, got {updates}")
        start = time.perf_counter()
        before = self._eval_row(start) if evaluations else None
        marks = {round(updates * (i + 1) / evaluations) for i in range(evaluations)} if evaluations else set()
        bar = None
        if self.progress:
            from tqdm import tqdm

            bar = tqdm(total=updates, unit="upd", dynamic_ncols=True, desc=f"offline {self.cfg.algo}")
        final = before
        try:
            with self.saving_on_stop() as check_stop:
                for i in range(1, updates + 1):
                    self._update(offline=True)
                    if bar is not None:
                        bar.update(1)
                    if i in marks:
                        final = self._eval_row(start)
                        if bar is not None:
                            bar.set_postfix({"eval": f"{final['success']:.2f}"}, refresh=False)
                    check_stop()  # Ctrl-C / SIGTERM land here, between updates
        finally:
            if bar is not None:
                bar.close()
        self.save()
        summary = {"algo": self.cfg.algo, "env": self.cfg.env, "offline": True, "episodes": self.episodes,
                   "transitions": self.env_steps, "updates": self.agent.sub.updates,
                   "wall_s": round(time.perf_counter() - start, 1), "before_eval": before, "final_eval": final}
        (self.run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        self.log.close()
        return summary
