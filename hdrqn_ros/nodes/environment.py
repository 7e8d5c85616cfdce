"""``environment`` node: one simulated domain, stepped in lock-step with the controllers.

For every step key it publishes ``observation`` (rgb8 Image), ``env_step`` (what the last
action did), ``pose`` (agent cell, PoseStamped) and ``/clock`` (sim time = key), and at
decision points ``subgoal_images``. It steps when the ``action`` for the current key
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
from hdrqn_ros.nodes.common import ENV_DEFAULTS, NodeConfigError, env_kwargs, run_node
from hdrqn_ros.throttle import Throttle

PARAMETERS = {**ENV_DEFAULTS, "step_period": 0.01, "frame_id": "hdrqn_map", "action_timeout": 5.0,
              "wait_for_learner": False, "max_episodes": 0, "step_log": "", "publish_clock": True}
"""``step_period``: simulated seconds per step (the key increment); ``max_episodes``: stop
after this many episodes (0: run until stopped); ``step_log``: append every step to this
JSON-lines file (the ground truth that learner transition logs are checked against; each
row also has ``wall_time``, the wall clock (``time.time()``) just before the step is
published, and ``action_time``, when the action that made the step arrived, for latency
measurements: ``benchmarks/bench_load.py``); ``publish_clock``: publish ``/clock`` (turn
off for all but one group: there is one sim clock)."""


class EnvironmentNode:
    def __init__(self, mw: Middleware):
        node = self.node = mw.create_node("environment")
        params = self.params = node.declare_parameters(PARAMETERS)
        self.period_ns = int(round(params["step_period"] * 1e9))
        if self.period_ns <= 0 or params["action_timeout"] <= 0:
            raise NodeConfigError("step_period and action_timeout must be > 0")
        self.batch = make_batch(params["env"], 1, **env_kwargs(params["env"], params["view"]))
        self.pub_obs = node.create_publisher(wire.IMAGE, wire.OBSERVATION, wire.STEP_QOS)
        self.pub_images = node.create_publisher(wire.IMAGE, wire.SUBGOAL_IMAGES, wire.STEP_QOS)
        self.pub_step = node.create_publisher(wire.FLOATS, wire.ENV_STEP, wire.STEP_QOS)
        self.pub_pose = node.create_publisher(wire.POSE_STAMPED, wire.POSE)
        self.pub_clock = node.create_publisher(wire.CLOCK_TYPE, wire.CLOCK) if params["publish_clock"] else None
        node.create_subscription(wire.INTS, wire.ACTION, self._on_action, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.CREDIT, self._on_credit, LATCHED_QOS)
        node.create_timer(min(0.5, params["action_timeout"]), self._watchdog)
        self.credit = 0  # the learner lets this env take steps while self.steps < credit
        self.steps = 0
        self.episode = 0
        self.key = 0
        self.pending_action: int | None = None
        self.action_time = 0.0  # wall clock when pending_action arrived (step_log)
        self.finished = False
        self.step_log = open(params["step_log"], "a", buffering=1) if params["step_log"] else None
        self.rejected_actions = Throttle(node.logger, f"rejected a message on {self._topic(wire.ACTION)}")
        self.rejected_credit = Throttle(node.logger, f"rejected a message on {self._topic(wire.CREDIT)}")
        self.obs = self.batch.reset(seed=params["seed"])[0]
        self._begin_episode()

    # -- publishing ------------------------------------------------------------------------
    def _begin_episode(self) -> None:
        self.t = 0
        self.step_record = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        self.step_record.update(prev_key=0, env_steps=self.steps, episode=self.episode, at_subgoal=NO_SUBGOAL,
                                decision_point=1)
        self._new_key()
        self._publish()

    def _new_key(self) -> None:
        self.key += self.period_ns
        self.step_record["key"] = self.key
        self.published_at = time.monotonic()

    def _publish(self) -> None:
        node, key, frame = self.node, self.key, self.params["frame_id"]
        # env_step first: the critic needs only it, and the others wait for the critic
        self.pub_step.publish(wire.make_record(node, wire.FLOATS, wire.STEP_FIELDS,
                                               [self.step_record[f] for f in wire.STEP_FIELDS]))
        self.pub_obs.publish(wire.make_image(node, key, self.obs, frame))
        if self.step_record["decision_point"]:
            images = [self.batch.subgoal_images(np.array([g]))[0] for g in range(self.batch.num_subgoals)]
            self.pub_images.publish(wire.make_image(node, key, np.concatenate(images), frame))
        if self.pub_clock is not None:
            self.pub_clock.publish(node.msg(wire.CLOCK_TYPE)(clock=wire.make_time(node, key)))
        self.pub_pose.publish(wire.make_pose(node, key, frame, *self._pose_xy()))

    def _pose_xy(self) -> tuple[float, float]:
        """Agent position for ``pose``: grid (column, row) in cells; Montezuma RAM (x, y) in pixels."""
        a, b = (float(v) for v in self.batch.agent_pos[0])
        return (a, b) if self.params["env"] in MONTEZUMA_IDS else (b, a)

    # -- stepping ----------------------------------------------------------------------------
    def _on_action(self, msg) -> None:
        try:
            record = wire.read_record(msg, wire.ACTION_FIELDS, np.int64)
            action = wire.check_index(record["action"], self.batch.num_actions, "action")
        except wire.ProtocolError as exc:
            self.rejected_actions.warn(exc)
            return
        if record["key"] != self.key or self.pending_action is not None:
            return  # a stale or repeated reply (e.g. to a re-published step)
        self.pending_action = action
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
        if self.pending_action is None or self.finished:
            return
        if self.params["wait_for_learner"] and self.steps >= self.credit:
            return
        action, self.pending_action = self.pending_action, None
        prev_key = self.key
        self.obs_digest_before = wire.obs_digest(self.obs) if self.step_log is not None else ""
        step = self.batch.step(np.array([action]))
        self.steps += 1
        self.t += 1
        self.obs = step.obs[0]
        self.step_record = {"prev_key": prev_key, "env_steps": self.steps, "episode": self.episode, "t": self.t,
                            "action": action, **wire.step_outcome(step, 0)}
        self._new_key()
        if self.step_log is not None:
            self.step_log.write(json.dumps({**self.step_record, "key": self.key, "next_obs": wire.obs_digest(self.obs),
                                            "obs": self.obs_digest_before, "action_time": self.action_time,
                                            "wall_time": time.time()}) + "\n")
        self._publish()
        if step.done[0]:
            self.episode += 1
            max_episodes = self.params["max_episodes"]
            if max_episodes and self.episode >= max_episodes:
                self.node.logger.info("finished %d episodes (%d steps)", self.episode, self.steps)
                self.finished = True
                return
            self.obs = self.batch.reset_where(np.ones(1, bool))[0]
            self._begin_episode()

    def _topic(self, name: str) -> str:
        return self.node.resolve_topic(name)

    def _watchdog(self) -> None:
        waited = time.monotonic() - self.published_at
        if not self.finished and not self.steps and self.pending_action is None:
            self._publish()  # starting up: peers may still be discovering us
        if self.finished or waited < self.params["action_timeout"]:
            return
        if self.pending_action is not None:
            self.node.logger.warning("step t=%d of episode %d waits for the learner: %d steps taken, credit %d "
                                     "(is the learner running? topic %s); re-publishing the step", self.t,
                                     self.episode, self.steps, self.credit, self._topic(wire.CREDIT))
        else:
            self.node.logger.warning("no action for step t=%d of episode %d after %.1f s on %s (is the "
                                     "sub_controller running?); re-publishing the step", self.t, self.episode,
                                     waited, self._topic(wire.ACTION))
        self._publish()  # a (re)started peer learns where the loop is
        self.published_at = time.monotonic()

    def close(self) -> None:
        if self.step_log is not None:
            self.step_log.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: EnvironmentNode(mw), argv)


if __name__ == "__main__":
    raise SystemExit(main())
