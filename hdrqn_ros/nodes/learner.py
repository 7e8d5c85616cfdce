"""``learner`` node: assembles transitions from the graph, owns replay, trains, publishes weights.

For each environment group (a namespace in ``groups``) a
:class:`~hdrqn_ros.protocol.group.GroupAssembler` joins the group's messages by step key
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

from hdrqn_ros.agents.weights import encode_weights
from hdrqn_ros.config import ConfigError, build_config, parse_set
from hdrqn_ros.middleware import LATCHED_QOS, Middleware, ParameterRule
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import LOST_AFTER_S
from hdrqn_ros.protocol.group import GroupAssembler
from hdrqn_ros.recording.bag import BagError
from hdrqn_ros.recording.received import GraphRecorder, earlier_recordings
from hdrqn_ros.recording.transitions import read_episodes
from hdrqn_ros.nodes.common import ENV_DEFAULTS, ENV_RULES, NodeConfigError, check_algo, env_kwargs, run_node
from hdrqn_ros.training.checkpoint import CheckpointError
from hdrqn_ros.training.learner import Learner

PARAMETERS = {**ENV_DEFAULTS, "config": "", "overrides": [""], "episodes": 1000, "run_dir": "runs/graph",
              "groups": ["/"], "resume": False, "weights_every": 100, "credit_window": 20, "max_owed_updates": 8,
              "status_period": 1.0, "evaluate": True, "transition_log": "", "record": "", "record_split_mb": 256.0,
              "bags": [""], "offline_updates": 0, "lost_after_s": LOST_AFTER_S}
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
few heartbeats; raise it where links or machines are slow)."""
RULES = {
    **ENV_RULES,
    "config": ParameterRule("training config YAML (hdrqn train --config)"),
    "overrides": ParameterRule("key=value config items, like hdrqn train --set"),
    "episodes": ParameterRule("training episodes, all groups together", low=1, high=10**9),
    "run_dir": ParameterRule("run directory: checkpoints, metrics, logs"),
    "groups": ParameterRule("the groups' namespaces ([''] : offline only)"),
    "resume": ParameterRule("continue from run_dir's checkpoint when there is one"),
    "weights_every": ParameterRule("updates between weight publications", low=1, high=10**9),
    "credit_window": ParameterRule("env steps a group may run ahead of the updates owed", low=1, high=10**9),
    "max_owed_updates": ParameterRule("updates owed before a group's credit stops", low=1, high=10**9),
    "status_period": ParameterRule("seconds between status publications", positive=True),
    "evaluate": ParameterRule("greedy evaluations during and after training"),
    "transition_log": ParameterRule("append every assembled transition to this JSON-lines file ('': off)"),
    "record": ParameterRule("record every message taken from the groups to this new rosbag2 MCAP bag ('': off)"),
    "record_split_mb": ParameterRule("split the recording every this many MB", positive=True),
    "bags": ParameterRule("fill the replay from these bags before training"),
    "offline_updates": ParameterRule("updates on the bags before taking the graph's data", low=0, high=10**9),
    "lost_after_s": ParameterRule("seconds a later step is complete before a step missing messages is given up",
                                  positive=True),
}
"""Descriptions of :data:`PARAMETERS`: all read-only (a learner's settings are its run's)."""

EPISODE_QUEUE = 256
"""Finished episodes waiting for the training thread (bounded; the credit keeps it short)."""


