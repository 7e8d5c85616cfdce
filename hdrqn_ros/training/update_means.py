"""Each controller's :class:`~hdrqn_ros.agents.controller.UpdateStats`, averaged over a
fixed number of its updates: one row of ``losses.csv`` per block. The statistics stay
tensors on the controller's device until a block is full, so the device is waited for
once per row, not once per update."""
from __future__ import annotations

from collections import defaultdict

import torch

from hdrqn_ros.agents.controller import UpdateStats


class UpdateMeans:
    """Collects update statistics per controller; every ``every`` updates of a controller,
    :meth:`add` returns their means."""

    def __init__(self, every: int):
        self.every = every
        self._pending: dict[str, list[torch.Tensor]] = defaultdict(list)

    def add(self, controller: str, stats: UpdateStats) -> dict[str, float] | None:
        """Add one update of ``controller``; returns ``{stat: mean}`` (the fields of
        :class:`UpdateStats`) over its last ``every`` updates when this one completes them,
        else None."""
        pending = self._pending[controller]
        pending.extend(stats)
        if len(pending) < self.every * len(UpdateStats._fields):
            return None
        means = torch.stack(pending).view(self.every, -1).mean(0).tolist()
        pending.clear()
        return dict(zip(UpdateStats._fields, means))
