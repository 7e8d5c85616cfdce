"""Transitions <-> bag messages: a run recorded as the training graph's own topics.

A recording holds, per environment group (namespace ``/`` or ``/group<i>``), the per-step
topics of :mod:`hdrqn_ros.protocol.wire`: ``env_step``, ``observation``, ``action`` and
``pose``, and for hierarchical agents ``critic``, ``subgoal``, ``subgoal_images`` and
(hDRQNv2) ``sub_state`` - standard ``sensor_msgs``/``std_msgs``/``geometry_msgs`` types.
So a bag written here, one the learner node writes, and one ``ros2 bag record -s mcap``
takes of a running graph are read the same way: :func:`read_episodes` joins each group's
messages by step key (:class:`~hdrqn_ros.protocol.assembly.TransitionAssembler`) into the
replay episodes the trainer would have stored. Episode boundaries are in ``env_step``
(``t`` = 0 starts an episode; ``episode`` counts them).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import yaml

from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.agents.policy import StepRecord
from hdrqn_ros.config import TrainConfig
from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.registration import MONTEZUMA_IDS
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.assembly import TransitionAssembler
from hdrqn_ros.recording.bag import TYPESTORE, BagError, BagWriter, bag_custom_data, open_bag, read_messages
from hdrqn_ros.training.episodes import FinishedEpisode
from hdrqn_ros.yaml_files import safe_load

CONFIG_KEY = "hdrqn.config"
"""``custom_data`` key of a recording's training config (YAML of :class:`TrainConfig`)."""
SOURCE_KEY = "hdrqn.source"
STEP_PERIOD_NS = 10_000_000
"""Sim time per recorded step (the environment node's default ``step_period``, 0.01 s)."""
FRAME_ID = "hdrqn_map"

GROUP_TOPICS = {wire.ENV_STEP: wire.FLOATS, wire.OBSERVATION: wire.IMAGE, wire.ACTION: wire.INTS,
                wire.POSE: wire.POSE_STAMPED, wire.CRITIC: wire.FLOATS, wire.SUBGOAL: wire.INTS,
                wire.SUBGOAL_IMAGES: wire.IMAGE, wire.SUB_STATE: wire.FLOATS}
"""A group's recorded topics and their ROS 2 types."""


class RosbagsMessages:
    """What :mod:`~hdrqn_ros.protocol.wire`'s ``make_*`` need of a node: message classes
    (``rosbags``' ROS 2 Jazzy classes, serialized with its CDR codec) and ``pack``."""

    @staticmethod
    def msg(type_name: str) -> type:
        return TYPESTORE.types[type_name]

    @staticmethod
    def pack(values):
        return values


def recorded_topics(algo: str) -> list[str]:
    """The per-group topics a recording of ``algo`` holds."""
    spec = ALGO_SPECS[algo]
    names = [wire.ENV_STEP, wire.OBSERVATION, wire.ACTION, wire.POSE]
    if spec.hierarchical:
        names += [wire.CRITIC, wire.SUBGOAL, wire.SUBGOAL_IMAGES]
    if spec.meta_input == "state":
        names.append(wire.SUB_STATE)
    return names


class BagRecorder:
    """A :class:`BagWriter` for recordings: message timestamps are the wall clock at
    recording (ns), made strictly increasing so that readers see the recording order."""

    def __init__(self, path, cfg: TrainConfig, source: str, *, split_bytes: int = 256 * 2**20,
                 split_seconds: float = 0.0, compress: bool = True):
        custom = {CONFIG_KEY: yaml.safe_dump(cfg.model_dump(), sort_keys=False), SOURCE_KEY: source}
        self.writer = BagWriter(path, split_bytes=split_bytes, split_seconds=split_seconds, compress=compress,
                                custom_data=custom)
        self.path = self.writer.path
        self.messages = 0
        self._last_ns = 0

    def add_group(self, namespace: str, topics: list[str]) -> dict[str, int]:
        """Register a group's topics; returns topic name -> connection id."""
        return {name: self.writer.add_topic(wire.group_topic(namespace, name), GROUP_TOPICS[name],
                                            depth=wire.STEP_DEPTH if name != wire.POSE else 10)
                for name in topics}

    def write(self, connection: int, cdr: bytes) -> None:
        self._last_ns = max(time.time_ns(), self._last_ns + 1)
        self.writer.write(connection, self._last_ns, cdr)
        self.messages += 1

    def sync(self) -> None:
        """Make every message written so far survive a kill of this process (see :meth:`BagWriter.sync`)."""
        self.writer.sync()

    def close(self) -> None:
        self.writer.close()


