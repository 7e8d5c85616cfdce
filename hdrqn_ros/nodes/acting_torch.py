"""A controller node's torch acting network: random or ``checkpoint`` weights, then the
learner's ``/learner/*_weights`` topic. Imported only when a node acts with torch
(:func:`hdrqn_ros.nodes.acting.make_acting_network`)."""
from __future__ import annotations

import numpy as np
import torch
from rclpy.node import Node
from std_msgs.msg import UInt8MultiArray

from hdrqn_ros.agents.algorithms import make_network
from hdrqn_ros.agents.weights import WeightsError, load_weights
from hdrqn_ros.nodes.acting_network import ActingNetwork
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.qos import LATCHED_QOS
from hdrqn_ros.nodes.ros_messages import bounded_subscription
from hdrqn_ros.protocol import wire
from hdrqn_ros.throttle import Throttle
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint


class TorchActingNetwork(ActingNetwork):
    """Acts under inference mode. At N = 1 its LSTM states (inference tensors) are replaced,
    never changed in place; for a batch they are cloned into normal tensors, which the
    policy updates row by row."""

    def __init__(self, node: Node, role: str, params: dict, default_epsilon: float,
                 num_actions: int, num_subgoals: int):
        super().__init__(node, role, params, default_epsilon, num_actions, num_subgoals)
        torch.set_num_threads(1)
        self.net = make_network(params["algo"], role, num_actions, num_subgoals)
        self.net.eval()
        self.weights_version = -1
        if params["checkpoint"]:
            self._load_checkpoint(params["checkpoint"])
        logger = python_logger(node)
        self.rejected_weights = Throttle(logger, f"rejected {role} weights on {wire.WEIGHTS[role]}")
        bounded_subscription(node, UInt8MultiArray, wire.WEIGHTS[role], self._on_weights, LATCHED_QOS,
                             params["max_message_bytes"], logger)

    def _load_checkpoint(self, path: str) -> None:
        payload = load_checkpoint(path)
        try:
            self.net.load_state_dict(payload["agent"][self.role]["online"])
        except (KeyError, RuntimeError) as exc:
            raise CheckpointError(f"{path} has no {self.role} network for this algo: "
                                  f"{str(exc).splitlines()[0]}") from None
        self.weights_version = 0
        self.node.get_logger().info(f"loaded {self.role} weights from {path}")

    def _on_weights(self, msg: UInt8MultiArray) -> None:
        try:
            version = wire.read_weights_version(msg)
            load_weights(self.net, wire.as_bytes(msg.data))
        except (WeightsError, ValueError) as exc:
            self.rejected_weights.warn(exc)
            return
        if self.weights_version < 0 or version // 100 > self.weights_version // 100:
            self.node.get_logger().info(f"acting with the learner's {self.role} weights of update {version}")
        self.weights_version = version

    def act(self, x: np.ndarray, state):
        with torch.inference_mode():
            q, state = self.net.act(torch.tensor(x), state)  # a copy: x may be read-only
        if state is not None and len(x) > 1:
            state = tuple(part.clone() for part in state)
        return q.numpy(), state

    def initial_state(self, batch_size: int):
        return self.net.initial_state(batch_size)
