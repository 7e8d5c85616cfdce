"""Algorithm 1's acting part for N environments at once (lines 10-25 of thesis Algorithm 1).

A :class:`Rollout` steps the environments with the agent's
:class:`~hdrqn_ros.agents.policy.HierarchicalPolicy` (which owns the acting state: LSTM
states, subgoals, meta inputs) and keeps what the environments add (observations, subgoal
images, the critic, option returns). :meth:`Rollout.step` advances all environments by one
primitive step and reports it as a :class:`~hdrqn_ros.agents.policy.StepRecord`, which the
trainer turns into replay episodes (:mod:`hdrqn_ros.training.episodes`) and metrics.
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.agents.algorithms import Agent
from hdrqn_ros.agents.policy import HierarchicalPolicy, StepRecord
from hdrqn_ros.envs.critic import sub_controller_terminal


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
        self.policy = HierarchicalPolicy(self.n, agent.sub, agent.meta, agent.spec.meta_input, meta_state)
        self.obs = batch.reset(seed=seed)
        self.need_meta = np.ones(self.n, bool)
        self.subgoal_image = np.zeros_like(self.obs)
        self.option_extrinsic = np.zeros(self.n, np.float32)
        self.option_steps = np.zeros(self.n, np.int64)

    @property
    def subgoal(self) -> np.ndarray:
        """(N,) int64: each environment's current subgoal (-1 for flat agents)."""
        return self.policy.subgoal

    def _choose_subgoals(self, eps_meta: float, rng: np.random.Generator) -> np.ndarray | None:
        """Lines 13-15: new options where needed. Returns the meta inputs (N, ...) or None."""
        rows = self.need_meta
        if self.agent.meta is None:  # flat agents: one option per episode, no subgoal
            self.need_meta[:] = False
            return None
        if not rows.any():
            return None
        _, x = self.policy.choose_subgoals(rows, self.obs, eps_meta, rng)
        self.subgoal_image[rows] = self.batch.subgoal_images(self.subgoal)[rows]
        if self.record_subgoal_images:
            self._all_images = np.concatenate([self.batch.subgoal_images(np.full(self.n, g))
                                               for g in range(self.batch.num_subgoals)], axis=1)
        self.option_extrinsic[rows] = 0.0
        self.option_steps[rows] = 0
        full = np.zeros((self.n, *x.shape[1:]), x.dtype)
        full[rows] = x
        self.need_meta[:] = False
        return full

    def step(self, eps_sub: float, eps_meta: float, rng: np.random.Generator) -> StepRecord:
        """Advance every environment by one primitive action (lines 15-24)."""
        new_option = self.need_meta.copy()
        self._all_images = None
        meta_input = self._choose_subgoals(eps_meta, rng)
        obs = self.obs
        action = self.policy.act(self.agent.sub_input(obs, self.subgoal_image), eps_sub, rng)
        env = self.batch.step(action)
        if self.agent.meta is not None:
            judged = self.critic.evaluate(env, self.subgoal)
            intrinsic, option_done = judged.intrinsic, judged.option_done
            sub_terminal = sub_controller_terminal(judged.reached, env.terminated, env.life_lost, option_done)
        else:
            intrinsic = np.zeros(self.n, np.float32)
            option_done = env.done.copy()
            sub_terminal = env.terminated.copy()
        self.option_extrinsic += env.extrinsic
        self.option_steps += 1
        self.policy.end_options(option_done, env.at_subgoal)
        meta_next = None
        if self.agent.meta is not None and option_done.any():
            meta_next = self.policy.meta_input_after(env.obs)
        record = StepRecord(obs=obs, new_option=new_option, meta_input=meta_input, subgoal=self.subgoal.copy(),
                            subgoal_image=self.subgoal_image.copy(), action=action, env=env, intrinsic=intrinsic,
                            option_done=option_done, sub_terminal=sub_terminal,
                            option_extrinsic=self.option_extrinsic.copy(), option_steps=self.option_steps.copy(),
                            meta_next_input=meta_next, all_subgoal_images=self._all_images)
        self.need_meta |= option_done
        done = env.done
        self.obs = env.obs
        if done.any():
            env.obs = env.obs.copy()  # keep the final observations: reset_where may reuse buffers
            self.obs = self.batch.reset_where(done)
            self.policy.start_episodes(done)  # line 11: h^M, h^S <- 0 for a new episode
        return record
