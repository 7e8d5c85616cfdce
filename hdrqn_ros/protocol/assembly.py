"""Joining one environment group's messages into replay episodes (no ROS, no DDS here).

:class:`TransitionAssembler` takes the group's decoded per-step messages (from the learner
node's subscriptions or from a bag), joins them by step key into the same
:class:`~hdrqn_ros.agents.policy.StepRecord` rows the in-process rollout produces, and
feeds the same :class:`~hdrqn_ros.training.episodes.EpisodeBuilder`; ``on_episode`` gets
each finished episode. It starts using a group's data at an episode boundary.
"""
from __future__ import annotations

import json
import time
from typing import Callable

import numpy as np

from hdrqn_ros.agents.algorithms import ALGO_SPECS
from hdrqn_ros.agents.networks import lstm_state_size
from hdrqn_ros.agents.policy import StepRecord
from hdrqn_ros.config import TrainConfig, batch_class
from hdrqn_ros.critic import sub_controller_terminal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import StepFollower, done
from hdrqn_ros.training.episodes import EpisodeBuilder, FinishedEpisode


def _critic_of(step: dict, critic: dict) -> dict:
    """``critic`` (the verdict on ``step``) if it ends the option where the episode ends."""
    if done(step) and not critic["option_done"]:
        raise wire.ProtocolError(f"the episode ends at step key {int(step['key'])} but its critic option_done is 0")
    return critic


