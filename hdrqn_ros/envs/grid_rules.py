"""The gridworld's goal rules as one table, read by both step paths of
:class:`~hdrqn_ros.envs.grid_batch.GridWorldBatch` (vectorised ``step`` and scalar ``step_one``)."""
from __future__ import annotations

import numpy as np


class GoalRules:
    """The goal rules of ``n_goals`` goals, tabulated over ``m``, the bitmask of the goals
    collected so far (bit ``g``: goal ``g``), and ``k``, the uncollected goal the agent
    steps on: it is collected in the right order (``right[m, k]``: ``k`` is the lowest
    uncollected goal and every goal before it was collected in order), which pays
    ``extrinsic[m, k]`` (+1, else +0.01); the goals collected are then ``m | 1 << k``.
    ``next_goal[m]`` is the lowest uncollected goal (``n_goals`` once all are) and
    ``collected[m]`` the mask as booleans. ``right_py``/``extrinsic_py`` are the same
    tables as Python lists, for the scalar path."""

    def __init__(self, n_goals: int):
        G = self.n_goals = int(n_goals)
        masks = np.arange(1 << G)
        self.collected = ((masks[:, None] >> np.arange(G)) & 1).astype(bool)  # (2^G, G)
        self.count = self.collected.sum(axis=1)
        self.next_goal = np.where(self.collected.all(axis=1), G, np.argmin(self.collected, axis=1)).astype(np.int64)
        k = np.arange(G)[None, :]
        self.right = (k == self.count[:, None]) & (k == self.next_goal[:, None])  # (2^G, G)
        self.extrinsic = np.where(self.right, 1.0, 0.01).astype(np.float32)
        self.all_collected = (1 << G) - 1
        self.bit_values = (1 << np.arange(G)).astype(np.int64)
        for table in (self.collected, self.count, self.next_goal, self.right, self.extrinsic, self.bit_values):
            table.flags.writeable = False  # shared by every batch
        self.right_py: list[list[bool]] = self.right.tolist()
        self.extrinsic_py: list[list[float]] = self.extrinsic.tolist()


GOAL_RULES = {g: GoalRules(g) for g in (2, 3)}
"""The rules of two and of three goals."""