@dataclass
class _EnvTrack:
    """One recorded environment's place in its own step-key sequence."""

    key: int = 0
    t: int = 0
    episode: int = 0
    env_steps: int = 0
    open: bool = False


class TransitionRecorder:
    """Records the in-process trainer's :class:`StepRecord` rows: environment ``i`` becomes
    group ``/group<i>`` (``/`` for one environment) with its own step keys, as if it were an
    environment node. The rollout must be made with ``record_subgoal_images=True``."""

    def __init__(self, path, cfg: TrainConfig, num_envs: int, source: str = "hdrqn train", **bag_options):
        self.bag = BagRecorder(path, cfg, source, **bag_options)
        self.spec = ALGO_SPECS[cfg.algo]
        self.namespaces = wire.group_namespaces(num_envs)
        topics = recorded_topics(cfg.algo)
        self.conns = [self.bag.add_group(ns, topics) for ns in self.namespaces]
        self.envs = [_EnvTrack() for _ in self.namespaces]
        self.grid = cfg.env not in MONTEZUMA_IDS
        self.m = RosbagsMessages()

    @property
    def path(self) -> Path:
        return self.bag.path

    def _put(self, i: int, topic: str, msg) -> None:
        self.bag.write(self.conns[i][topic], TYPESTORE.serialize_cdr(msg, GROUP_TOPICS[topic]))

    def _step_record(self, i: int, values: dict) -> None:
        track = self.envs[i]
        row = {f: 0.0 for f in wire.STEP_FIELDS}
        row.update(key=track.key, env_steps=track.env_steps, episode=track.episode, t=track.t, **values)
        self._put(i, wire.ENV_STEP, wire.make_record(self.m, wire.FLOATS, wire.STEP_FIELDS,
                                                     [row[f] for f in wire.STEP_FIELDS]))

    def write(self, step: StepRecord) -> None:
        """Record one step of every environment (call after each ``Rollout.step``)."""
        messages, env = self.m, step.env
        for i, track in enumerate(self.envs):
            if not track.open:  # the episode's first observation: t = 0, no action yet
                track.open, track.t = True, 0
                track.key += STEP_PERIOD_NS
                self._step_record(i, {"prev_key": 0, "at_subgoal": NO_SUBGOAL, "decision_point": 1})
                self._put(i, wire.OBSERVATION, wire.make_image(messages, track.key, step.obs[i], FRAME_ID))
                if self.spec.hierarchical:
                    self._put(i, wire.CRITIC,
                              wire.make_record(messages, wire.FLOATS, wire.CRITIC_FIELDS, [track.key, 0, 0, 1, -1]))
            prev = track.key
            self._put(i, wire.ACTION,
                      wire.make_record(messages, wire.INTS, wire.ACTION_FIELDS, [prev, int(step.action[i])]))
            if self.spec.hierarchical and step.new_option[i]:
                self._put(i, wire.SUBGOAL,
                          wire.make_record(messages, wire.INTS, wire.SUBGOAL_FIELDS, [prev, int(step.subgoal[i]), 1]))
                self._put(i, wire.SUBGOAL_IMAGES, wire.make_image(messages, prev, step.all_subgoal_images[i], FRAME_ID))
            if self.spec.meta_input == "state" and step.option_done[i]:
                self._put(i, wire.SUB_STATE,
                          wire.make_state(messages, prev, step.meta_next_input[i].astype(np.float64)))
            track.key += STEP_PERIOD_NS
            track.t += 1
            track.env_steps += 1
            self._step_record(i, {"prev_key": prev, "action": int(step.action[i]), **wire.step_outcome(env, i)})
            if self.spec.hierarchical:
                reached = int(env.at_subgoal[i] == step.subgoal[i])
                self._put(i, wire.CRITIC, wire.make_record(messages, wire.FLOATS, wire.CRITIC_FIELDS, [
                    track.key, float(step.intrinsic[i]), reached, int(step.option_done[i]), int(step.subgoal[i])]))
            self._put(i, wire.OBSERVATION, wire.make_image(messages, track.key, env.obs[i], FRAME_ID))
            a, b = (float(v) for v in env.agent_pos[i])
            self._put(i, wire.POSE, wire.make_pose(messages, track.key, FRAME_ID, *((b, a) if self.grid else (a, b))))
            if env.done[i]:
                track.open = False
                track.episode += 1

    def close(self) -> None:
        self.bag.close()


