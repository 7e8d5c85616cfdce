"""The loopback navigator's planner (``hdrqn_ros.robot.grid_planner``): shortest free paths,
no corner cutting, and a reason for every failure."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hdrqn_ros.robot.grid_planner import PlanError, path_length, plan

ROOM = np.array([[c == "." for c in row] for row in (
    ".....",
    ".###.",
    ".#...",
    ".#.#.",
    "...#.",
)])


def cost(path: list[tuple[int, int]]) -> float:
    return sum(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(path, path[1:]))


def check_path(free: np.ndarray, path: list[tuple[int, int]]) -> None:
    for (r0, c0), (r1, c1) in zip(path, path[1:]):
        assert max(abs(r1 - r0), abs(c1 - c0)) == 1, f"not a step: {(r0, c0)} -> {(r1, c1)}"
        assert free[r1, c1], f"{(r1, c1)} is not free"
        if r1 != r0 and c1 != c0:
            assert free[r1, c0] and free[r0, c1], f"{(r0, c0)} -> {(r1, c1)} cuts a corner"


def test_shortest_free_path_without_cutting_corners():
    path = plan(ROOM, (4, 0), (2, 2))
    check_path(ROOM, path)
    assert path[0] == (4, 0) and path[-1] == (2, 2)
    assert path == [(4, 0), (4, 1), (4, 2), (3, 2), (2, 2)]  # under the wall: no diagonal past its corners
    assert cost(plan(ROOM, (0, 0), (2, 2))) == pytest.approx(8.0)  # no diagonal (1, 4) -> (2, 3) past (1, 3)
    assert plan(ROOM, (4, 0), (2, 2)) == path, "the same inputs give the same plan"


def test_open_grid_takes_diagonals():
    free = np.ones((6, 6), bool)
    path = plan(free, (0, 0), (5, 3))
    check_path(free, path)
    assert cost(path) == pytest.approx(3 * math.sqrt(2) + 2)
    assert plan(free, (2, 2), (2, 2)) == [(2, 2)]


@pytest.mark.parametrize("goal, reason", [((0, 9), "outside"), ((-1, 0), "outside"), ((1, 1), "occupied")])
def test_goals_off_the_grid_or_in_a_wall(goal, reason):
    with pytest.raises(PlanError) as info:
        plan(ROOM, (0, 0), goal)
    assert info.value.reason == reason and str(goal) in str(info.value)


def test_no_path_to_an_enclosed_cell():
    free = np.ones((5, 5), bool)
    free[1:4, 1:4] = False
    free[2, 2] = True  # a free cell walled in on all sides, diagonals included
    with pytest.raises(PlanError) as info:
        plan(free, (0, 0), (2, 2))
    assert info.value.reason == "no_path" and "(0, 0)" in str(info.value) and "(2, 2)" in str(info.value)


def test_diagonal_gap_between_walls_is_no_path():
    free = np.array([[True, False], [False, True]])
    with pytest.raises(PlanError) as info:
        plan(free, (0, 0), (1, 1))
    assert info.value.reason == "no_path"


def test_a_start_in_a_wall_and_a_bad_grid_are_refused():
    with pytest.raises(PlanError) as info:
        plan(ROOM, (1, 1), (0, 0))
    assert info.value.reason == "occupied" and "start" in str(info.value)
    with pytest.raises(ValueError, match="2-D"):
        plan(np.ones(4, bool), (0, 0), (0, 1))


def test_path_length():
    assert path_length([(0, 0), (3, 4), (3, 5)]) == pytest.approx(6.0)
    assert path_length([(1, 1)]) == 0.0
