"""The task on a robot: visit the subgoal places in their order (the gridworld's goal rules).

A robot has no simulator to say what a step did, so the robot-side environment node asks
this object. At each agent step it takes the robot's position (metres, the subgoals'
frame) and the place the current option aims at (the meta-controller's subgoal) and
reports the ``env_step`` outcome fields the environment node would publish: the robot is
at (``at_subgoal``) the aimed place when it is within ``tolerance_m`` of it, otherwise at
the nearest place within ``tolerance_m`` (a place counts after its visit too, a subgoal is
a place), so a navigator's arrival at the place it was sent to is a visit of that place
even when a neighbour is nearer (two places 0.35 m apart, tolerance 0.25 m); the first time
there is a visit (``collected``), paid by :class:`~hdrqn_ros.envs.grid_rules.GoalRules`
(+1 in order, +0.01 out of order); the episode terminates when every place was visited
and is truncated at ``max_steps``. There is no fire on a robot; a robot standing on a
lethal costmap cell reports ``hit_obstacle`` (classical reward -1), and no life is lost.
:class:`CellVisits` is the simulator's rule instead (in the place's cell). No ROS, numpy only.
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.grid_rules import GoalRules


class OrderedVisits:
    """One robot's episode of visiting ``n_goals`` places in index order."""

    def __init__(self, n_goals: int, tolerance_m: float, max_steps: int):
        if not tolerance_m > 0:
            raise ValueError(f"tolerance_m must be > 0, got {tolerance_m!r}")
        if max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps!r}")
        self.rules = GoalRules(n_goals)
        self.n_goals, self.tolerance_m, self.max_steps = int(n_goals), float(tolerance_m), int(max_steps)
        self.goal_xy = np.zeros((self.n_goals, 2))
        self.mask = 0  # goals visited, bit g: goal g
        self.in_order = True
        self.t = 0
        self.visits: list[int] = []  # the goals in the order they were visited

    def start(self, goal_xy) -> None:
        """A new episode with the places ``goal_xy`` ``(n_goals, 2)`` (m)."""
        goal_xy = np.asarray(goal_xy, dtype=np.float64)
        if goal_xy.shape != (self.n_goals, 2) or not np.isfinite(goal_xy).all():
            raise ValueError(f"goal_xy must be {self.n_goals} finite (x, y) pairs, got {goal_xy.tolist()}")
        self.goal_xy = goal_xy
        self.mask, self.in_order, self.t, self.visits = 0, True, 0, []

    @property
    def collected(self) -> np.ndarray:
        """``(n_goals,) bool``: which places were visited this episode."""
        return self.rules.collected[self.mask]

    def uncollected_xy(self) -> list[tuple[float, float] | None]:
        """Each place's (x, y), ``None`` once visited (what an observation draws)."""
        return [None if seen else (float(x), float(y)) for seen, (x, y) in zip(self.collected, self.goal_xy)]

    def offsets(self, robot_xy) -> np.ndarray:
        """``(n_goals,)`` metres from ``robot_xy`` to each place (Euclidean)."""
        return np.hypot(*(self.goal_xy - np.asarray(robot_xy, dtype=np.float64)).T)

    def within(self, offset: float) -> bool:
        """Whether a place ``offset`` (m, as :meth:`offsets` measures) away is where the robot is."""
        return bool(offset <= self.tolerance_m)

    def where(self, robot_xy, aimed: int = NO_SUBGOAL) -> int:
        """The place the robot at ``robot_xy`` is at: ``aimed`` (the current option's place)
        if it is within tolerance, else the nearest within tolerance, else ``NO_SUBGOAL``."""
        if aimed != NO_SUBGOAL and not 0 <= aimed < self.n_goals:
            raise ValueError(f"aimed must be a place 0..{self.n_goals - 1} or NO_SUBGOAL ({NO_SUBGOAL}), "
                             f"got {aimed!r}")
        offset = self.offsets(robot_xy)
        if aimed != NO_SUBGOAL and self.within(offset[aimed]):
            return int(aimed)
        nearest = int(np.argmin(offset))
        return nearest if self.within(offset[nearest]) else NO_SUBGOAL

    def step(self, robot_xy, on_lethal: bool = False, aimed: int = NO_SUBGOAL) -> dict:
        """One agent step ending at ``robot_xy`` under the option aiming at place ``aimed``:
        the ``env_step`` outcome fields (``extrinsic`` ... ``decision_point``, as
        :func:`hdrqn_ros.protocol.wire.step_outcome`)."""
        at = self.where(robot_xy, aimed)
        collected = at != NO_SUBGOAL and not self.collected[at]
        extrinsic = 0.0
        if collected:
            extrinsic = float(self.rules.extrinsic[self.mask, at])
            self.in_order &= bool(self.rules.right[self.mask, at])
            self.mask |= 1 << at
            self.visits.append(at)
        self.t += 1
        terminated = self.mask == self.rules.all_collected
        truncated = not terminated and self.t >= self.max_steps
        return {"extrinsic": extrinsic, "classical": extrinsic - float(on_lethal), "terminated": terminated,
                "truncated": truncated, "at_subgoal": at, "collected": collected, "hit_obstacle": bool(on_lethal),
                "life_lost": False, "success": terminated and self.in_order,
                "decision_point": at != NO_SUBGOAL and not (terminated or truncated)}


class CellVisits(OrderedVisits):
    """:class:`OrderedVisits` by the simulator's rule: the robot is at a place when it is in
    the place's cell, the square of ``cell_m`` centred on it (axes of the pose's frame).
    The cells of places a cell apart never overlap, so ``aimed`` changes nothing there."""

    def __init__(self, n_goals: int, cell_m: float, max_steps: int):
        super().__init__(n_goals, cell_m / 2, max_steps)

    def offsets(self, robot_xy) -> np.ndarray:
        """``(n_goals,)`` metres from ``robot_xy`` to each place along the farther axis."""
        return np.abs(self.goal_xy - np.asarray(robot_xy, dtype=np.float64)).max(axis=1)

    def within(self, offset: float) -> bool:
        return bool(offset < self.tolerance_m)
