"""The contract every domain's batch core fulfils (see docs/architecture.md).

A batch core steps ``N`` environments as one operation; the single ``gymnasium.Env`` of a
domain is a view of a batch of one. Images are ``(N, 44, 44, 3) uint8`` RGB.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

OBS_SIZE = 44
"""Side of every observation and subgoal image in pixels (thesis section 4.1.4)."""
OBS_SHAPE = (OBS_SIZE, OBS_SIZE, 3)
NO_SUBGOAL = -1
"""Value of ``StepBatch.at_subgoal`` when the agent achieved no subgoal at this step."""


@dataclass
class StepBatch:
    """What ``N`` environments report after one step; every array has ``N`` rows."""

    obs: np.ndarray  # (N, 44, 44, 3) uint8, observation after the step
    classical: np.ndarray  # (N,) float32, eq. 4.3 / 4.6
    extrinsic: np.ndarray  # (N,) float32, eq. 4.2 / 4.5
    terminated: np.ndarray  # (N,) bool
    truncated: np.ndarray  # (N,) bool, step limit
    agent_pos: np.ndarray  # (N, 2) int32, grid (row, col) or Montezuma RAM (x, y)
    at_subgoal: np.ndarray  # (N,) int32, subgoal whose place the agent is at after the step, or NO_SUBGOAL
    collected: np.ndarray  # (N,) bool, an object was picked up at this step (a goal; the key)
    hit_obstacle: np.ndarray  # (N,) bool
    life_lost: np.ndarray  # (N,) bool
    success: np.ndarray  # (N,) bool, episode solved (meaningful when done)

    @property
    def done(self) -> np.ndarray:
        """(N,) bool: the episode ended (terminated or truncated)."""
        return self.terminated | self.truncated

    def row(self, i: int) -> "StepBatch":
        """The batch of one holding row ``i`` (arrays keep their leading axis)."""
        return StepBatch(**{k: v[i : i + 1] for k, v in self.__dict__.items()})


class DomainBatch(Protocol):
    """``N`` environments of one domain, stepped together (no auto-reset)."""

    num_envs: int
    num_actions: int
    num_subgoals: int
    subgoal_names: tuple[str, ...]  # one per subgoal index
    subgoal_neighbours: tuple[tuple[int, ...], ...]  # per subgoal: those reachable from it directly
    return_bound: float  # the largest extrinsic return one episode can give (the meta-controller's)

    def reset(self, seed: int | None = None) -> np.ndarray: ...

    def reset_where(self, mask: np.ndarray) -> np.ndarray: ...

    def step(self, actions: np.ndarray) -> StepBatch: ...

    def subgoal_images(self, subgoals: np.ndarray) -> np.ndarray: ...

    def critic(self): ...


def check_actions(actions, num_envs: int, num_actions: int) -> np.ndarray:
    """Validate a batch of discrete actions; returns them as ``(N,) int64``.

    Raises ``ValueError`` naming the bad shape or value.
    """
    a = np.asarray(actions)
    if a.shape == () and num_envs == 1:
        a = a.reshape(1)
    if a.shape != (num_envs,):
        raise ValueError(f"actions must have shape ({num_envs},), got {a.shape}")
    if not np.issubdtype(a.dtype, np.integer):
        if np.issubdtype(a.dtype, np.floating) and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
            a = a.astype(np.int64)
        else:
            raise ValueError(f"actions must be integers, got dtype {a.dtype} ({a.tolist()})")
    bad = (a < 0) | (a >= num_actions)
    if bad.any():
        raise ValueError(f"action {int(a[bad][0])} out of range [0, {num_actions})")
    return a.astype(np.int64, copy=False)
