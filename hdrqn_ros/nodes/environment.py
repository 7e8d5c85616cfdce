"""``environment`` node: one simulated domain (or ``num_envs`` of them as a batch), stepped
in lock-step with the controllers.

For every step key it publishes ``observation`` (rgb8 Image), ``env_step`` (what the last
action did), ``pose`` (agent cell, PoseStamped; a batch: ``poses``, PoseArray) and
``/clock`` (sim time = key), and at decision points ``subgoal_images``. It steps when the
``action`` for the current key arrives and, with ``wait_for_learner``, only while the
learner's ``learner_credit`` allows. A missing peer is logged every ``action_timeout``
seconds (wall time) and the current step is re-published, so a controller that (re)joins
late picks the loop up again.
"""
from __future__ import annotations

import json
import time

import numpy as np
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Int64MultiArray

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.registration import MONTEZUMA_IDS, make_batch
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, NUM_ENVS, env_kwargs
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import Param, declare_parameters, value_of
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS, STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import done
from hdrqn_ros.throttle import Throttle

PARAMETERS = {
    **ENV_PARAMETERS, **NUM_ENVS, **MAX_MESSAGE_BYTES,
    "step_period": Param(0.01, "simulated seconds per step (the step key's increment)", positive=True),
    "frame_id": Param("hdrqn_map", "header.frame_id of observation, subgoal_images and pose"),
    "action_timeout": Param(5.0, "seconds without an action before a warning and a re-published step", live=True,
                            positive=True),
    "wait_for_learner": Param(False, "step only while the learner's credit allows (the training graph)"),
    "max_episodes": Param(0, "stop after this many episodes, all environments together (0: never)", live=True,
                          low=0, high=2**31),
    "step_log": Param("", "append every step to this JSON-lines file ('': off)"),
    "publish_clock": Param(True, "publish /clock (one group only: there is one sim clock)"),
}
"""``num_envs`` > 1: one message per topic and step holds every environment's (see
``docs/topics.md``; every node of the group needs the same value). ``step_log`` rows also
have ``wall_time``, the wall clock (``time.time()``) just before the step is published, and
``action_time``, when the action that made the step arrived: the ground truth that learner
transition logs are checked against, and latencies (``benchmarks/bench_load.py``)."""