class LearnerNode:
    def __init__(self, mw: Middleware):
        node = self.node = mw.create_node("learner")
        params = self.params = node.declare_parameters(PARAMETERS, rules=RULES)
        check_algo(params["algo"])
        overrides = parse_set([item for item in params["overrides"] if item])
        overrides.setdefault("env_kwargs", {}).update(env_kwargs(params["env"], params["view"]))
        cfg = build_config([params["config"]] if params["config"] else [],
                           **{**overrides, "algo": params["algo"], "env": params["env"], "seed": params["seed"],
                              "episodes": params["episodes"]})
        run_dir = Path(params["run_dir"])
        resume = params["resume"] and (run_dir / "checkpoints" / "last.pt").exists()
        self.learner = Learner(cfg, run_dir, resume=resume, progress=False)
        if resume:
            node.logger.info("resumed from %s at episode %d", run_dir, self.learner.episodes)
        for key in ("weights_every", "credit_window", "max_owed_updates"):
            if params[key] < 1:
                raise NodeConfigError(f"{key} must be >= 1, got {params[key]}")
        self.episodes: queue.Queue = queue.Queue(EPISODE_QUEUE)
        self.transition_log = open(params["transition_log"], "a", buffering=1) if params["transition_log"] else None
        if params["offline_updates"] < 0:
            raise NodeConfigError(f"offline_updates must be >= 0, got {params['offline_updates']}")
        bags, namespaces = [b for b in params["bags"] if b], [ns for ns in params["groups"] if ns]
        if not bags and not namespaces:
            raise NodeConfigError("nothing to learn from: give environment groups (groups) or bags (bags)")
        if params["record"] and params["record_split_mb"] <= 0:
            raise NodeConfigError(f"record_split_mb must be > 0, got {params['record_split_mb']}")
        self.prefilled = self._fill(bags)
        if bags:
            node.logger.info("replay filled from %d bag(s): %d episodes, %d steps", len(bags), *self.prefilled)
            if not self.prefilled[0]:
                raise NodeConfigError(f"no complete episode for {cfg.algo} in {bags}")
        recorded = earlier_recordings(params["record"], node.logger) if resume and params["record"] else []
        if recorded and self.learner.replay_restored:
            # The recordings hold every acknowledged episode, those after the checkpoint too:
            # refill from them alone rather than on top of the checkpoint's replay snapshot.
            for replay in self.learner.replays().values():
                replay.clear()
        self.recovered = self._fill(recorded)
        if recorded:
            node.logger.info("recovered %d acknowledged episodes (%d transitions) from %s", *self.recovered,
                             ", ".join(recorded))
        self.offline_updates = params["offline_updates"]
        if not namespaces and not self.offline_updates:
            self.offline_updates = max(1, 10 * self.prefilled[1] // cfg.update_every)
        self.recorder = (GraphRecorder(node, params["record"], cfg, params["record_split_mb"])
                         if params["record"] else None)
        self.groups = [GroupAssembler(node, ns, self.learner, self.episodes, self.transition_log, self.recorder,
                                      params["lost_after_s"]) for ns in namespaces]
        self.weight_pubs = {c.name: node.create_publisher(wire.BYTES, wire.WEIGHTS[c.name], LATCHED_QOS)
                            for c in self.learner.agent.controllers}
        self.status_pub = node.create_publisher(wire.STRING, wire.STATUS, LATCHED_QOS)
        self.epoch = time.time()
        self.learner.begin()
        self.finished = False
        self.exit_code = 0
        self.summary: dict | None = None
        self._credit_lock = threading.Lock()
        self._stop = threading.Event()
        self._publish_weights()
        node.create_timer(params["status_period"], self._status)
        node.create_timer(1.0, lambda: self._grant_credit(force=True))  # also reaches late joiners
        self.thread = threading.Thread(target=self._train, name="learner-train", daemon=True)
        self.thread.start()

    def _fill(self, bags: list[str]) -> tuple[int, int]:
        """Fill the replay from ``bags`` (not counted as this run's episodes); returns (episodes, steps)."""
        if not bags:
            return 0, 0
        items = read_episodes(bags, self.learner.cfg, self.learner.agent.num_subgoals, logger=self.node.logger)
        return self.learner.store(items, counted=False)

    # -- the training thread ---------------------------------------------------------------------
    def _train(self) -> None:
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
            self.node.logger.error("training stopped: %s: %s", type(exc).__name__, exc)
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
            self.weight_pubs[c.name].publish(wire.make_weights(self.node, encode_weights(c.online), updates))

    def _finish(self) -> None:
        learner, cfg = self.learner, self.learner.cfg
        learner.save()
        wall = learner.wall_s  # the training's, without the final evaluation
        final = learner.evaluate() if self.params["evaluate"] and cfg.eval_every else None  # eval.csv too
        self.summary = learner.summary(final, wall, groups={g.ns or "/": g.stats() for g in self.groups},
                                       prefilled={"episodes": self.prefilled[0], "steps": self.prefilled[1]},
                                       recovered={"episodes": self.recovered[0], "steps": self.recovered[1]})
        self._status()
        self.node.logger.info("done: %s", json.dumps(self.summary))

    # -- status ------------------------------------------------------------------------------------
    def status(self) -> dict:
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
        self.status_pub.publish(self.node.msg(wire.STRING)(data=text))
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
    return run_node(lambda mw: LearnerNode(mw), argv, (ConfigError, BagError, CheckpointError),
                    large_buffers_to_os=False)


if __name__ == "__main__":
    raise SystemExit(main())
