"""``critic`` node: the internal critic (thesis 3.6) between environment and controllers.

For each ``env_step`` (key K, the step taken on observation ``prev_key``) it evaluates the
domain's :class:`~hdrqn_ros.critic.InternalCritic` with the current option's subgoal and
publishes ``critic`` (intrinsic reward, subgoal reached, option done). At an episode's
first step it publishes ``option_done = 1`` with no reward. The meta-controller publishes a
``subgoal`` only when an option starts, so after announcing ``option_done`` the critic
waits for the subgoal chosen at that key. A critic that (re)starts mid-option does not
know the option's subgoal: it gives no intrinsic reward until the next step where an
option can start (a decision point), and ends the option there.
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.middleware import Middleware
from hdrqn_ros.protocol import wire
from hdrqn_ros.nodes.common import ENV_DEFAULTS, env_kwargs, run_node
from hdrqn_ros.protocol.follower import StepFollower, done


class CriticNode(StepFollower):
    def __init__(self, mw: Middleware):
        node = mw.create_node("critic")
        super().__init__(node)
        params = node.declare_parameters(dict(ENV_DEFAULTS))
        probe = make_batch(params["env"], 1, **env_kwargs(params["env"], params["view"]))
        self.critic, self.num_subgoals = probe.critic(), probe.num_subgoals
        self.pub = node.create_publisher(wire.FLOATS, wire.CRITIC, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.ENV_STEP, self.on_env_step, wire.STEP_QOS)
        node.create_subscription(wire.INTS, wire.SUBGOAL, self._on_subgoal, wire.STEP_QOS)
        self.option_subgoal = -1  # the current option's subgoal (-1: unknown)
        self.choice_at = 0  # key at which we announced option_done: its subgoal is the next option's

    def _on_subgoal(self, msg) -> None:
        record = self.decode(wire.SUBGOAL, lambda: wire.read_record(msg, wire.SUBGOAL_FIELDS, np.int64))
        if record is not None and self.decode(
                wire.SUBGOAL, lambda: wire.check_index(record["subgoal"], self.num_subgoals, "subgoal")) is not None:
            self.put(wire.SUBGOAL, record["key"], record["subgoal"])

    def ready(self, step: dict) -> bool:
        prev = int(step["prev_key"])
        return step["t"] == 0 or prev != self.choice_at or self.inbox.has(wire.SUBGOAL, prev)

    def process(self, step: dict) -> list:
        key, prev = int(step["key"]), int(step["prev_key"])
        if step["t"] > 0 and prev == self.choice_at:
            self.option_subgoal = int(self.inbox.get(wire.SUBGOAL, prev))
        if step["t"] == 0:
            values = [key, 0.0, 0.0, 1.0, -1.0]
        elif self.option_subgoal < 0:  # (re)started mid-option: end it where a new one can start
            values = [key, 0.0, 0.0, float(step["decision_point"] or done(step)), -1.0]
        else:
            result = self.critic.evaluate(wire.step_batch(step), np.array([self.option_subgoal]))
            values = [key, result.intrinsic[0], result.reached[0], result.option_done[0], self.option_subgoal]
        if values[3] and not done(step):
            self.choice_at, self.option_subgoal = key, -1
        return [(self.pub, wire.make_record(self.node, wire.FLOATS, wire.CRITIC_FIELDS, values))]

    def reset(self) -> None:
        super().reset()
        self.option_subgoal, self.choice_at = -1, 0


def main(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: CriticNode(mw), argv)


if __name__ == "__main__":
    raise SystemExit(main())