class TransitionAssembler(StepFollower):
    """One environment group's messages -> :class:`StepRecord` rows -> replay episodes."""

    skip_stale = False  # a transition needs every step of its episode

    def __init__(self, namespace: str, cfg: TrainConfig, num_subgoals: int,
                 on_episode: Callable[[FinishedEpisode], None], node=None, logger=None, log=None):
        super().__init__(node, logger=logger)
        self.ns = namespace.rstrip("/")
        self.on_episode = on_episode
        self.spec = ALGO_SPECS[cfg.algo]
        self.num_subgoals = num_subgoals
        self.num_actions = batch_class(cfg.env).num_actions
        self.builder_args = (1, self.spec.hierarchical, cfg.controller("sub").gamma, cfg.meta.gamma,
                             cfg.smdp_discount)
        self.env_steps_seen = 0  # the env's own step count, from its latest env_step
        self.transitions = 0
        self.skipped = 0  # steps seen while waiting for an episode boundary
        self.lost_episodes = 0  # episodes cut short by missing messages or restarts
        self.open = False
        self.log = log

    def topic(self, name: str) -> str:
        return f"{self.ns}/{name}"

    def inputs(self) -> dict[str, tuple[str, Callable]]:
        """The group's topics this assembler reads: relative name -> (type, handler(msg))."""
        out = {wire.ENV_STEP: (wire.FLOATS, self.on_env_step),
               wire.OBSERVATION: (wire.IMAGE, lambda m: self._image(wire.OBSERVATION, m, 1)),
               wire.ACTION: (wire.INTS, lambda m: self._ints(wire.ACTION, wire.ACTION_FIELDS, m, self.num_actions))}
        if self.spec.hierarchical:
            out[wire.SUBGOAL_IMAGES] = (wire.IMAGE, lambda m: self._image(wire.SUBGOAL_IMAGES, m, self.num_subgoals))
            out[wire.SUBGOAL] = (wire.INTS,
                                 lambda m: self._ints(wire.SUBGOAL, wire.SUBGOAL_FIELDS, m, self.num_subgoals))
            out[wire.CRITIC] = (wire.FLOATS, self._critic)
        if self.spec.meta_input == "state":
            out[wire.SUB_STATE] = (wire.FLOATS, self._sub_state)
        return out

    # -- inputs --------------------------------------------------------------------------------
    def _image(self, topic: str, msg, rows: int) -> None:
        got = self.decode(self.topic(topic), lambda: wire.read_image(msg, OBS_SIZE * rows, OBS_SIZE))
        if got is not None:
            self.put(topic, *got)

    def _ints(self, topic: str, fields, msg, n: int) -> None:
        """An ``action`` or ``subgoal`` record; its value (field ``topic``) must be in [0, n)."""
        def read() -> dict:
            record = wire.read_record(msg, fields, np.int64)
            wire.check_index(record[topic], n, topic)
            return record

        record = self.decode(self.topic(topic), read)
        if record is not None:
            self.put(topic, record["key"], record)

    def _critic(self, msg) -> None:
        record = self.decode(self.topic(wire.CRITIC), lambda: wire.read_record(msg, wire.CRITIC_FIELDS))
        if record is not None:
            self.put(wire.CRITIC, record["key"], record)

    def _sub_state(self, msg) -> None:
        got = self.decode(self.topic(wire.SUB_STATE), lambda: wire.read_state(msg, lstm_state_size))
        if got is not None:
            self.put(wire.SUB_STATE, *got)

    def received(self, step: dict) -> None:
        self.env_steps_seen = int(step["env_steps"])

    def holds_answers(self, step: dict) -> bool:
        """Whether the inbox holds ``step``'s observation and the controllers' answers to it:
        its action and, at an episode's first step, its subgoal and subgoal images."""
        key, box = int(step["key"]), self.inbox
        if not (box.has(wire.OBSERVATION, key) and box.has(wire.ACTION, key)):
            return False
        if self.spec.hierarchical and step["t"] == 0:
            return box.has(wire.SUBGOAL, key) and box.has(wire.SUBGOAL_IMAGES, key)
        return True

    # -- assembly -----------------------------------------------------------------------------------
    def ready(self, step: dict) -> bool:
        key, prev, box = int(step["key"]), int(step["prev_key"]), self.inbox
        if not box.has(wire.OBSERVATION, key):
            return False
        if step["t"] == 0 or not self.open:
            return True
        if not box.has(wire.ACTION, prev):
            return False
        if not self.spec.hierarchical:
            return True
        critic = box.get(wire.CRITIC, key)
        if critic is None:
            return False
        if self.option_next and not (box.has(wire.SUBGOAL, prev) and box.has(wire.SUBGOAL_IMAGES, prev)):
            return False
        return not (self.spec.meta_input == "state" and critic["option_done"]) or box.has(wire.SUB_STATE, prev)

    def process(self, step: dict) -> list:
        key, obs = int(step["key"]), self.inbox.get(wire.OBSERVATION, int(step["key"]))
        if step["t"] == 0:
            if self.open:
                self.lost_episodes += 1
            self._begin(key, obs)
        elif not self.open:
            self.skipped += 1
        elif int(step["prev_key"]) != self.last_key:  # steps in between never arrived (e.g. a link was down)
            self.lost_episodes += 1
            self.skipped += 1
            self.open = False
        else:
            self._transition(step, obs)
        return []

    def _begin(self, key: int, obs: np.ndarray) -> None:
        self.open = True
        self.option_next = True  # an option starts at the episode's first step
        self.builder = EpisodeBuilder(*self.builder_args)
        self.prev_obs = obs
        self.subgoal_image = np.zeros_like(obs)
        self.option_extrinsic = 0.0
        self.option_steps = 0
        self.last_sub_state = np.zeros(lstm_state_size, np.float32)

    def _transition(self, step: dict, obs: np.ndarray) -> None:
        box, key, prev = self.inbox, int(step["key"]), int(step["prev_key"])
        action = int(box.get(wire.ACTION, prev)["action"])
        env = wire.step_batch(step, obs)
        if self.spec.hierarchical:
            critic = self.decode(self.topic(wire.CRITIC), lambda: _critic_of(step, box.get(wire.CRITIC, key)))
            if critic is None:  # the messages contradict each other: the episode cannot be assembled
                self.lost_episodes += 1
                self.open = False
                return
            new_option = self.option_next
            if new_option:  # the meta-controller publishes a subgoal when an option starts
                self.option_subgoal = int(box.get(wire.SUBGOAL, prev)["subgoal"])
            subgoal = self.option_subgoal
            intrinsic, reached, option_done = critic["intrinsic"], bool(critic["reached"]), bool(critic["option_done"])
            self.option_next = option_done
            sub_terminal = bool(sub_controller_terminal(reached, step["terminated"], step["life_lost"], option_done))
        else:
            subgoal, new_option = -1, step["t"] == 1
            intrinsic, option_done, sub_terminal = 0.0, done(step), bool(step["terminated"])
        meta_input = None
        if new_option:
            if self.spec.hierarchical:
                images = box.get(wire.SUBGOAL_IMAGES, prev)
                self.subgoal_image = images[subgoal * OBS_SIZE:(subgoal + 1) * OBS_SIZE]
                meta_input = (self.last_sub_state if self.spec.meta_input == "state" else self.prev_obs)[None].copy()
            self.option_extrinsic, self.option_steps = 0.0, 0
        self.option_extrinsic += float(step["extrinsic"])
        self.option_steps += 1
        meta_next = None
        if self.spec.hierarchical and option_done:
            if self.spec.meta_input == "state":
                self.last_sub_state = box.get(wire.SUB_STATE, prev)
                meta_next = self.last_sub_state[None].copy()
            else:
                meta_next = obs[None].copy()
        record = StepRecord(
            obs=self.prev_obs[None], new_option=np.array([new_option]), meta_input=meta_input,
            subgoal=np.array([subgoal]), subgoal_image=self.subgoal_image[None], action=np.array([action]),
            env=env, intrinsic=np.array([intrinsic], np.float32), option_done=np.array([option_done]),
            sub_terminal=np.array([sub_terminal]), option_extrinsic=np.array([self.option_extrinsic], np.float32),
            option_steps=np.array([self.option_steps]), meta_next_input=meta_next)
        self.transitions += 1
        if self.log is not None:
            self._log(step, action, subgoal, intrinsic, obs)
        for episode in self.builder.add(record):
            self.on_episode(episode._replace(group=self.ns or "/"))
            self.open = False
        self.prev_obs = obs

    def _log(self, step: dict, action: int, subgoal: int, intrinsic: float, obs: np.ndarray) -> None:
        row = {"group": self.ns or "/", **{f: step[f] for f in ("key", "prev_key", "episode", "t", "extrinsic",
                                                                "classical", "terminated", "truncated")},
               "action": action, "subgoal": subgoal, "intrinsic": intrinsic,
               "obs": wire.obs_digest(self.prev_obs), "next_obs": wire.obs_digest(obs),
               "wall_time": time.time()}  # when assembled (wall clock): latency vs the step_log's wall_time
        self.log.write(json.dumps(row) + "\n")

    def stats(self) -> dict:
        return {"env_steps": self.env_steps_seen, "transitions": self.transitions, "skipped": self.skipped,
                "lost_episodes": self.lost_episodes, "rejected": self.rejected}


