"""Shortest paths over the free cells of an occupancy grid: what the loopback robot's
navigator plans on (a stand-in for Nav2's global planner, on the map's own cells).

A* over 8-connected cells (a step costs 1, a diagonal step sqrt 2); a diagonal step is
taken only where both cells beside it are free too, so a path never cuts a wall's corner.
Cells are ``(row, col)`` of a ``(rows, cols)`` bool grid (True: free). Ties break the same
way every time, so a plan depends on its inputs only. No ROS, numpy only.
"""
from __future__ import annotations

import heapq
import math

import numpy as np

STEPS = ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1))
"""The moves from a cell: the four sides, then the four diagonals."""


class PlanError(ValueError):
    """No plan: ``reason`` is ``"outside"`` (the goal is off the grid), ``"occupied"`` (the
    goal or the start is not free) or ``"no_path"`` (no free path joins them)."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def plan(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]]:
    """The cells of a shortest free path from ``start`` to ``goal``, both included (one cell
    when they are the same). Raises :class:`PlanError` saying why there is none."""
    free = np.asarray(free, dtype=bool)
    if free.ndim != 2:
        raise ValueError(f"free must be a 2-D grid, got shape {free.shape}")
    rows, cols = free.shape
    start, goal = (int(start[0]), int(start[1])), (int(goal[0]), int(goal[1]))

    def inside(cell: tuple[int, int]) -> bool:
        return 0 <= cell[0] < rows and 0 <= cell[1] < cols

    if not inside(goal):
        raise PlanError("outside", f"goal cell {goal} is off the {rows}x{cols} grid")
    if not inside(start):
        raise PlanError("outside", f"start cell {start} is off the {rows}x{cols} grid")
    if not free[goal]:
        raise PlanError("occupied", f"goal cell {goal} is not free")
    if not free[start]:
        raise PlanError("occupied", f"start cell {start} is not free")

    def estimate(cell: tuple[int, int]) -> float:  # octile distance: never above the true cost
        dr, dc = abs(cell[0] - goal[0]), abs(cell[1] - goal[1])
        return max(dr, dc) + (math.sqrt(2) - 1) * min(dr, dc)

    cost = {start: 0.0}
    came_from: dict[tuple[int, int], tuple[int, int] | None] = {start: None}
    frontier = [(estimate(start), 0, start)]
    order = 0  # insertion order: equal estimates pop first in, first out
    while frontier:
        _, _, cell = heapq.heappop(frontier)
        if cell == goal:
            path = [cell]
            while (cell := came_from[cell]) is not None:
                path.append(cell)
            return path[::-1]
        for dr, dc in STEPS:
            nxt = (cell[0] + dr, cell[1] + dc)
            if not inside(nxt) or not free[nxt]:
                continue
            if dr and dc and not (free[cell[0] + dr, cell[1]] and free[cell[0], cell[1] + dc]):
                continue  # would cut a corner
            new_cost = cost[cell] + (math.sqrt(2) if dr and dc else 1.0)
            if new_cost < cost.get(nxt, math.inf) - 1e-12:
                cost[nxt], came_from[nxt] = new_cost, cell
                order += 1
                heapq.heappush(frontier, (new_cost + estimate(nxt), order, nxt))
    raise PlanError("no_path", f"no free path from cell {start} to cell {goal}")


def path_length(points) -> float:
    """Length (in the points' units) of the polyline through ``points`` ``(n, 2)``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    return float(np.hypot(*np.diff(points, axis=0).T).sum()) if len(points) > 1 else 0.0
