"""An exported policy as the agent the simulator plays with (:func:`hdrqn_ros.training.learner.play`).

``play(agent, settings, ...)`` reads of its agent ``sub``, ``meta`` (``None`` for a flat
agent), ``spec`` and ``sub_input``, and of its config ``env``, ``env_kwargs`` and
``meta_state``: :class:`OnnxAgent` and :class:`PlaySettings` give them from an
:class:`~hdrqn_ros.deploy.onnx_policy.OnnxPolicy`, so an exported policy plays the
simulator's episodes as its checkpoint does (epsilon-greedy exploration is the rollout's,
any epsilon works). Imports no torch and no ROS.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrqn_ros.agents.specs import ALGO_SPECS, AlgoSpec
from hdrqn_ros.deploy.errors import PolicyError
from hdrqn_ros.deploy.onnx_policy import POLICY_FILE, LSTMState, OnnxPolicy

__all__ = ["OnnxController", "OnnxAgent", "PlaySettings"]


@dataclass(frozen=True)
class PlaySettings:
    """What ``play`` reads of a training config, from ``policy.json``."""

    algo: str
    env: str
    env_kwargs: dict
    meta_state: str  # "c" or "h": the sub LSTM state the hDRQNv2 meta-controller reads


class OnnxController:
    """One controller (``role``) of a policy: ``act(x (B, ...), state) -> (q (B, n), state)``
    and ``initial_state(B)``, as a torch controller acts; states are float32 numpy arrays."""

    def __init__(self, policy: OnnxPolicy, role: str):
        self.policy, self.role = policy, role

    def act(self, x: np.ndarray, state: LSTMState | None) -> tuple[np.ndarray, LSTMState | None]:
        return self.policy.act(self.role, x, state)

    def initial_state(self, batch_size: int) -> LSTMState | None:
        return self.policy.initial_state(self.role, batch_size)


class OnnxAgent:
    """The controllers of ``policy`` with the surface of :class:`~hdrqn_ros.agents.algorithms.Agent`
    that acting uses; ``meta`` is ``None`` for the flat algorithms."""

    def __init__(self, policy: OnnxPolicy):
        self.policy = policy
        self.spec: AlgoSpec = ALGO_SPECS[policy.algo]
        self.sub = OnnxController(policy, "sub")
        self.meta = OnnxController(policy, "meta") if policy.hierarchical else None

    def sub_input(self, obs: np.ndarray, subgoal_images: np.ndarray) -> np.ndarray:
        """(N, 44, 44, 3) observations -> the sub-controller's (N, 44, 44, 3 or 6) input."""
        return self.policy.sub_input(obs, subgoal_images)

    def settings(self, **env_kwargs) -> PlaySettings:
        """The policy's env and options, ``env_kwargs`` over them (e.g. ``obstacles=False``);
        :class:`PolicyError` when ``policy.json`` names no env."""
        if not self.policy.env:
            raise PolicyError(f"{self.policy.directory / POLICY_FILE} names no env to play the policy in")
        return PlaySettings(algo=self.policy.algo, env=self.policy.env,
                            env_kwargs={**self.policy.env_kwargs, **env_kwargs}, meta_state=self.policy.meta_state)
