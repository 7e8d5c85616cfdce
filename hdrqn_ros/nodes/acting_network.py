"""The acting network a controller node acts through, and its exploration (the base of the
torch and the ONNX kinds, :mod:`hdrqn_ros.nodes.acting_torch` and :mod:`hdrqn_ros.nodes.acting_onnx`)."""
from __future__ import annotations

import numpy as np
from rclpy.node import Node


class ActingNetwork:
    """A controller's Q-network for acting in a node, and its exploration (``epsilon``,
    ``rng``): what :class:`~hdrqn_ros.agents.policy.HierarchicalPolicy` calls
    (``act(x, state)``, ``initial_state(batch_size)``). ``role``: ``"sub"`` or ``"meta"``."""

    def __init__(self, node: Node, role: str, params: dict, default_epsilon: float,
                 num_actions: int, num_subgoals: int):
        self.node, self.role = node, role
        self.num_actions, self.num_subgoals = num_actions, num_subgoals
        self.rng = np.random.default_rng(params["seed"] + (7 if role == "meta" else 11))
        self.epsilon = default_epsilon
        self.fixed_epsilon: float | None = None
        self.set_fixed_epsilon(params["epsilon"])

    def set_fixed_epsilon(self, epsilon: float) -> None:
        """``epsilon`` >= 0: explore at this rate from now on; < 0: the learner's schedule again."""
        self.fixed_epsilon = epsilon if epsilon >= 0 else None
        if self.fixed_epsilon is not None:
            self.epsilon = self.fixed_epsilon

    def on_credit(self, credit: dict) -> None:
        """The learner's credit record: its current exploration rate, unless ``epsilon`` is fixed."""
        if self.fixed_epsilon is None:
            self.epsilon = credit["eps_meta" if self.role == "meta" else "eps_sub"]

    def act(self, x: np.ndarray, state):
        """``x`` (B, ...) -> (Q-values (B, n) numpy, new LSTM state)."""
        raise NotImplementedError

    def initial_state(self, batch_size: int):
        """The LSTM state of ``batch_size`` fresh episodes (``None`` for a feed-forward network)."""
        raise NotImplementedError