# -- reading ---------------------------------------------------------------------------------------
class _BagAssembler(TransitionAssembler):
    """A :class:`TransitionAssembler` for bag data: a malformed message is an error, and the
    recording's clock (the arrival times) drives the learner's 1 s stall timer, through the
    silent gaps too, so a step the live learner gave up as lost is given up here as well,
    not waited for until the queue overflows; at the recording's end every step that still
    keeps a complete one waiting is given up (:meth:`give_up_waiting`)."""

    def __init__(self, bag: Path, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.bag = bag
        self._next_tick_ns: int | None = None

    def at(self, timestamp_ns: int) -> None:
        """The recording's clock reached ``timestamp_ns`` (a message's arrival time): the
        timer ticks due since the last message, each at its own time; while no step waits
        a tick changes nothing, so the ticks of a long gap are skipped to its last one."""
        second = 1_000_000_000
        tick = timestamp_ns if self._next_tick_ns is None else self._next_tick_ns
        while tick <= timestamp_ns:
            if not self.waiting:
                tick += (timestamp_ns - tick) // second * second
            self.check_stall(now=tick / 1e9, report=False)
            tick += second
        self._next_tick_ns = tick

    def decode(self, topic, read):
        try:
            return read()
        except (wire.ProtocolError, ValueError, TypeError, AttributeError) as exc:
            raise BagError(f"{self.bag}: topic {topic}: {exc}") from None


@dataclass
class BagReadStats:
    """What :func:`read_episodes` found; counts per bag directory."""

    episodes: dict[str, int] = field(default_factory=dict)
    incomplete_episodes: dict[str, int] = field(default_factory=dict)  # cut short by the bag's end or gaps


def bag_config(path) -> dict | None:
    """The training config stored in a recording's metadata (None for other bags)."""
    text = bag_custom_data(path).get(CONFIG_KEY)
    if not text:
        return None
    try:
        data = safe_load(text)
    except yaml.YAMLError as exc:
        raise BagError(f"{path}: metadata.yaml custom_data {CONFIG_KEY} is not YAML ({exc})") from None
    if not isinstance(data, dict):
        raise BagError(f"{path}: metadata.yaml custom_data {CONFIG_KEY} is not a mapping")
    return data


def bag_groups(path) -> dict[str, dict[str, str]]:
    """Group namespace -> {topic name relative to it: type} for every ``.../env_step`` in a bag."""
    with open_bag(path) as reader:
        topics = {name: t.msgtype for name, t in reader.topics.items()}
    groups = {}
    for name in topics:
        if name.endswith("/" + wire.ENV_STEP):
            ns = name[: -len(wire.ENV_STEP)].rstrip("/") or "/"
            prefix = "" if ns == "/" else ns
            groups[ns] = {t[len(prefix) + 1:]: ty for t, ty in topics.items()
                          if t.startswith(prefix + "/") and "/" not in t[len(prefix) + 1:]}
    return groups


def read_episodes(paths, cfg: TrainConfig, num_subgoals: int, stats: BagReadStats | None = None,
                  logger: logging.Logger | None = None) -> Iterator[FinishedEpisode]:
    """Replay episodes for ``cfg.algo`` from the groups of each bag in ``paths`` (``group``:
    the group's namespace), in recording order.

    Raises :class:`BagError` naming the bag and the problem: not a bag, no ``env_step``
    topic, a topic ``cfg.algo`` needs missing or of the wrong type, malformed messages
    (e.g. images of another size than the domain's)."""
    logger = logger or logging.getLogger("hdrqn.bag")
    stats = stats if stats is not None else BagReadStats()
    for path in map(Path, paths):
        groups = bag_groups(path)
        if not groups:
            raise BagError(f"{path}: no {wire.ENV_STEP} topic (type {wire.FLOATS}): not a recording of hdrqn "
                           "transitions")
        finished: list = []
        handlers, assemblers = {}, []
        for ns, have in sorted(groups.items()):
            asm = _BagAssembler(path, ns, cfg, num_subgoals, finished.append, logger=logger)
            for name, (type_name, handler) in asm.inputs().items():
                topic = wire.group_topic(ns, name)
                if name not in have:
                    raise BagError(f"{path}: topic {topic} is missing; {cfg.algo} needs {sorted(asm.inputs())} "
                                   f"of each group")
                if have[name] != type_name:
                    raise BagError(f"{path}: topic {topic} has type {have[name]}, expected {type_name}")
                handlers[topic] = (type_name, handler)
            assemblers.append(asm)
        key = str(path)

        def taken() -> Iterator[FinishedEpisode]:
            while finished:
                stats.episodes[key] = stats.episodes.get(key, 0) + 1
                yield finished.pop(0)
        for topic, type_name, t, cdr in read_messages(path, topics=handlers):
            for asm in assemblers:
                asm.at(t)
            try:
                msg = TYPESTORE.deserialize_cdr(cdr, type_name)
            except Exception as exc:  # truncated or garbled CDR
                raise BagError(f"{path}: topic {topic}: undecodable {type_name} message ({exc})") from None
            handlers[topic][1](msg)
            yield from taken()
        for asm in assemblers:
            asm.give_up_waiting()
        yield from taken()
        stats.incomplete_episodes[key] = sum(a.lost_episodes + a.open_episodes for a in assemblers)


def episode_summary(path) -> dict[str, dict]:
    """Per group of a recording (from its ``env_step`` topic alone, a re-published step
    counted once): the environments it steps, complete episodes, mean return (classical
    reward), success rate, mean length, and episodes cut short."""
    groups = {wire.group_topic(ns, wire.ENV_STEP): ns for ns, have in bag_groups(path).items()
              if have.get(wire.ENV_STEP) == wire.FLOATS}
    acc = {ns: {"episodes": 0, "incomplete": 0, "returns": [], "successes": 0, "steps": 0, "num_envs": 0}
           for ns in groups.values()}
    open_return: dict[tuple[str, int], float | None] = {}  # (group, environment) -> return so far
    last_key: dict[tuple[str, int], int] = {}  # (group, environment) -> its latest step's key
    for topic, type_name, _t, cdr in read_messages(path, topics=groups):
        ns, totals = groups[topic], acc[groups[topic]]
        try:
            rows = wire.read_steps(TYPESTORE.deserialize_cdr(cdr, type_name))
        except Exception as exc:  # not our layout, or garbled
            raise BagError(f"{path}: topic {topic}: {exc}") from None
        totals["num_envs"] = len(rows)
        for i, step in enumerate(rows):
            if last_key.get((ns, i)) == int(step["key"]):
                continue  # a step re-published (no answer came in time): once is counted
            last_key[ns, i] = int(step["key"])
            so_far = open_return.get((ns, i))
            if step["t"] == 0:
                totals["incomplete"] += so_far is not None
                open_return[ns, i] = 0.0
            elif so_far is not None:
                open_return[ns, i] = so_far + step["classical"]
                if step["terminated"] or step["truncated"]:
                    totals["episodes"] += 1
                    totals["returns"].append(open_return[ns, i])
                    totals["successes"] += bool(step["success"])
                    totals["steps"] += int(step["t"])
                    open_return[ns, i] = None
    out = {}
    for ns, totals in acc.items():
        episodes = totals["episodes"]
        still_open = sum(v is not None for (group, _), v in open_return.items() if group == ns)
        out[ns] = {"num_envs": totals["num_envs"], "episodes": episodes, "incomplete": totals["incomplete"] + still_open,
                   "mean_return": float(np.mean(totals["returns"])) if episodes else None,
                   "success_rate": totals["successes"] / episodes if episodes else None,
                   "mean_steps": totals["steps"] / episodes if episodes else None}
    return out
