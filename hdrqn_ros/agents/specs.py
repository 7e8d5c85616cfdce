"""The five algorithms as plain data: the one table every list of algorithm names is taken
from, read by the torch side (:mod:`hdrqn_ros.agents.algorithms`, :mod:`hdrqn_ros.agents.networks`),
the torch-free side (:mod:`hdrqn_ros.deploy.onnx_policy`, the controller nodes acting from an
exported policy), the config, the nodes and the launch files. Imports only the standard library
and numpy: no torch, no onnxruntime.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = ["AlgoSpec", "ALGO_SPECS", "ALGOS", "STATE_SIZE", "stack_subgoal"]

STATE_SIZE = 256
"""The LSTM state size (``h`` and ``c`` are (B, 256)); ``hdrqn_ros.agents.networks.lstm_state_size``."""


@dataclass(frozen=True)
class AlgoSpec:
    hierarchical: bool
    recurrent: bool
    meta_input: Literal["image", "state", None]


ALGO_SPECS: dict[str, AlgoSpec] = {
    "hdrqn-v2": AlgoSpec(hierarchical=True, recurrent=True, meta_input="state"),
    "hdrqn-v1": AlgoSpec(hierarchical=True, recurrent=True, meta_input="image"),
    "hdqn": AlgoSpec(hierarchical=True, recurrent=False, meta_input="image"),
    "drqn": AlgoSpec(hierarchical=False, recurrent=True, meta_input=None),
    "dqn": AlgoSpec(hierarchical=False, recurrent=False, meta_input=None),
}
"""The five algorithms (thesis table 4.4; see :mod:`hdrqn_ros.agents.algorithms`)."""
ALGOS = tuple(ALGO_SPECS)
"""Their names, in the table's order (the default first)."""


def stack_subgoal(obs: np.ndarray, subgoal_image: np.ndarray) -> np.ndarray:
    """The hierarchical sub-controller's input: ``obs`` (..., 44, 44, 3) and the subgoal
    image broadcast to it, stacked to (..., 44, 44, 6) uint8."""
    return np.concatenate([obs, np.broadcast_to(subgoal_image, obs.shape)], axis=-1)
