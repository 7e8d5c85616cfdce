"""Each controller's :class:`~hdrqn_ros.agents.controller.UpdateStats`, averaged over a
fixed number of its updates: one row of ``losses.csv`` per block. The statistics stay
tensors on the controller's device until a block is full, so the device is waited for
once per row, not once per update."""
from __future__ import annotations

from collections import defaultdict

import torch

from hdrqn_ros.agents.controller import INDEX_BUCKETS, UpdateStats

SCALAR_STATS = UpdateStats._fields[:4]
"""The per-update means: TD loss, Q taken, target, gradient norm."""


class UpdateMeans:
    """Collects update statistics per controller; every ``every`` updates of a controller,
    :meth:`add` returns their means."""

    def __init__(self, every: int):
        self.every = every
        self._pending: dict[str, list[torch.Tensor]] = defaultdict(list)
        self._by_index: dict[str, torch.Tensor] = {}

    def add(self, controller: str, stats: UpdateStats) -> dict[str, float] | None:
        """Add one update of ``controller``; returns ``{stat: mean}`` over its last ``every``
        updates when this one completes them, else None: the :data:`SCALAR_STATS` and, for a
        controller whose updates carry ``by_index``, ``losses.csv``'s ``q_opt<i>``, ``return_opt<i>`` (NaN for an
        option index no loss step had)."""
        pending = self._pending[controller]
        pending.extend(stats[:len(SCALAR_STATS)])
        if stats.by_index is not None:
            total = self._by_index.get(controller)
            self._by_index[controller] = stats.by_index if total is None else total + stats.by_index
        if len(pending) < self.every * len(SCALAR_STATS):
            return None
        means = dict(zip(SCALAR_STATS, torch.stack(pending).view(self.every, -1).mean(0).tolist()))
        pending.clear()
        if (by_index := self._by_index.pop(controller, None)) is not None:
            count, q, ret = by_index.tolist()
            for i in range(INDEX_BUCKETS):
                means[f"q_opt{i}"] = q[i] / count[i] if count[i] else float("nan")
                means[f"return_opt{i}"] = ret[i] / count[i] if count[i] else float("nan")
        return means
