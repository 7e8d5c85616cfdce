"""A controller node's lock-step join with the environment node: what the meta- and the
sub-controller both do with each ``env_step`` before they decide."""
from __future__ import annotations

import numpy as np
from rclpy.clock import Clock, ClockType
from std_msgs.msg import Float64MultiArray

from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.nodes.controller_node import ControllerNode
from hdrqn_ros.nodes.qos import STEP_QOS
from hdrqn_ros.nodes.ros_messages import bounded_subscription
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import StepFollower, done


class LockStepController(StepFollower):
    """Follows the environment node's steps for a :class:`ControllerNode` (its ``ros_node``):
    steps are taken only while the node is active, inputs are decoded by the node, and a step
    of another ``num_envs`` ends the node's process (exit code 2). Subclasses subscribe to
    their inputs with :meth:`subscribe` and implement ``ready`` and ``process``."""

    def __init__(self, node: ControllerNode):
        super().__init__(logger=node.logger, num_envs=node.params["num_envs"])
        self.ros_node = node
        self.net, self.policy, self.diagnostics = node.net, node.policy, node.diagnostics
        node.watch.expect(wire.ENV_STEP, "the environment node (environment, or robot_environment on a robot)")
        self.subscribe(Float64MultiArray, wire.ENV_STEP, self._on_env_step)
        node.create_timer(1.0, self.check_stall, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def subscribe(self, msg_type: type, topic: str, callback) -> None:
        """A per-step input (:data:`~hdrqn_ros.nodes.qos.STEP_QOS`, at most ``max_message_bytes``)."""
        node = self.ros_node
        bounded_subscription(node, msg_type, topic, callback, STEP_QOS, node.params["max_message_bytes"], self.logger)

    def decode(self, topic: str, read):
        return self.ros_node.decode(topic, read)

    def resolve_topic_name(self, topic: str) -> str:
        return self.ros_node.resolve_topic_name(topic)

    def problems(self) -> list[str]:
        """Nothing beyond the node's own checks: a stalled step is logged by ``check_stall``."""
        return []

    def _on_env_step(self, msg: Float64MultiArray) -> None:
        if not self.ros_node.active:
            return
        self.ros_node.watch.hear(wire.ENV_STEP)
        self.on_env_step(msg)
        if self.finished:
            self.ros_node.finish(self.exit_code)

    def on_image(self, topic: str, msg, height: int = OBS_SIZE) -> None:
        """(N, height, 44, 3): the environments' images, stacked top to bottom on the wire."""
        got = self.decode(topic, lambda: wire.read_images(msg, height, OBS_SIZE, self.num_envs))
        if got is not None:
            self.put(topic, got[0], got[1])

    def on_critic(self, msg: Float64MultiArray) -> None:
        def read() -> list[dict]:
            verdicts = wire.read_records(msg, wire.CRITIC_FIELDS)
            if len(verdicts) != self.num_envs:
                raise wire.ProtocolError(f"critic holds {len(verdicts)} environment(s)' records, "
                                         f"expected {self.num_envs}")
            return verdicts

        verdicts = self.decode(wire.CRITIC, read)
        if verdicts is not None:
            self.put(wire.CRITIC, verdicts[0]["key"], verdicts)

    def option_starts(self, rows: list[dict]) -> np.ndarray | None:
        """(N,) bool: where the critic ended the option at this step and the episode goes on
        (a new option starts); ``None``: the critic not heard yet."""
        critic = self.inbox.get(wire.CRITIC, int(rows[0]["key"]))
        if critic is None:
            return None
        return np.array([bool(c["option_done"]) and not done(row) for c, row in zip(critic, rows)])

    def reset(self) -> None:
        """Forget every step and input, and start every environment's episode afresh."""
        super().reset()
        self.policy.start_episodes(np.ones(self.num_envs, bool))
