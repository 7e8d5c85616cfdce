"""``learner`` node: assembles transitions from the graph, owns replay, trains, publishes weights.

For each environment group (a namespace in ``groups``) a
:class:`~hdrqn_ros.nodes.learner_groups.GroupAssembler` joins the group's messages by step key
into the same :class:`StepRecord` rows the in-process rollout produces, and the same
:class:`EpisodeBuilder` turns them into replay episodes (recorded, when ``record``, by
:class:`~hdrqn_ros.recording.received.GraphRecorder`).
A training thread runs the :class:`~hdrqn_ros.training.learner.Learner` (one update per
controller every ``update_every`` env steps), publishes weights every ``weights_every``
updates on latched topics, and checkpoints. Each group's environment may run
``credit_window`` steps ahead of what the learner has received, and no further while the
learner owes more than ``max_owed_updates`` updates: so the thesis update ratio holds.
A group that joins late (or a learner that restarts) starts using a group's data at its
next episode boundary.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from pathlib import Path

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import String, UInt8MultiArray

from hdrqn_ros.agents.weights import encode_weights
from hdrqn_ros.config import ConfigError, TrainConfig, build_config, parse_set
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, env_kwargs
from hdrqn_ros.nodes.learner_groups import GroupAssembler
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import NodeConfigError, Param, declare_parameters
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import LATCHED_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, to_cdr
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import LOST_AFTER_S
from hdrqn_ros.recording.bag import BagError
from hdrqn_ros.recording.received import GraphRecorder, earlier_recordings
from hdrqn_ros.recording.transitions import read_episodes
from hdrqn_ros.training.checkpoint import CheckpointError
from hdrqn_ros.training.learner import Learner

MAX_COUNT = 10**9
"""The largest count a parameter takes (episodes, updates, steps)."""
PARAMETERS = {
    **ENV_PARAMETERS, **MAX_MESSAGE_BYTES,
    "config": Param("", "training config YAML (hdrqn train --config)"),
    "overrides": Param([""], "key=value config items, like hdrqn train --set"),
    "episodes": Param(1000, "training episodes, all groups together", low=1, high=MAX_COUNT),
    "run_dir": Param("runs/graph", "run directory: checkpoints, metrics, logs"),
    "groups": Param(["/"], "the groups' namespaces ([''] : offline only)"),
    "resume": Param(False, "continue from run_dir's checkpoint when there is one"),
    "weights_every": Param(100, "updates between weight publications", low=1, high=MAX_COUNT),
    "credit_window": Param(20, "env steps a group may run ahead of the updates owed", low=1, high=MAX_COUNT),
    "max_owed_updates": Param(8, "updates owed before a group's credit stops", low=1, high=MAX_COUNT),
    "status_period": Param(1.0, "seconds between status publications", positive=True),
    "evaluate": Param(True, "greedy evaluations during and after training"),
    "transition_log": Param("", "append every assembled transition to this JSON-lines file ('': off)"),
    "record": Param("", "record every message taken from the groups to this new rosbag2 MCAP bag ('': off)"),
    "record_split_mb": Param(256.0, "split the recording every this many MB", positive=True),
    "bags": Param([""], "fill the replay from these bags before training"),
    "offline_updates": Param(0, "updates on the bags before taking the graph's data", low=0, high=MAX_COUNT),
    "lost_after_s": Param(LOST_AFTER_S, "seconds a later step is complete before a step missing messages is "
                                        "given up", positive=True),
}
"""``config``: a training config YAML (``hdrqn train --config``); ``overrides``:
``key=value`` items like ``hdrqn train --set``; the parameters ``algo``, ``env``, ``view``,
``seed``, ``episodes`` win over both. ``resume``: continue from ``run_dir``'s checkpoint
when there is one. ``transition_log``: append every assembled transition to this JSON-lines
file (keys, action, rewards, flags, observation digests: for checking alignment; and
``wall_time``, the wall clock when the transition was assembled, for latency measurements).
``record``: write every message the learner takes from the groups to this new rosbag2 MCAP
bag (split every ``record_split_mb`` MB; a restarted learner records to ``<record>-restart<k>``).
With ``record`` and ``resume``, a restarted learner first refills its replay from the bags
its earlier lives recorded; an episode is acknowledged (``acked_episodes``/``acked_steps``
in each group's status) once its messages are flushed to the bag, so a killed learner
loses no acknowledged transition.
``bags``: fill the replay from these bags before training (not counted as this run's
episodes), then run ``offline_updates`` updates on them before taking the graph's data.
With no groups (``groups: [""]``) the learner trains offline only: ``offline_updates``
(default 10 per ``update_every`` recorded steps), then evaluates and finishes.
``lost_after_s``: a step whose messages have not all come is given up as lost once a later
step of its environment has been complete this long (DDS repairs a reliable sample within a
few heartbeats; raise it where links or machines are slow). All read-only: a learner's
settings are its run's."""

EPISODE_QUEUE = 256
"""Finished episodes waiting for the training thread (bounded; the credit keeps it short)."""


def train_config(params: dict) -> TrainConfig:
    """The run's config: the ``config`` file, then ``overrides``, then the parameters ``algo``,
    ``env``, ``view``, ``seed`` and ``episodes``."""
    overrides = parse_set([item for item in params["overrides"] if item])
    overrides.setdefault("env_kwargs", {}).update(env_kwargs(params["env"], params["view"]))
    return build_config([params["config"]] if params["config"] else [],
                        **{**overrides, "algo": params["algo"], "env": params["env"], "seed": params["seed"],
                           "episodes": params["episodes"]})


class LearnerNode(Node):
    """The learner: one :class:`GroupAssembler` per group, the replay and a training thread."""

    def __init__(self, **kwargs):
        super().__init__("learner", **kwargs)
        params = self.params = declare_parameters(self, PARAMETERS)
        self.logger = python_logger(self)  # %-style, for the protocol and recording layers
        bags, namespaces = [b for b in params["bags"] if b], [ns for ns in params["groups"] if ns]
        if not bags and not namespaces:
            raise NodeConfigError("nothing to learn from: give environment groups (groups) or bags (bags)")
        cfg = train_config(params)
        run_dir = Path(params["run_dir"])
        resume = params["resume"] and (run_dir / "checkpoints" / "last.pt").exists()
        self.learner = Learner(cfg, run_dir, resume=resume, progress=False, warn=self.get_logger().warning)
        if resume:
            self.get_logger().info(f"resumed from {run_dir} at episode {self.learner.episodes}")
        self.episodes: queue.Queue = queue.Queue(EPISODE_QUEUE)
        self.transition_log = open(params["transition_log"], "a", buffering=1) if params["transition_log"] else None
        self.prefilled = self._fill(bags)
        if bags:
            self.get_logger().info(f"replay filled from {len(bags)} bag(s): {self.prefilled[0]} episodes, "
                                   f"{self.prefilled[1]} steps")
            if not self.prefilled[0]:
                raise NodeConfigError(f"no complete episode for {cfg.algo} in {bags}")
        self.recovered = self._recover(params["record"]) if resume and params["record"] else (0, 0)
        self.offline_updates = params["offline_updates"]
        if not namespaces and not self.offline_updates:
            self.offline_updates = max(1, 10 * self.prefilled[1] // cfg.update_every)
        self.recorder = (GraphRecorder(params["record"], cfg, params["record_split_mb"], to_cdr, self.logger)
                         if params["record"] else None)
        self.groups = [GroupAssembler(self, ns, self.learner, self.episodes, self.logger, params["max_message_bytes"],
                                      params["lost_after_s"], self.transition_log, self.recorder)
                       for ns in namespaces]
        self.weight_pubs = {c.name: self.create_publisher(UInt8MultiArray, wire.WEIGHTS[c.name], LATCHED_QOS)
                            for c in self.learner.agent.controllers}
        self.status_pub = self.create_publisher(String, wire.STATUS, LATCHED_QOS)
        self.epoch = time.time()
        self.learner.begin()
        self.finished = False
        self.exit_code = 0
        self.summary: dict | None = None
        self._credit_lock = threading.Lock()
        self._stop = threading.Event()
        self._publish_weights()
        steady = Clock(clock_type=ClockType.STEADY_TIME)  # credit must flow while simulated time stands still
        self.create_timer(params["status_period"], self._status, clock=steady)
        self.create_timer(1.0, lambda: self._grant_credit(force=True), clock=steady)  # also reaches late joiners
        self.thread = threading.Thread(target=self._train, name="learner-train", daemon=True)
        self.thread.start()

    def _recover(self, record: str) -> tuple[int, int]:
        """Refill the replay from the bags the learner's earlier lives recorded to ``record``;
        returns (episodes, steps)."""
        recorded = earlier_recordings(record, self.logger)
        if recorded and self.learner.replay_restored:
            # The recordings hold every acknowledged episode, those after the checkpoint too:
            # refill from them alone rather than on top of the checkpoint's replay snapshot.
            for replay in self.learner.replays().values():
                replay.clear()
        recovered = self._fill(recorded)
        if recorded:
            self.get_logger().info(f"recovered {recovered[0]} acknowledged episodes ({recovered[1]} transitions) "
                                   f"from {', '.join(recorded)}")
        return recovered

    def _fill(self, bags: list[str]) -> tuple[int, int]:
        """Fill the replay from ``bags`` (not counted as this run's episodes); returns (episodes, steps)."""
        if not bags:
            return 0, 0
        items = read_episodes(bags, self.learner.cfg, self.learner.agent.num_subgoals, logger=self.logger)
        return self.learner.store(items, counted=False)

    # -- the training thread ---------------------------------------------------------------------
    def _train(self) -> None:
        """The offline updates, then: count the groups' transitions, store finished episodes, run
        the updates owed, publish weights and credit, until ``episodes``; then :meth:`_finish`."""
        learner, cfg = self.learner, self.learner.cfg
        counted = {id(g): g.transitions for g in self.groups}
        try:
            for i in range(1, self.offline_updates + 1):
                if self._stop.is_set():
                    return
                learner.update_once(offline=True)
                if i % self.params["weights_every"] == 0:
                    self._publish_weights()
            if not self.groups:
                self._finish()
                return
            while not self._stop.is_set() and learner.episodes < cfg.episodes:
                for g in self.groups:
                    learner.add_steps(g.transitions - counted[id(g)])
                    counted[id(g)] = g.transitions
                self._store_episodes()
                if learner.due("checkpoint"):
                    learner.save()
                if learner.owed_updates:
                    before = learner.agent.sub.updates
                    learner.run_owed_updates(limit=1)
                    if learner.agent.sub.updates // self.params["weights_every"] > before // self.params["weights_every"]:
                        self._publish_weights()
                self._grant_credit()
                if not learner.owed_updates:
                    time.sleep(0.001)
            if learner.episodes >= cfg.episodes:
                self._finish()
        except Exception as exc:  # TrainingDiverged and friends: keep the last good checkpoint
            self.get_logger().error(f"training stopped: {type(exc).__name__}: {exc}")
            self.exit_code = 1
        finally:
            self.finished = True

    def _store_episodes(self) -> None:
        learner = self.learner
        while learner.episodes < learner.cfg.episodes:
            try:
                episode = self.episodes.get_nowait()
            except queue.Empty:
                return
            eps = learner.epsilons()
            learner.store([episode])
            learner.log_episode(episode.stats, *eps)

    def _grant_credit(self, force: bool = False) -> None:
        learner = self.learner
        owed_ok = learner.owed_updates <= self.params["max_owed_updates"] and not self.episodes.full()
        with self._credit_lock:
            for g in self.groups:
                g.publish_credit(self.params["credit_window"], owed_ok, learner.epsilons(), self.epoch, force)

    def _publish_weights(self) -> None:
        updates = self.learner.agent.sub.updates
        for c in self.learner.agent.controllers:
            self.weight_pubs[c.name].publish(wire.make_weights(ROS_MESSAGES, encode_weights(c.online), updates))

    def _finish(self) -> None:
        learner, cfg = self.learner, self.learner.cfg
        learner.save()
        wall = learner.wall_s  # the training's, without the final evaluation
        final = learner.evaluate() if self.params["evaluate"] and cfg.eval_every else None  # eval.csv too
        self.summary = learner.summary(final, wall, groups={g.ns or "/": g.stats() for g in self.groups},
                                       prefilled={"episodes": self.prefilled[0], "steps": self.prefilled[1]},
                                       recovered={"episodes": self.recovered[0], "steps": self.recovered[1]})
        self._status()
        self.get_logger().info(f"done: {json.dumps(self.summary)}")

    # -- status ------------------------------------------------------------------------------------
    def status(self) -> dict:
        """What ``/learner/status`` and ``run_dir/status.json`` hold."""
        learner = self.learner
        eps, recent = learner.epsilons(), learner.recent
        return {"episodes": learner.episodes, "target_episodes": learner.cfg.episodes,
                "env_steps": learner.env_steps, "updates": learner.agent.sub.updates,
                "steps_per_s": round((learner.env_steps - learner.start_steps) / max(learner.wall_s, 1e-9), 1),
                "success_last100": round(float(np.mean([s.success for s in recent])), 3) if recent else None,
                "eps_sub": round(eps[0], 3), "eps_meta": round(eps[1], 3), "finished": self.summary is not None,
                "groups": {g.ns or "/": g.stats() for g in self.groups}}

    def _status(self) -> None:
        text = json.dumps(self.status())
        self.status_pub.publish(String(data=text))
        path = self.learner.run_dir / "status.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(path)

    def close(self) -> None:
        """Stop training; keep what was learned (a checkpoint unless training just finished)."""
        self._stop.set()
        self.thread.join(timeout=30)
        if self.summary is None and self.exit_code == 0:
            self.learner.save()
        self.learner.log.close()
        if self.transition_log is not None:
            self.transition_log.close()
        if self.recorder is not None:
            self.recorder.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(LearnerNode, argv, (ConfigError, BagError, CheckpointError), large_buffers_to_os=False)


if __name__ == "__main__":
    raise SystemExit(main())
