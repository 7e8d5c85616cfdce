"""Deployment: acting from an exported ONNX policy without torch (numpy + onnxruntime).

``OnnxPolicy.load(DIR)`` reads a directory written by ``hdrqn export`` (torch side:
:func:`hdrqn_ros.training.export.export_policy`). Nothing here imports torch.
"""
from hdrqn_ros.deploy.onnx_policy import POLICY_FILE, OnnxPolicy, PolicyError, TensorSpec, role_io, stack_subgoal

__all__ = ["POLICY_FILE", "OnnxPolicy", "PolicyError", "TensorSpec", "role_io", "stack_subgoal"]
