"""Deployment: acting from an exported ONNX policy without torch (numpy + onnxruntime).

``OnnxPolicy.load(DIR)`` reads a directory written by ``hdrqn export`` (torch side:
:func:`hdrqn_ros.training.export.export_policy`). Nothing here imports torch.
:mod:`hdrqn_ros.agents.specs` (the algorithm table, numpy only) is what the torch side
reads too; this package imports onnxruntime only when one of the names below that need it
is first used.
"""
from __future__ import annotations

from hdrqn_ros.agents.specs import stack_subgoal
from hdrqn_ros.deploy.errors import PolicyError

__all__ = ["POLICY_FILE", "OnnxPolicy", "PolicyError", "TensorSpec", "role_io", "stack_subgoal"]

_FROM_ONNX_POLICY = ("POLICY_FILE", "OnnxPolicy", "TensorSpec", "role_io")


def __getattr__(name: str):
    if name in _FROM_ONNX_POLICY:
        from hdrqn_ros.deploy import onnx_policy

        return getattr(onnx_policy, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
