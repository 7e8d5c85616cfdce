"""The robot's finished episodes: how many, how many succeeded, one JSON line each.

No ROS: the robot-side environment node hands each episode over as it ends.
"""
from __future__ import annotations

import json

import numpy as np


class EpisodeLog:
    """Counts the finished episodes and appends each to the JSON-lines file ``path`` ('': none)."""

    def __init__(self, path: str = ""):
        self.file = open(path, "a", buffering=1, encoding="utf-8") if path else None
        self.done = self.successes = 0

    def add(self, episode: int, success: bool, steps: int, visits: list[int], episode_return: float,
            decision_s: list[float]) -> dict:
        """One finished episode: ``visits`` the place indices in visit order, ``decision_s`` the
        wall seconds from each step's publication to its action's arrival. The row written:
        ``episode``, ``success``, ``steps``, ``visits``, ``return``, ``decision_ms`` (the median)
        and ``success_rate`` so far."""
        self.done += 1
        self.successes += bool(success)
        row = {"episode": episode, "success": bool(success), "steps": steps, "visits": list(visits),
               "return": round(episode_return, 4),
               "decision_ms": round(1e3 * float(np.median(decision_s)), 3) if decision_s else 0.0,
               "success_rate": self.successes / self.done}
        if self.file is not None:
            self.file.write(json.dumps(row) + "\n")
        return row

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
            self.file = None
