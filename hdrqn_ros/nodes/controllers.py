"""The ``meta_controller`` and ``sub_controller`` executables: the two levels of the agent
(:mod:`hdrqn_ros.nodes.meta_controller`, :mod:`hdrqn_ros.nodes.sub_controller`), each a
managed node (``--managed``: a lifecycle manager configures and activates it).

Both explore with the learner's epsilons (or a fixed ``epsilon`` parameter) and take new
weights from the learner's latched weights topics, or act from an exported ONNX policy
(``policy``: numpy and onnxruntime only, torch is never imported, frozen weights).
"""
from __future__ import annotations

from hdrqn_ros.nodes.meta_controller import MetaControllerNode
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.sub_controller import SubControllerNode


def main_meta(argv: list[str] | None = None) -> int:
    return run_node(MetaControllerNode, argv)


def main_sub(argv: list[str] | None = None) -> int:
    return run_node(SubControllerNode, argv)
