"""The gridworld / four-rooms maps and the padded canvas that holds them.

Each environment keeps a *padded code canvas*: the 11x11 map surrounded by a 5-cell
margin of "outside" cells (a 21x21 array, flattened), so that every egocentric window
(3, 5 or 11 cells) is a plain slice of it. Positions are flat indices into that canvas.
"""
from __future__ import annotations

import numpy as np

MAP_SIZE = 11
"""Side of the map in cells; its border cells are walls."""
PAD = 5
"""Margin of outside cells around the map in the padded canvas (half the largest view)."""
CANVAS = MAP_SIZE + 2 * PAD  # 21
CANVAS_CELLS = CANVAS * CANVAS  # 441

FREE, WALL, GOAL0, FIRE, AGENT, OUTSIDE = 0, 1, 2, 5, 6, 7
"""Cell codes of the canvas. Goal ``g`` has code ``GOAL0 + g``."""
PALETTE = np.array(
    [
        (255, 255, 255),  # free: white
        (128, 128, 128),  # wall: grey
        (0, 0, 255),  # goal 0: blue
        (0, 255, 0),  # goal 1: green
        (0, 255, 255),  # goal 2: cyan
        (255, 0, 0),  # fire (obstacle): red
        (0, 0, 0),  # agent: black
        (0, 0, 0),  # outside the map: black
    ],
    dtype=np.uint8,
)
GOAL_NAMES = ("blue", "green", "cyan")
NUM_OBSTACLES = 2
ACTIONS = ("up", "down", "left", "right")
"""Action ``a`` moves the agent by ``ACTION_DELTAS[a]`` (row, col)."""
ACTION_DELTAS = ((-1, 0), (1, 0), (0, -1), (0, 1))
DELTA_FLAT = tuple(dr * CANVAS + dc for dr, dc in ACTION_DELTAS)
"""``ACTION_DELTAS`` as steps between flat canvas indices."""
LAYOUTS = ("gridworld", "fourrooms")
VIEWS = (3, 5, 11, "full")
FOURROOMS_DOORS = ((3, 5), (7, 5), (5, 3), (5, 7))


def layout_walls(layout: str) -> np.ndarray:
    """``(11, 11) bool``: the wall cells of ``layout`` ('gridworld' or 'fourrooms')."""
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
    walls = np.zeros((MAP_SIZE, MAP_SIZE), dtype=bool)
    walls[0, :] = walls[-1, :] = walls[:, 0] = walls[:, -1] = True
    if layout == "fourrooms":
        mid = MAP_SIZE // 2
        walls[mid, :] = walls[:, mid] = True
        for r, c in FOURROOMS_DOORS:
            walls[r, c] = False
    return walls


def default_max_steps(layout: str, n_goals: int) -> int:
    """Step limit of the thesis: 50, or 100 for three goals in four-rooms."""
    return 100 if (layout == "fourrooms" and n_goals == 3) else 50


def pad_index(r, c):
    """Flat index in the padded canvas of map cell ``(r, c)``."""
    return (np.asarray(r) + PAD) * CANVAS + (np.asarray(c) + PAD)


def rowcol(flat) -> np.ndarray:
    """``(..., 2) int32``: the map (row, col) of padded canvas indices ``flat``."""
    flat = np.asarray(flat)
    return np.stack([flat // CANVAS - PAD, flat % CANVAS - PAD], axis=-1).astype(np.int32)


PAD_TO_CELL = np.full(CANVAS_CELLS, -1, dtype=np.intp)
"""Padded flat index -> map cell id ``r*11+c`` (-1 outside the map)."""
for _r in range(MAP_SIZE):
    for _c in range(MAP_SIZE):
        PAD_TO_CELL[int(pad_index(_r, _c))] = _r * MAP_SIZE + _c
del _r, _c


def check_view(view):
    """``view`` (3, 5, 11 or 'full') as an int or 'full'; ValueError for anything else."""
    if isinstance(view, str):
        if view != "full":
            raise ValueError(f"invalid view {view!r}; expected one of {VIEWS}")
        return view
    if isinstance(view, (bool, np.bool_)) or not isinstance(view, (int, np.integer)) or int(view) not in (3, 5, 11):
        raise ValueError(f"invalid view {view!r}; expected one of {VIEWS}")
    return int(view)
