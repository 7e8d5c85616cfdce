"""Joining one environment group's messages into replay episodes (no ROS, no DDS here).

:class:`TransitionAssembler` takes the group's decoded per-step messages (from the learner
node's subscriptions or from a bag), joins them by step key into the same
:class:`~hdrqn_ros.agents.policy.StepRecord` rows the in-process rollout produces, and
feeds the same :class:`~hdrqn_ros.training.episodes.EpisodeBuilder`; ``on_episode`` gets
each finished episode. A group may step a batch of environments: each one's records are
assembled on their own (:class:`EnvAssembler`), from an episode boundary on.
"""
from __future__ import annotations

import json
import logging
import time
from typing import Callable

import numpy as np

from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.agents.networks import lstm_state_size
from hdrqn_ros.agents.policy import StepRecord
from hdrqn_ros.config import TrainConfig, batch_class
from hdrqn_ros.envs.critic import sub_controller_terminal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import LOST_AFTER_S, Decoder, StepFollower, done
from hdrqn_ros.training.episodes import EpisodeBuilder, FinishedEpisode


def _critic_of(step: dict, critic: dict) -> dict:
    """``critic`` (the verdict on ``step``) if it ends the option where the episode ends."""
    if done(step) and not critic["option_done"]:
        raise wire.ProtocolError(f"the episode ends at step key {int(step['key'])} but its critic option_done is 0")
    return critic


class _Prefixed:
    """A logger whose lines start with ``prefix`` (which group and environment they are about)."""

    def __init__(self, logger, prefix: str):
        self.logger, self.prefix = logger, prefix

    def info(self, msg: str, *args) -> None:
        self.logger.info(self.prefix + msg, *args)

    def warning(self, msg: str, *args) -> None:
        self.logger.warning(self.prefix + msg, *args)

    def error(self, msg: str, *args) -> None:
        self.logger.error(self.prefix + msg, *args)


