"""``environment`` node: one simulated domain (or ``num_envs`` of them as a batch), stepped
in lock-step with the controllers.

For every step key it publishes ``observation`` (rgb8 Image), ``env_step`` (what the last
action did), ``pose`` (agent cell, PoseStamped; a batch: ``poses``, PoseArray) and
``/clock`` (sim time = key), and at decision points ``subgoal_images``. It steps when the ``action`` for the current key
arrives and, with ``wait_for_learner``, only while the learner's ``learner_credit``
allows. A missing peer is logged every ``action_timeout`` seconds and the current step
is re-published, so a controller that (re)joins late picks the loop up again.
"""
from __future__ import annotations

import json
import time

import numpy as np

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.registration import MONTEZUMA_IDS, make_batch
from hdrqn_ros.middleware import LATCHED_QOS, Middleware
from hdrqn_ros.protocol import wire
from hdrqn_ros.middleware import ParameterRule
from hdrqn_ros.nodes.common import (ENV_DEFAULTS, ENV_RULES, NodeConfigError, check_num_envs, env_kwargs,
                                    live_parameters, run_node)
from hdrqn_ros.protocol.follower import done
from hdrqn_ros.throttle import Throttle

PARAMETERS = {**ENV_DEFAULTS, "step_period": 0.01, "frame_id": "hdrqn_map", "action_timeout": 5.0,
              "wait_for_learner": False, "max_episodes": 0, "step_log": "", "publish_clock": True, "num_envs": 1}
"""``step_period``: simulated seconds per step (the key increment); ``num_envs``: environments
stepped together as one batch (1..64; > 1: one message per topic and step holds them all, see
``docs/topics.md``; every node of the group needs the same value); ``max_episodes``: stop
after this many episodes, all environments together (0: run until stopped); ``step_log``: append every step to this
JSON-lines file (the ground truth that learner transition logs are checked against; each
row also has ``wall_time``, the wall clock (``time.time()``) just before the step is
published, and ``action_time``, when the action that made the step arrived, for latency
measurements: ``benchmarks/bench_load.py``); ``publish_clock``: publish ``/clock`` (turn
off for all but one group: there is one sim clock)."""

RULES = {**ENV_RULES,
         "step_period": ParameterRule("simulated seconds per step (the step key's increment)", positive=True),
         "frame_id": ParameterRule("header.frame_id of observation, subgoal_images and pose"),
         "action_timeout": ParameterRule("seconds without an action before a warning and a re-published step",
                                         live=True, positive=True),
         "wait_for_learner": ParameterRule("step only while the learner's credit allows (the training graph)"),
         "max_episodes": ParameterRule("stop after this many episodes, all environments together (0: never)",
                                       live=True, low=0, high=2**31),
         "step_log": ParameterRule("append every step to this JSON-lines file ('': off)"),
         "publish_clock": ParameterRule("publish /clock (one group only: there is one sim clock)")}
"""Descriptions and rules of :data:`PARAMETERS` (``ros2 param describe``); live: the action
timeout and ``max_episodes``."""


