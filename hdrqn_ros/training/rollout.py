"""Algorithm 1's acting part for N environments at once (lines 10-25 of thesis Algorithm 1).

A :class:`Rollout` owns the per-environment acting state (LSTM states, current subgoal
and its image, the meta input) and advances all environments by one primitive step in
:meth:`Rollout.step`. It reports what happened as a :class:`StepRecord`, which the
trainer turns into replay episodes (:mod:`hdrqn_ros.training.episodes`) and metrics.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from hdrqn_ros.agents.algorithms import Agent
from hdrqn_ros.agents.networks import lstm_state_size
from hdrqn_ros.critic import sub_controller_terminal
from hdrqn_ros.envs.domain import NO_SUBGOAL, StepBatch


def epsilon_greedy(q: np.ndarray, eps: float, rng: np.random.Generator,
                   invalid: np.ndarray | None = None) -> np.ndarray:
    """(B, n) Q-values -> (B,) int64 actions: random with probability ``eps``, else argmax.

    ``invalid`` (B,) int: one choice per row that may not be taken (-1: none).
    """
    b, n = q.shape
    explore = rng.random(b) < eps
    if invalid is None:
        return np.where(explore, rng.integers(0, n, size=b), q.argmax(axis=1))
    masked = np.where(np.arange(n) == invalid[:, None], -np.inf, q)
    has = invalid >= 0
    r = rng.integers(0, n - has.astype(np.int64), size=b)  # uniform over the valid choices
    r += has & (r >= invalid)
    return np.where(explore, r, masked.argmax(axis=1))


@dataclass
class StepRecord:
    """One primitive step of N environments. Arrays have N rows."""

    obs: np.ndarray  # (N, 44, 44, 3) observation the action was taken on
    new_option: np.ndarray  # (N,) bool: a subgoal was chosen before this step
    meta_input: np.ndarray | None  # (N, ...) meta input at the decision (rows of new_option)
    subgoal: np.ndarray  # (N,) int, -1 for flat agents
    subgoal_image: np.ndarray  # (N, 44, 44, 3)
    action: np.ndarray  # (N,) int
    env: StepBatch  # what the environments reported
    intrinsic: np.ndarray  # (N,) float32
    option_done: np.ndarray  # (N,) bool
    sub_terminal: np.ndarray  # (N,) bool: no bootstrap for the sub-controller (see critic.sub_controller_terminal)
    option_extrinsic: np.ndarray  # (N,) float32: extrinsic summed over the option (at option end)
    option_steps: np.ndarray  # (N,) int: option length (at option end)
    meta_next_input: np.ndarray | None  # (N, ...) meta input after the option (at option end)
    all_subgoal_images: np.ndarray | None = None  # (N, S*44, 44, 3) every subgoal's image at the
    # decision, stacked (rows of new_option); only from a rollout made with record_subgoal_images


class Rollout:
    """Steps a batch of environments with an agent's (epsilon-greedy) hierarchical policy."""

    def __init__(self, batch, agent: Agent, seed: int, meta_state: str = "c", record_subgoal_images: bool = False):
        """``record_subgoal_images``: fill :attr:`StepRecord.all_subgoal_images` (for recording)."""
        self.batch = batch
        self.record_subgoal_images = record_subgoal_images
        self._all_images = None
        self.agent = agent
        self.n = batch.num_envs
        self.critic = batch.critic()
        self.meta_state_index = 1 if meta_state == "c" else 0
        self.obs = batch.reset(seed=seed)
        self.need_meta = np.ones(self.n, bool)
        self.subgoal = np.full(self.n, -1, np.int64)
        self.subgoal_image = np.zeros_like(self.obs)
        self.sub_state = agent.sub.initial_state(self.n)
        meta = agent.meta
        self.meta_state = meta.initial_state(self.n) if meta is not None else None
        # hDRQNv2's meta input: the sub LSTM state at the end of the previous option
        self.last_sub_state = np.zeros((self.n, lstm_state_size), np.float32)
        self.option_extrinsic = np.zeros(self.n, np.float32)
        self.option_steps = np.zeros(self.n, np.int64)
        # the subgoal whose place each agent stands on: not a valid next subgoal (a subgoal
        # is reached "from the other subgoals", thesis 4.1.1)
        self.place = np.full(self.n, NO_SUBGOAL, np.int64)

    def _meta_input(self, rows: np.ndarray) -> np.ndarray:
        if self.agent.spec.meta_input == "state":
            return self.last_sub_state[rows].copy()
        return self.obs[rows].copy()

    @staticmethod
    def _zero_rows(state, rows: np.ndarray) -> None:
        if state is not None and rows.any():
            mask = torch.as_tensor(rows, device=state[0].device)
            for t in state:
                t[mask] = 0.0

    def _choose_subgoals(self, eps_meta: float, rng: np.random.Generator) -> np.ndarray | None:
        """Lines 13-15: new options where needed. Returns the meta inputs (N, ...) or None."""
        rows = self.need_meta
        if self.agent.meta is None:  # flat agents: one option per episode, no subgoal
            self.need_meta[:] = False
            return None
        if not rows.any():
            return None
        idx = np.flatnonzero(rows)
        x = self._meta_input(idx)
        meta = self.agent.meta
        state = None if self.meta_state is None else tuple(t[idx] for t in self.meta_state)
        q, new_state = meta.act(x, state)
        if new_state is not None:
            for t, new in zip(self.meta_state, new_state):
                t[torch.as_tensor(idx, device=t.device)] = new
        self.subgoal[idx] = epsilon_greedy(q, eps_meta, rng, invalid=self.place[idx])
        self.subgoal_image[idx] = self.batch.subgoal_images(self.subgoal)[idx]
        if self.record_subgoal_images:
            self._all_images = np.concatenate([self.batch.subgoal_images(np.full(self.n, g))
                                               for g in range(self.batch.num_subgoals)], axis=1)
        self._zero_rows(self.sub_state, rows)  # line 13: h^S <- 0 for every new option
        self.option_extrinsic[idx] = 0.0
        self.option_steps[idx] = 0
        full = np.zeros((self.n, *x.shape[1:]), x.dtype)
        full[idx] = x
        self.need_meta[:] = False
        return full

    def step(self, eps_sub: float, eps_meta: float, rng: np.random.Generator) -> StepRecord:
        """Advance every environment by one primitive action (lines 15-24)."""
        new_option = self.need_meta.copy()
        self._all_images = None
        meta_input = self._choose_subgoals(eps_meta, rng)
        obs = self.obs
        q, self.sub_state = self.agent.sub.act(self.agent.sub_input(obs, self.subgoal_image), self.sub_state)
        action = epsilon_greedy(q, eps_sub, rng)
        env = self.batch.step(action)
        if self.agent.meta is not None:
            crit = self.critic.evaluate(env, self.subgoal)
            intrinsic, option_done = crit.intrinsic, crit.option_done
            sub_terminal = sub_controller_terminal(crit.reached, env.terminated, env.life_lost, option_done)
        else:
            intrinsic = np.zeros(self.n, np.float32)
            option_done = env.done.copy()
            sub_terminal = env.terminated.copy()
        self.option_extrinsic += env.extrinsic
        self.option_steps += 1
        meta_next = None
        if self.sub_state is not None:
            self.last_sub_state[option_done] = self.sub_state[self.meta_state_index][
                torch.as_tensor(option_done, device=self.sub_state[0].device)].cpu().numpy()
        if self.agent.meta is not None and option_done.any():
            meta_next = self._meta_input_after(env)
        record = StepRecord(obs=obs, new_option=new_option, meta_input=meta_input, subgoal=self.subgoal.copy(),
                            subgoal_image=self.subgoal_image.copy(), action=action, env=env, intrinsic=intrinsic,
                            option_done=option_done, sub_terminal=sub_terminal,
                            option_extrinsic=self.option_extrinsic.copy(), option_steps=self.option_steps.copy(),
                            meta_next_input=meta_next, all_subgoal_images=self._all_images)
        self.need_meta |= option_done
        self.place = env.at_subgoal.astype(np.int64)
        done = env.done
        self.obs = env.obs
        if done.any():
            self.place[done] = NO_SUBGOAL
            env.obs = env.obs.copy()  # keep the final observations: reset_where may reuse buffers
            self.obs = self.batch.reset_where(done)
            self.last_sub_state[done] = 0.0
            self._zero_rows(self.meta_state, done)  # line 11: h^M <- 0 for a new episode
            self._zero_rows(self.sub_state, done)
        return record

    def _meta_input_after(self, env: StepBatch) -> np.ndarray:
        """(N, ...) the meta inputs after this step (read at the rows whose option ended)."""
        if self.agent.spec.meta_input == "state":
            return self.last_sub_state.copy()
        return env.obs.copy()