class TransitionAssembler(Decoder):
    """One environment group's messages -> :class:`StepRecord` rows -> replay episodes.

    A group's environment node steps one environment or a batch of them (``num_envs``):
    the number comes with the messages (their ``env`` dimension, or the stacked images'
    height), and each environment's records go to its own :class:`EnvAssembler`."""

    def __init__(self, namespace: str, cfg: TrainConfig, num_subgoals: int,
                 on_episode: Callable[[FinishedEpisode], None], logger: logging.Logger, log=None,
                 lost_after_s: float = LOST_AFTER_S):
        """``logger``: %-style; ``log``: the transition log (a text file) or None;
        ``lost_after_s``: each environment's :attr:`StepFollower.lost_after_s`. The reader
        calls :meth:`check_stall` every second."""
        self.lost_after_s = lost_after_s
        self.logger = logger
        self.ns = namespace.rstrip("/")
        self.cfg, self.num_subgoals, self.on_episode, self.log = cfg, num_subgoals, on_episode, log
        self.spec = ALGO_SPECS[cfg.algo]
        self.num_actions = batch_class(cfg.env).num_actions
        self.envs: list[EnvAssembler] = []  # one per environment, made when the first message says how many
        self.env_steps_seen = 0  # the env node's own step count, from its latest env_step

    def topic(self, name: str) -> str:
        return f"{self.ns}/{name}"

    def inputs(self) -> dict[str, tuple[str, Callable]]:
        """The group's topics this assembler reads: relative name -> (type, handler(msg))."""
        out = {wire.ENV_STEP: (wire.FLOATS, self.on_env_step),
               wire.OBSERVATION: (wire.IMAGE, lambda m: self._images(wire.OBSERVATION, m, 1)),
               wire.ACTION: (wire.INTS, self._actions)}
        if self.spec.hierarchical:
            out[wire.SUBGOAL_IMAGES] = (wire.IMAGE, lambda m: self._images(wire.SUBGOAL_IMAGES, m, self.num_subgoals))
            out[wire.SUBGOAL] = (wire.INTS, self._subgoals)
            out[wire.CRITIC] = (wire.FLOATS, self._critic)
        if self.spec.meta_input == "state":
            out[wire.SUB_STATE] = (wire.FLOATS, self._sub_states)
        return out

    # -- inputs: each environment's part to its assembler ---------------------------------------------
    def _group_of(self, n: int, topic: str) -> list["EnvAssembler"]:
        """The group's assemblers, made for ``n`` environments if there are none yet."""
        if not self.envs:
            self.envs = [EnvAssembler(self, i) for i in range(n)]
            for env in self.envs:
                env.lost_after_s = self.lost_after_s
        elif n != len(self.envs):
            raise wire.ProtocolError(f"{topic} holds {n} environment(s)' data, the group's messages so far "
                                     f"{len(self.envs)}")
        return self.envs

    def on_env_step(self, msg) -> None:
        def read() -> list[dict]:
            rows = wire.read_steps(msg)
            if self.envs and len(rows) != len(self.envs) and all(row["t"] == 0 for row in rows):
                self.logger.info("group %s now steps %d environment(s) (was %d): starting over", self.ns or "/",
                                 len(rows), len(self.envs))
                self.envs = []  # the environment node restarted with another num_envs
            self._group_of(len(rows), wire.ENV_STEP)
            return rows

        rows = self.decode(self.topic(wire.ENV_STEP), read)
        if rows is None:
            return
        self.received(rows)
        for env, row in zip(self.envs, rows):
            env.take([row])

    def _images(self, topic: str, msg, per_env: int) -> None:
        def read() -> tuple[int, np.ndarray]:
            rows, part = int(msg.height), OBS_SIZE * per_env
            n = rows // part if rows % part == 0 and rows else 0
            if not 1 <= n <= wire.MAX_ENVS:
                raise wire.ProtocolError(f"image must be {part}x{OBS_SIZE} per environment (stacked top to bottom), "
                                         f"got {rows}x{msg.width}")
            got = wire.read_images(msg, part, OBS_SIZE, n)
            self._group_of(n, topic)
            return got

        got = self.decode(self.topic(topic), read)
        if got is not None:
            for env, pixels in zip(self.envs, got[1]):
                env.put(topic, got[0], pixels)

    def _values(self, topic: str, read: Callable[[], tuple[int, np.ndarray]], missing: int | None = None) -> None:
        """Each environment's value of a per-environment message (none where it is ``missing``)."""
        def checked() -> tuple[int, np.ndarray]:
            key, values = read()
            self._group_of(len(values), topic)
            return key, values

        got = self.decode(self.topic(topic), checked)
        if got is not None:
            for env, value in zip(self.envs, got[1]):
                if missing is None or value != missing:
                    env.put(topic, got[0], value)

    def _actions(self, msg) -> None:
        self._values(wire.ACTION, lambda: wire.read_actions(msg, self.num_actions), missing=-1)

    def _subgoals(self, msg) -> None:
        self._values(wire.SUBGOAL, lambda: wire.read_subgoals(msg, self.num_subgoals), missing=-1)

    def _critic(self, msg) -> None:
        def read() -> tuple[int, list]:
            verdicts = wire.read_records(msg, wire.CRITIC_FIELDS)
            return int(verdicts[0]["key"]), verdicts

        self._values(wire.CRITIC, read)

    def _sub_states(self, msg) -> None:
        self._values(wire.SUB_STATE, lambda: wire.read_states(msg, lstm_state_size))

    def received(self, rows: list[dict]) -> None:
        """Called for every well-formed step (its ``env_step`` records) on arrival."""
        self.env_steps_seen = int(rows[0]["env_steps"])

    def check_stall(self, now: float | None = None, report: bool = True) -> None:
        """Every second: each environment's :meth:`StepFollower.check_stall`."""
        for env in self.envs:
            env.check_stall(now, report)

    @property
    def waiting(self) -> bool:
        """Some environment's :attr:`StepFollower.waiting`."""
        return any(env.waiting for env in self.envs)

    def give_up_waiting(self) -> None:
        """The end of a recording: each environment's :meth:`StepFollower.give_up_waiting`."""
        for env in self.envs:
            env.give_up_waiting()

    @property
    def assembled_env_steps(self) -> int | None:
        """The env node's step count at the last step every environment's assembler has
        processed (``None`` before one has)."""
        done_at = [env.processed_env_steps for env in self.envs]
        return None if not done_at or None in done_at else min(done_at)

    def holds_answers(self, rows: list[dict]) -> bool:
        """Whether the assemblers hold a step's observations and the other nodes' answers to
        it (:meth:`EnvAssembler.holds_answers`, for every environment of ``rows``)."""
        return len(rows) == len(self.envs) and all(env.holds_answers(row) for env, row in zip(self.envs, rows))

    # -- what the group's assemblers did, together -----------------------------------------------------
    @property
    def transitions(self) -> int:
        return sum(env.transitions for env in self.envs)

    @property
    def lost_episodes(self) -> int:
        return sum(env.lost_episodes for env in self.envs)

    @property
    def open_episodes(self) -> int:
        """Episodes begun and not finished (a bag that ends mid-episode)."""
        return sum(env.open for env in self.envs)

    @property
    def last_key(self) -> int:
        """The last step key assembled."""
        return max((env.last_key for env in self.envs), default=0)

    def stats(self) -> dict:
        return {"env_steps": self.env_steps_seen, "transitions": self.transitions,
                "skipped": sum(env.skipped for env in self.envs), "lost_episodes": self.lost_episodes,
                "rejected": self.rejected, "num_envs": len(self.envs)}