class EnvironmentNode:
    def __init__(self, mw: Middleware):
        node = self.node = mw.create_node("environment")
        params = self.params = node.declare_parameters(PARAMETERS, rules=RULES)
        live_parameters(node, params, RULES)
        self.period_ns = int(round(params["step_period"] * 1e9))
        if self.period_ns <= 0 or params["action_timeout"] <= 0:
            raise NodeConfigError("step_period and action_timeout must be > 0")
        n = self.num_envs = check_num_envs(params["num_envs"])
        kwargs = env_kwargs(params["env"], params["view"])
        self.envs = [make_batch(params["env"], 1, **kwargs) for _ in range(n)]  # stepped one by one: see _advance
        self.num_actions, self.num_subgoals = self.envs[0].num_actions, self.envs[0].num_subgoals
        self.pub_obs = node.create_publisher(wire.IMAGE, wire.OBSERVATION, wire.STEP_QOS)
        self.pub_images = node.create_publisher(wire.IMAGE, wire.SUBGOAL_IMAGES, wire.STEP_QOS)
        self.pub_step = node.create_publisher(wire.FLOATS, wire.ENV_STEP, wire.STEP_QOS)
        self.pub_pose = node.create_publisher(wire.POSE_STAMPED, wire.POSE) if n == 1 else \
            node.create_publisher(wire.POSE_ARRAY, wire.POSES)
        self.pub_clock = node.create_publisher(wire.CLOCK_TYPE, wire.CLOCK) if params["publish_clock"] else None
        node.create_subscription(wire.INTS, wire.ACTION, self._on_action, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.CREDIT, self._on_credit, LATCHED_QOS)
        node.create_timer(min(0.5, params["action_timeout"]), self._watchdog)
        self.credit = 0  # the learner lets this env take steps while self.steps < credit
        self.steps = 0  # env steps taken, all environments together
        self.finished_episodes = 0
        self.key = 0
        self.pending_actions: np.ndarray | None = None
        self.action_time = 0.0  # wall clock when pending_actions arrived (step_log)
        self.finished = False
        self.step_log = open(params["step_log"], "a", buffering=1) if params["step_log"] else None
        self.rejected_actions = Throttle(node.logger, f"rejected a message on {self._topic(wire.ACTION)}")
        self.rejected_credit = Throttle(node.logger, f"rejected a message on {self._topic(wire.CREDIT)}")
        self.obs = np.stack([env.reset(seed=params["seed"] + i)[0] for i, env in enumerate(self.envs)])
        self.episode = np.zeros(n, np.int64)  # each environment's episode index
        self.records = [self._first_record(i) for i in range(n)]  # each environment's env_step fields
        self._new_key()
        self._publish()

    # -- publishing ------------------------------------------------------------------------
    def _first_record(self, i: int) -> dict:
        """Environment ``i``'s ``env_step`` fields at its episode's first observation (t = 0)."""
        record = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        record.update(prev_key=0, env_steps=self.steps, episode=int(self.episode[i]), at_subgoal=NO_SUBGOAL,
                      decision_point=1)
        return record

    def _new_key(self) -> None:
        self.key += self.period_ns
        for record in self.records:
            record["key"] = self.key
        self.published_at = time.monotonic()

    def _publish(self) -> None:
        node, key, frame = self.node, self.key, self.params["frame_id"]
        # env_step first: the critic needs only it, and the others wait for the critic
        self.pub_step.publish(wire.make_records(node, wire.FLOATS, wire.STEP_FIELDS,
                                                [[r[f] for f in wire.STEP_FIELDS] for r in self.records]))
        self.pub_obs.publish(wire.make_image(node, key, self.obs, frame))
        if any(r["decision_point"] for r in self.records):
            images = np.stack([np.concatenate([env.subgoal_images(np.array([g]))[0] for g in range(self.num_subgoals)])
                               for env in self.envs])
            self.pub_images.publish(wire.make_image(node, key, images, frame))
        if self.pub_clock is not None:
            self.pub_clock.publish(node.msg(wire.CLOCK_TYPE)(clock=wire.make_time(node, key)))
        poses = [self._pose_xy(env) for env in self.envs]
        self.pub_pose.publish(wire.make_pose(node, key, frame, *poses[0]) if self.num_envs == 1 else
                              wire.make_poses(node, key, frame, poses))

    def _pose_xy(self, env) -> tuple[float, float]:
        """Agent position for ``pose``: grid (column, row) in cells; Montezuma RAM (x, y) in pixels."""
        a, b = (float(v) for v in env.agent_pos[0])
        return (a, b) if self.params["env"] in MONTEZUMA_IDS else (b, a)

    # -- stepping ----------------------------------------------------------------------------
    def _on_action(self, msg) -> None:
        try:
            key, actions = wire.read_actions(msg, self.num_actions, self.num_envs)
            for i, record in enumerate(self.records):
                if actions[i] < 0 and not done(record):
                    raise wire.ProtocolError(f"no action (-1) for environment {i}, whose episode goes on")
        except wire.ProtocolError as exc:
            self.rejected_actions.warn(exc)
            return
        if key != self.key or self.pending_actions is not None:
            return  # a stale or repeated reply (e.g. to a re-published step)
        self.pending_actions = actions
        self.action_time = time.time()  # wall clock, for the step_log row
        self._step_if_allowed()

    def _on_credit(self, msg) -> None:
        try:
            credit = wire.read_record(msg, wire.CREDIT_FIELDS)
        except wire.ProtocolError as exc:
            self.rejected_credit.warn(exc)
            return
        self.credit = int(credit["credit_steps"])
        self._step_if_allowed()

    def _step_if_allowed(self) -> None:
        if self.pending_actions is None or self.finished:
            return
        if self.params["wait_for_learner"] and self.steps >= self.credit:
            return
        actions, self.pending_actions = self.pending_actions, None
        self._advance(actions)

    def _advance(self, actions: np.ndarray) -> None:
        """One step of the batch: an environment whose episode ended at the last key starts
        a new one (t = 0), every other one takes its action. Then publish the new key, and
        if every episode has ended, start new ones right away (nobody acts on such a step).

        The environments are stepped one by one (each a batch of one): in a batch some
        start new episodes while the others step, which the vectorised step does not do."""
        prev_key = self.key
        log_rows = []
        for i, env in enumerate(self.envs):
            if done(self.records[i]):
                self.episode[i] += 1
                self.obs[i] = env.reset_where(np.ones(1, bool))[0]
                self.records[i] = self._first_record(i)
                continue
            before = wire.obs_digest(self.obs[i]) if self.step_log is not None else ""
            step = env.step(actions[i:i + 1])
            self.steps += 1
            self.obs[i] = step.obs[0]
            record = self.records[i]
            self.records[i] = {"prev_key": prev_key, "episode": int(self.episode[i]), "t": record["t"] + 1,
                               "action": int(actions[i]), **wire.step_outcome(step, 0)}
            self.finished_episodes += done(self.records[i])
            log_rows.append((i, before))
        for record in self.records:
            record["env_steps"] = self.steps
        self._new_key()
        if self.step_log is not None:
            for i, before in log_rows:
                self.step_log.write(json.dumps({**self.records[i], "env": i, "next_obs": wire.obs_digest(self.obs[i]),
                                                "obs": before, "action_time": self.action_time,
                                                "wall_time": time.time()}) + "\n")
        self._publish()
        max_episodes = self.params["max_episodes"]
        if max_episodes and self.finished_episodes >= max_episodes:
            self.node.logger.info("finished %d episodes (%d steps)", self.finished_episodes, self.steps)
            self.finished = True
        elif all(done(record) for record in self.records):
            self._advance(np.full(self.num_envs, -1))

    def _topic(self, name: str) -> str:
        return self.node.resolve_topic(name)

    def _watchdog(self) -> None:
        waited = time.monotonic() - self.published_at
        if not self.finished and not self.steps and self.pending_actions is None:
            self._publish()  # starting up: peers may still be discovering us
        if self.finished or waited < self.params["action_timeout"]:
            return
        where = f"step t={int(self.records[0]['t'])} of episode {int(self.episode[0])}" if self.num_envs == 1 else \
            f"step key {self.key} of {self.num_envs} environments"
        if self.pending_actions is not None:
            self.node.logger.warning("%s waits for the learner: %d steps taken, credit %d (is the learner running? "
                                     "topic %s); re-publishing the step", where, self.steps, self.credit,
                                     self._topic(wire.CREDIT))
        else:
            self.node.logger.warning("no action for %s after %.1f s on %s (is the sub_controller running?); "
                                     "re-publishing the step", where, waited, self._topic(wire.ACTION))
        self._publish()  # a (re)started peer learns where the loop is
        self.published_at = time.monotonic()

    def close(self) -> None:
        if self.step_log is not None:
            self.step_log.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: EnvironmentNode(mw), argv)


if __name__ == "__main__":
    raise SystemExit(main())
