"""The five algorithms as one agent type with different parts (thesis table 4.4).

| algo      | controllers      | networks                       | meta input               |
|-----------|------------------|--------------------------------|--------------------------|
| hdrqn-v2  | meta + sub       | LSTM (meta: MLP trunk)         | sub LSTM state (c or h)  |
| hdrqn-v1  | meta + sub       | LSTM (conv trunks)             | observation image        |
| hdqn      | meta + sub       | feed-forward (conv trunks)     | observation image        |
| drqn      | one (flat)       | LSTM                           | -                        |
| dqn       | one (flat)       | feed-forward                   | -                        |

The sub-controller of a hierarchical agent sees the observation and the subgoal image
stacked to 6 channels; a flat agent's controller sees the observation (3 channels) and
learns from the classical reward. The table itself (:data:`ALGO_SPECS`) and
:func:`stack_subgoal` live in the torch-free :mod:`hdrqn_ros.agents.specs`.
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.agents.controller import Controller
from hdrqn_ros.agents.networks import lstm_state_size, make_image_qnet, make_state_qnet
from hdrqn_ros.agents.replay import SequenceBatch
from hdrqn_ros.config import TrainConfig
from hdrqn_ros.agents.specs import ALGO_SPECS, stack_subgoal  # noqa: F401 (torch-free; re-exported)


def make_network(algo: str, role: str, num_actions: int, num_subgoals: int):
    """The Q-network of ``role`` ("meta" or "sub") of ``algo`` (thesis tables 4.5, 4.6)."""
    spec = ALGO_SPECS[algo]
    if role == "sub":
        return make_image_qnet(6 if spec.hierarchical else 3, num_actions, recurrent=spec.recurrent)
    if role != "meta" or not spec.hierarchical:
        raise ValueError(f"{algo} has no {role!r} controller")
    if spec.meta_input == "state":
        return make_state_qnet(lstm_state_size, num_subgoals, recurrent=True)
    return make_image_qnet(3, num_subgoals, recurrent=spec.recurrent)


def _sub_window_input(batch: SequenceBatch) -> np.ndarray:
    # frames (B, n+1, 44, 44, 3); one subgoal image per window (its option's)
    return stack_subgoal(batch.frames, batch.segment_data["subgoal_image"][:, None])


def _frames(batch: SequenceBatch) -> np.ndarray:
    return batch.frames


class Agent:
    """The controllers of one algorithm; ``meta`` is ``None`` for the flat baselines."""

    def __init__(self, cfg: TrainConfig, num_actions: int, num_subgoals: int):
        self.algo = cfg.algo
        self.spec = spec = ALGO_SPECS[cfg.algo]
        self.num_actions = num_actions
        self.num_subgoals = num_subgoals
        self.sub = Controller("sub", make_network(cfg.algo, "sub", num_actions, num_subgoals),
                              cfg.controller("sub"), _sub_window_input if spec.hierarchical else _frames,
                              device=cfg.device, seed=cfg.seed)
        self.meta: Controller | None = None
        if spec.hierarchical:
            self.meta = Controller("meta", make_network(cfg.algo, "meta", num_actions, num_subgoals),
                                   cfg.controller("meta"), _frames, device=cfg.device, seed=cfg.seed + 1,
                                   smdp_discount=cfg.smdp_discount, track_returns=True)

    @property
    def controllers(self) -> list[Controller]:
        return [c for c in (self.meta, self.sub) if c is not None]

    def sub_input(self, obs: np.ndarray, subgoal_images: np.ndarray) -> np.ndarray:
        """(N, 44, 44, 3) observations -> the sub-controller's (N, 44, 44, 3 or 6) input."""
        return stack_subgoal(obs, subgoal_images) if self.spec.hierarchical else obs

    def state_dict(self) -> dict:
        return {c.name: c.state_dict() for c in self.controllers}

    def load_state_dict(self, state: dict) -> None:
        for c in self.controllers:
            c.load_state_dict(state[c.name])
