"""Which acting network a controller node builds from its parameters.

Imports no torch (nor onnxruntime): :func:`make_acting_network` imports the kind it builds,
torch weights (:mod:`hdrqn_ros.nodes.acting_torch`) or an exported ONNX policy
(:mod:`hdrqn_ros.nodes.acting_onnx`).
"""
from __future__ import annotations

from rclpy.node import Node

from hdrqn_ros.extras import require
from hdrqn_ros.nodes.acting_network import ActingNetwork
from hdrqn_ros.nodes.graph_parameters import domain_sizes
from hdrqn_ros.nodes.parameters import NodeConfigError


def make_acting_network(node: Node, role: str, params: dict, default_epsilon: float) -> ActingNetwork:
    """The ``role`` controller's acting network from the node's parameters: an exported
    policy with ``policy`` (torch is never imported), else torch weights (random, or
    ``checkpoint``'s, then the learner's). ``policy`` and ``checkpoint`` together:
    :class:`NodeConfigError`."""
    if params["policy"] and params["checkpoint"]:
        raise NodeConfigError(f"give either policy ({params['policy']}) or checkpoint ({params['checkpoint']}), "
                              f"not both: an exported policy is acted from as it is")
    num_actions, num_subgoals = domain_sizes(params["env"], params["view"])
    if params["policy"]:
        require("deploy", f"policy:={params['policy']} (acting from an exported policy)", ("onnxruntime",))
        from hdrqn_ros.nodes.acting_onnx import OnnxActingNetwork

        return OnnxActingNetwork(node, role, params, default_epsilon, num_actions, num_subgoals)
    from hdrqn_ros.nodes.acting_torch import TorchActingNetwork

    return TorchActingNetwork(node, role, params, default_epsilon, num_actions, num_subgoals)
