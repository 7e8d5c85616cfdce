"""Turn the per-step records of N environments into whole replay episodes and statistics.

Sub-controller episode: frames o_0..o_T (T+1 observations, each stored once); fields
``action, reward (intrinsic, or classical for flat agents), terminal``; one
segment per option with its subgoal image (windows never cross an option boundary).
``terminal`` is the record's ``sub_terminal`` (:func:`~hdrqn_ros.envs.critic.sub_controller_terminal`,
applied alike by the in-process rollout and the graph's assembler).
Meta-controller episode: one step per option; frames are the meta inputs at each decision
plus the input after the last option; each step's reward, ``option_steps`` (the option's
length in primitive steps), terminal and ``next_invalid`` are
:func:`~hdrqn_ros.agents.controller.meta_transition` (defined beside the update that reads
them, :meth:`~hdrqn_ros.agents.controller.Controller.update`). No discount is stored: the
update applies its controller's configured gamma (and ``smdp_discount``).
Statistics also count the steps spent at each subgoal's place and log every option as
:class:`OptionOutcome` (thesis figure 4.13b and the phase-1 table of section 4.5).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from hdrqn_ros.agents.controller import meta_transition
from hdrqn_ros.agents.policy import StepRecord
from hdrqn_ros.agents.replay import Episode


@dataclass(frozen=True)
class OptionOutcome:
    """One finished option: where it started, what it aimed at, how it ended."""

    start: int  # subgoal whose place the agent stood on when the option began, or NO_SUBGOAL (-1)
    subgoal: int  # the option's subgoal
    steps: int  # primitive steps the option lasted
    reached: bool  # the agent was at the subgoal's place when the option ended


@dataclass
class EpisodeStats:
    """Totals of one finished episode."""

    steps: int
    classical: float
    extrinsic: float
    intrinsic: float
    success: bool
    options: int
    visits: Counter = field(default_factory=Counter)  # subgoal -> steps ending at its place
    option_log: list[OptionOutcome] = field(default_factory=list)  # hierarchical agents only


META_FIELDS = (("action", np.uint8), ("reward", np.float32), ("option_steps", np.int32), ("terminal", bool),
               ("next_invalid", np.int8))
"""The meta-controller's replay fields, in the order of ``_Open.meta_steps``' tuples."""


@dataclass
class _Open:
    """One environment's episode in progress."""

    obs: list = field(default_factory=list)
    action: list = field(default_factory=list)
    reward: list = field(default_factory=list)
    terminal: list = field(default_factory=list)
    segment_starts: list = field(default_factory=list)
    segment_images: list = field(default_factory=list)
    meta_frames: list = field(default_factory=list)
    meta_steps: list = field(default_factory=list)  # per finished option: a row of META_FIELDS
    classical: float = 0.0
    extrinsic: float = 0.0
    intrinsic: float = 0.0
    visits: Counter = field(default_factory=Counter)
    option_log: list = field(default_factory=list)
    place: int = -1  # the subgoal place the agent stands on (after the last step), or -1
    option_start: int = -1  # ``place`` when the current option began


class FinishedEpisode(NamedTuple):
    """One finished episode of one environment, ready for replay and the metrics."""

    group: int | str  # the environment's index in the batch (in-process), or its group's namespace (graph, bags)
    sub: Episode  # the sub-controller's (the flat agent's) episode
    meta: Episode | None  # the meta-controller's episode of options (None for flat agents)
    stats: EpisodeStats


class EpisodeBuilder:
    """Builds replay episodes from :class:`StepRecord` rows, per environment; :meth:`add`
    returns the episodes that finished at that step."""

    def __init__(self, num_envs: int, hierarchical: bool):
        self.hierarchical = hierarchical
        self.open = [_Open() for _ in range(num_envs)]

    def add(self, step: StepRecord) -> list[FinishedEpisode]:
        finished = []
        env = step.env
        reward = step.intrinsic if self.hierarchical else env.classical
        for i, ep in enumerate(self.open):
            if step.new_option[i] or not ep.obs:
                ep.segment_starts.append(len(ep.obs))
                if self.hierarchical:
                    ep.segment_images.append(step.subgoal_image[i].copy())
                    ep.meta_frames.append(step.meta_input[i].copy())
                    ep.option_start = ep.place
            ep.obs.append(step.obs[i].copy())
            ep.action.append(step.action[i])
            ep.reward.append(reward[i])
            ep.terminal.append(step.sub_terminal[i])
            ep.classical += float(env.classical[i])
            ep.extrinsic += float(env.extrinsic[i])
            ep.intrinsic += float(step.intrinsic[i])
            ep.place = int(env.at_subgoal[i])
            if ep.place >= 0:
                ep.visits[ep.place] += 1
            if self.hierarchical and step.option_done[i]:
                option_steps = int(step.option_steps[i])
                ep.option_log.append(OptionOutcome(ep.option_start, int(step.subgoal[i]), option_steps,
                                                   ep.place == int(step.subgoal[i])))
                ep.meta_steps.append((step.subgoal[i], *meta_transition(
                    step.option_extrinsic[i], env.terminated[i], option_steps, env.at_subgoal[i])))
            if env.done[i]:
                finished.append(self._close(i, ep, step))
                self.open[i] = _Open()
        return finished

    def _close(self, i: int, ep: _Open, step: StepRecord) -> FinishedEpisode:
        env = step.env
        t = len(ep.obs)
        sub = Episode(
            frames=np.stack(ep.obs + [env.obs[i].copy()]),
            fields={"action": np.asarray(ep.action, np.uint8), "reward": np.asarray(ep.reward, np.float32),
                    "terminal": np.asarray(ep.terminal, bool)},
            segment_starts=np.asarray(ep.segment_starts, np.int32),
            segment_data={"subgoal_image": np.stack(ep.segment_images)} if self.hierarchical else {},
        )
        meta = None
        if self.hierarchical:
            meta = Episode(
                frames=np.stack(ep.meta_frames + [step.meta_next_input[i].copy()]),
                fields={name: np.asarray(column, dtype) for (name, dtype), column in
                        zip(META_FIELDS, list(zip(*ep.meta_steps)) or [()] * len(META_FIELDS))},
            )
        stats = EpisodeStats(steps=t, classical=ep.classical, extrinsic=ep.extrinsic, intrinsic=ep.intrinsic,
                             success=bool(env.success[i]), options=len(ep.segment_starts), visits=ep.visits,
                             option_log=ep.option_log)
        return FinishedEpisode(i, sub, meta, stats)