class EnvironmentNode(Node):
    """The simulator of one environment group."""

    def __init__(self, **kwargs):
        super().__init__("environment", **kwargs)
        params = declare_parameters(self, PARAMETERS)
        logger = python_logger(self)
        self.env_id, self.frame_id = params["env"], params["frame_id"]
        self.wait_for_learner = params["wait_for_learner"]
        self.period_ns = int(round(params["step_period"] * 1e9))
        n = self.num_envs = params["num_envs"]
        view = env_kwargs(params["env"], params["view"])
        self.envs = [make_batch(params["env"], 1, **view) for _ in range(n)]  # stepped one by one: see _advance
        self.num_actions, self.num_subgoals = self.envs[0].num_actions, self.envs[0].num_subgoals
        self.pub_obs = self.create_publisher(Image, wire.OBSERVATION, STEP_QOS)
        self.pub_images = self.create_publisher(Image, wire.SUBGOAL_IMAGES, STEP_QOS)
        self.pub_step = self.create_publisher(Float64MultiArray, wire.ENV_STEP, STEP_QOS)
        self.pub_pose = self.create_publisher(PoseStamped, wire.POSE, DEFAULT_QOS) if n == 1 else \
            self.create_publisher(PoseArray, wire.POSES, DEFAULT_QOS)
        self.pub_clock = self.create_publisher(ClockMsg, wire.CLOCK, DEFAULT_QOS) if params["publish_clock"] else None
        limit = params["max_message_bytes"]
        bounded_subscription(self, Int64MultiArray, wire.ACTION, self._on_action, STEP_QOS, limit, logger)
        bounded_subscription(self, Float64MultiArray, wire.CREDIT, self._on_credit, LATCHED_QOS, limit, logger)
        # wall time: with use_sim_time the node's clock is the /clock it publishes, which stops with the loop
        self.create_timer(min(0.5, params["action_timeout"]), self._watchdog,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.credit = 0  # the learner lets this env take steps while self.steps < credit
        self.steps = 0  # env steps taken, all environments together
        self.finished_episodes = 0
        self.key = 0
        self.pending_actions: np.ndarray | None = None
        self.action_time = 0.0  # wall clock when pending_actions arrived (step_log)
        self.finished = False
        self.step_log = open(params["step_log"], "a", buffering=1) if params["step_log"] else None
        self.rejected_actions = Throttle(logger, f"rejected a message on {self.resolve_topic_name(wire.ACTION)}")
        self.rejected_credit = Throttle(logger, f"rejected a message on {self.resolve_topic_name(wire.CREDIT)}")
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
        key, frame = self.key, self.frame_id
        # env_step first: the critic needs only it, and the others wait for the critic
        self.pub_step.publish(wire.make_records(ROS_MESSAGES, wire.FLOATS, wire.STEP_FIELDS,
                                                [[r[f] for f in wire.STEP_FIELDS] for r in self.records]))
        self.pub_obs.publish(wire.make_image(ROS_MESSAGES, key, self.obs, frame))
        if any(r["decision_point"] for r in self.records):
            images = np.stack([np.concatenate([env.subgoal_images(np.array([g]))[0] for g in range(self.num_subgoals)])
                               for env in self.envs])
            self.pub_images.publish(wire.make_image(ROS_MESSAGES, key, images, frame))
        if self.pub_clock is not None:
            self.pub_clock.publish(ClockMsg(clock=wire.make_time(ROS_MESSAGES, key)))
        poses = [self._pose_xy(env) for env in self.envs]
        self.pub_pose.publish(wire.make_pose(ROS_MESSAGES, key, frame, *poses[0]) if self.num_envs == 1 else
                              wire.make_poses(ROS_MESSAGES, key, frame, poses))

    def _pose_xy(self, env) -> tuple[float, float]:
        """Agent position for ``pose``: grid (column, row) in cells; Montezuma RAM (x, y) in pixels."""
        a, b = (float(v) for v in env.agent_pos[0])
        return (a, b) if self.env_id in MONTEZUMA_IDS else (b, a)

    # -- stepping ----------------------------------------------------------------------------
    def _on_action(self, msg: Int64MultiArray) -> None:
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

    def _on_credit(self, msg: Float64MultiArray) -> None:
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
        if self.wait_for_learner and self.steps >= self.credit:
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
        max_episodes = value_of(self, "max_episodes")
        if max_episodes and self.finished_episodes >= max_episodes:
            self.get_logger().info(f"finished {self.finished_episodes} episodes ({self.steps} steps)")
            self.finished = True
        elif all(done(record) for record in self.records):
            self._advance(np.full(self.num_envs, -1))

    def _watchdog(self) -> None:
        """Every half second (wall time): re-publish while starting up; warn and re-publish
        when no action came for ``action_timeout`` seconds."""
        waited = time.monotonic() - self.published_at
        if not self.finished and not self.steps and self.pending_actions is None:
            self._publish()  # starting up: peers may still be discovering us
        if self.finished or waited < value_of(self, "action_timeout"):
            return
        where = f"step t={int(self.records[0]['t'])} of episode {int(self.episode[0])}" if self.num_envs == 1 else \
            f"step key {self.key} of {self.num_envs} environments"
        if self.pending_actions is not None:
            self.get_logger().warning(f"{where} waits for the learner: {self.steps} steps taken, credit {self.credit} "
                                      f"(is the learner running? topic {self.resolve_topic_name(wire.CREDIT)}); "
                                      f"re-publishing the step")
        else:
            self.get_logger().warning(f"no action for {where} after {waited:.1f} s on "
                                      f"{self.resolve_topic_name(wire.ACTION)} (is the sub_controller running?); "
                                      f"re-publishing the step")
        self._publish()  # a (re)started peer learns where the loop is
        self.published_at = time.monotonic()

    def close(self) -> None:
        """Close the step log."""
        if self.step_log is not None:
            self.step_log.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(EnvironmentNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