class EnvAssembler(StepFollower):
    """One environment's records of a group's messages (put by its
    :class:`TransitionAssembler`) -> :class:`StepRecord` rows -> replay episodes. Starts
    using the environment's data at an episode boundary."""

    skip_stale = False  # a transition needs every step of its episode

    def __init__(self, group: TransitionAssembler, index: int):
        super().__init__(logger=_Prefixed(group.logger, f"group {group.ns or '/'} env {index}: "))
        self.group, self.index = group, index
        self.spec = group.spec
        self.builder_args = (1, self.spec.hierarchical)
        self.transitions = 0
        self.skipped = 0  # steps seen while waiting for an episode boundary
        self.lost_episodes = 0  # episodes cut short by missing messages or restarts
        self.open = False

    def decode(self, topic, read):
        return self.group.decode(topic, read)

    def topic(self, name: str) -> str:
        return self.group.topic(name)

    def holds_answers(self, step: dict) -> bool:
        """Whether the inbox holds ``step``'s observation and the other nodes' answers to it:
        in a hierarchical group the critic's (it answers every step), its action and, at an
        episode's first step, its subgoal and subgoal images."""
        key, box = int(step["key"]), self.inbox
        if self.spec.hierarchical and not box.has(wire.CRITIC, key):
            return False
        if done(step):
            return box.has(wire.OBSERVATION, key)
        if not (box.has(wire.OBSERVATION, key) and box.has(wire.ACTION, key)):
            return False
        if self.spec.hierarchical and step["t"] == 0:
            return box.has(wire.SUBGOAL, key) and box.has(wire.SUBGOAL_IMAGES, key)
        return True

    # -- assembly -----------------------------------------------------------------------------------
    def ready(self, rows: list[dict]) -> bool:
        step = rows[0]
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

    def process(self, rows: list[dict]) -> list:
        step = rows[0]
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
        action = int(box.get(wire.ACTION, prev))
        env = wire.step_batch(step, obs)
        if self.spec.hierarchical:
            critic = self.decode(self.topic(wire.CRITIC), lambda: _critic_of(step, box.get(wire.CRITIC, key)))
            if critic is None:  # the messages contradict each other: the episode cannot be assembled
                self.lost_episodes += 1
                self.open = False
                return
            new_option = self.option_next
            if new_option:  # the meta-controller publishes a subgoal when an option starts
                self.option_subgoal = int(box.get(wire.SUBGOAL, prev))
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
        if self.group.log is not None:
            self._log(step, action, subgoal, intrinsic, obs)
        for episode in self.builder.add(record):
            self.group.on_episode(episode._replace(group=self.group.ns or "/"))
            self.open = False
        self.prev_obs = obs

    def _log(self, step: dict, action: int, subgoal: int, intrinsic: float, obs: np.ndarray) -> None:
        row = {"group": self.group.ns or "/", "env": self.index, **{f: step[f] for f in ("key", "prev_key", "episode", "t", "extrinsic",
                                                                "classical", "terminated", "truncated")},
               "action": action, "subgoal": subgoal, "intrinsic": intrinsic,
               "obs": wire.obs_digest(self.prev_obs), "next_obs": wire.obs_digest(obs),
               "wall_time": time.time()}  # when assembled (wall clock): latency vs the step_log's wall_time
        self.group.log.write(json.dumps(row) + "\n")
