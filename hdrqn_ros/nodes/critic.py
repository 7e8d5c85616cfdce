"""``critic`` node: the internal critic (thesis 3.6) between environment and controllers.

For each ``env_step`` (key K, the step taken on observation ``prev_key``) it evaluates the
domain's :class:`~hdrqn_ros.envs.critic.InternalCritic` with the current option's subgoal and
publishes ``critic`` (intrinsic reward, subgoal reached, option done). At an episode's
first step it publishes ``option_done = 1`` with no reward. The meta-controller publishes a
``subgoal`` only when an option starts, so after announcing ``option_done`` the critic
waits for the subgoal chosen at that key. A critic that (re)starts mid-option does not
know the option's subgoal: it gives no intrinsic reward until the next step where an
option can start (a decision point), and ends the option there. With ``num_envs`` > 1 it
judges every environment of the batch and publishes one ``critic`` record per environment.
"""
from __future__ import annotations

import numpy as np
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray, Int64MultiArray

from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, NUM_ENVS, env_kwargs
from hdrqn_ros.nodes.navigation_outcomes import NavigationOutcomes
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import Param, declare_parameters
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import StepFollower, done

PARAMETERS = {**ENV_PARAMETERS, **NUM_ENVS, **MAX_MESSAGE_BYTES, "option_timeout": Param(
    0.0, "seconds (of step keys) after which an option not yet done ends without reward (0: never)", live=True,
    low=0.0, high=1e9),
    "navigation_outcome": Param(False, "end an option at the step after the navigator's result for it comes on "
                                       "navigation_outcome (meta_controller navigation: action)")}
"""``option_timeout``: an option not done this many seconds (of step keys, i.e. ROS time on a
robot) after it started ends there (0: never; a robot whose navigator cannot reach a place).
A robot setting: the simulator's ``environment`` node sends ``subgoal_images`` only at
decision points, which an option cut short elsewhere would wait for."""


class CriticNode(Node, StepFollower):
    """The internal critic of one environment group."""

    def __init__(self, **kwargs):
        Node.__init__(self, "critic", **kwargs)
        params = declare_parameters(self, PARAMETERS, apply=self._apply)
        StepFollower.__init__(self, logger=python_logger(self), num_envs=params["num_envs"])
        self.timeout_ns = int(round(params["option_timeout"] * 1e9))
        probe = make_batch(params["env"], 1, **env_kwargs(params["env"], params["view"]))
        self.critic, self.num_subgoals = probe.critic(), probe.num_subgoals
        self.pub = self.create_publisher(Float64MultiArray, wire.CRITIC, STEP_QOS)
        limit = params["max_message_bytes"]
        bounded_subscription(self, Float64MultiArray, wire.ENV_STEP, self.on_env_step, STEP_QOS, limit, self.logger)
        bounded_subscription(self, Int64MultiArray, wire.SUBGOAL, self._on_subgoal, STEP_QOS, limit, self.logger)
        self.navigation = NavigationOutcomes(self, limit, self.logger) if params["navigation_outcome"] else None
        self.create_timer(1.0, self.check_stall, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.option_subgoal = np.full(self.num_envs, -1)  # each environment's option's subgoal (-1: unknown)
        self.choice_at = np.zeros(self.num_envs, np.int64)  # key at which we announced option_done

    def _apply(self, name: str, value) -> None:
        if name == "option_timeout":
            self.timeout_ns = int(round(value * 1e9))

    def _on_subgoal(self, msg: Int64MultiArray) -> None:
        chosen = self.decode(wire.SUBGOAL, lambda: wire.read_subgoals(msg, self.num_subgoals, self.num_envs))
        if chosen is not None:
            self.put(wire.SUBGOAL, *chosen)

    def ready(self, rows: list[dict]) -> bool:
        return all(row["t"] == 0 or int(row["prev_key"]) != self.choice_at[i] or
                   self.inbox.has(wire.SUBGOAL, int(row["prev_key"])) for i, row in enumerate(rows))

    def process(self, rows: list[dict]) -> list:
        key = int(rows[0]["key"])
        for i, row in enumerate(rows):
            prev = int(row["prev_key"])
            if row["t"] > 0 and prev == self.choice_at[i]:
                self.option_subgoal[i] = self.inbox.get(wire.SUBGOAL, prev)[i]
        result = self.critic.evaluate(wire.step_batch(rows), np.maximum(self.option_subgoal, 0))
        values = []
        for i, row in enumerate(rows):
            if row["t"] == 0:
                verdict = [key, 0.0, 0.0, 1.0, -1.0]
            elif self.option_subgoal[i] < 0:  # (re)started mid-option: end it where a new one can start
                verdict = [key, 0.0, 0.0, float(row["decision_point"] or done(row)), -1.0]
            else:
                verdict = [key, result.intrinsic[i], result.reached[i], result.option_done[i], self.option_subgoal[i]]
                if self.timeout_ns and key - self.choice_at[i] >= self.timeout_ns:  # ran out of time
                    verdict[3] = 1.0
                if self.navigation is not None and self.navigation.ended(self.choice_at[i]):  # the navigator's result
                    verdict[3] = 1.0
            if verdict[3] and not done(row):
                self.choice_at[i], self.option_subgoal[i] = key, -1
            values.append(verdict)
        return [(self.pub, wire.make_records(ROS_MESSAGES, wire.FLOATS, wire.CRITIC_FIELDS, values))]

    def reset(self) -> None:
        super().reset()
        self.option_subgoal[:], self.choice_at[:] = -1, 0
        if self.navigation is not None:
            self.navigation.clear()


def main(argv: list[str] | None = None) -> int:
    return run_node(CriticNode, argv)


if __name__ == "__main__":
    raise SystemExit(main())
