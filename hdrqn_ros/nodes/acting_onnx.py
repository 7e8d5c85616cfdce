"""A controller node's acting network from an exported policy directory (``policy``
parameter, ``hdrqn export``): numpy and onnxruntime only, so the node process never
imports torch. Frozen: the learner's weights topic is not subscribed. Imported only when
a node is given ``policy`` (:func:`hdrqn_ros.nodes.acting.make_acting_network`)."""
from __future__ import annotations

import sys

import numpy as np
from rclpy.node import Node

from hdrqn_ros.deploy.onnx_policy import OnnxPolicy
from hdrqn_ros.nodes.acting_network import ActingNetwork
from hdrqn_ros.nodes.graph_parameters import env_kwargs
from hdrqn_ros.nodes.parameters import NodeConfigError
from hdrqn_ros.protocol import wire


class OnnxActingNetwork(ActingNetwork):
    """The ``role`` model of ``OnnxPolicy.load(params["policy"])`` (a :class:`PolicyError`
    for a bad directory). The policy must fit the node: its algo is the node's ``algo``,
    its ``num_actions``/``num_subgoals`` are the domain's, and for hDRQNv2 its
    ``meta_state`` is the node's; else :class:`NodeConfigError` naming the mismatch. LSTM
    states are (h, c) pairs of float32 (1, 256) numpy arrays, new ones every step."""

    def __init__(self, node: Node, role: str, params: dict, default_epsilon: float,
                 num_actions: int, num_subgoals: int):
        super().__init__(node, role, params, default_epsilon, num_actions, num_subgoals)
        directory = params["policy"]
        self.policy = policy = OnnxPolicy.load(directory)
        mismatches = []
        if policy.algo != params["algo"]:
            mismatches.append(f"algo is {policy.algo}, the node's algo is {params['algo']}")
        if (policy.num_actions, policy.num_subgoals) != (num_actions, num_subgoals):
            mismatches.append(f"num_actions/num_subgoals are {policy.num_actions}/{policy.num_subgoals}, "
                              f"{params['env']} has {num_actions}/{num_subgoals}")
        if params["algo"] == policy.algo == "hdrqn-v2" and policy.meta_state != params["meta_state"]:
            mismatches.append(f"meta_state is {policy.meta_state!r}, the node's meta_state is "
                              f"{params['meta_state']!r}")
        if mismatches:
            raise NodeConfigError(f"policy {directory} does not fit this node: {'; '.join(mismatches)}")
        if role not in policy.roles:
            raise NodeConfigError(f"policy {directory} has no {role} controller (roles: {list(policy.roles)})")
        trained_view = policy.env_kwargs.get("view")  # absent: the env's default
        logger = node.get_logger()
        if (policy.env and policy.env != params["env"]) or \
                (trained_view is not None and env_kwargs(params["env"], params["view"]).get("view") != trained_view):
            logger.warning(f"policy {directory} was exported from a run on {policy.env} {policy.env_kwargs}; "
                           f"this node acts on {params['env']} view {params['view']}")
        logger.info(f"acting with the exported {role} policy {directory} ({policy.algo}, onnxruntime; "
                    f"torch imported: {'torch' in sys.modules})")
        logger.info(f"an exported policy is frozen: not subscribing to the learner's {wire.WEIGHTS[role]}")

    def act(self, x: np.ndarray, state):
        return self.policy.act(self.role, x, state)

    def initial_state(self, batch_size: int):
        return self.policy.initial_state(self.role, batch_size)
