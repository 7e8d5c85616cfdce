"""Rendering the gridworld's RGB canvases: egocentric observations and whole maps.

An observation is a gather of the ``view x view`` window of the padded RGB canvas (see
:mod:`~hdrqn_ros.envs.grid_layout`) followed by a nearest-neighbour upscale to 44x44
(pixel ``i`` shows window cell ``floor(i * view / 44)``), done as two ``np.repeat`` calls.
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.envs.grid_layout import CANVAS, CANVAS_CELLS, MAP_SIZE, PAD, PAD_TO_CELL, pad_index

RENDER_CELL_PX = 32
"""Pixels per cell of ``render()`` (``render_mode='rgb_array'``)."""


def upscale_counts(view_cells: int) -> np.ndarray:
    """How many of the 44 pixels show each of the ``view_cells`` window cells."""
    return np.bincount((np.arange(OBS_SIZE) * view_cells) // OBS_SIZE, minlength=view_cells)


_WINDOW_TABLES: dict = {}


def window_table(view) -> np.ndarray:
    """``(121, v*v) intp``: for each map cell (``r*11+c``) the padded-canvas indices of the
    window centred on it, row-major (for ``'full'`` every row is the whole map)."""
    if view not in _WINDOW_TABLES:
        if view == "full":
            rows, cols = np.meshgrid(np.arange(MAP_SIZE), np.arange(MAP_SIZE), indexing="ij")
            one = pad_index(rows, cols).reshape(-1)
            table = np.repeat(one[None, :], MAP_SIZE * MAP_SIZE, axis=0)
        else:
            h = view // 2
            d = np.arange(-h, h + 1)
            dr, dc = np.meshgrid(d, d, indexing="ij")
            cells = np.arange(MAP_SIZE * MAP_SIZE)
            r, c = cells // MAP_SIZE, cells % MAP_SIZE
            table = pad_index(r[:, None] + dr.reshape(1, -1), c[:, None] + dc.reshape(1, -1))
        _WINDOW_TABLES[view] = np.ascontiguousarray(table, dtype=np.intp)
    return _WINDOW_TABLES[view]


class WindowRenderer:
    """Observations of ``num_envs`` RGB canvases stacked as one ``(num_envs*441, 3)`` array:
    the ``view`` window (3, 5, 11 cells, or ``'full'``: the whole map) around a canvas cell,
    upscaled to 44x44."""

    def __init__(self, view, num_envs: int):
        self._win = window_table(view)
        self._v = MAP_SIZE if view == "full" else view
        self._counts = upscale_counts(self._v)
        self._row_off = np.arange(num_envs, dtype=np.intp) * CANVAS_CELLS

    def windows(self, rgb: np.ndarray, centers: np.ndarray) -> np.ndarray:
        """``(N, 44, 44, 3)``: env ``i``'s window centred on canvas index ``centers[i]``."""
        v, k = self._v, self._counts
        ix = self._win[PAD_TO_CELL[centers]]
        ix += self._row_off[:, None]
        w = rgb.take(ix, axis=0).reshape(len(centers), v, v, 3)
        return np.repeat(np.repeat(w, k, axis=2), k, axis=1)

    def window_one(self, rgb: np.ndarray, center: int) -> np.ndarray:
        """``(44, 44, 3)``: the window of the first env's canvas centred on ``center``."""
        v, k = self._v, self._counts
        w = rgb.take(self._win[PAD_TO_CELL[center]], axis=0).reshape(v, v, 3)
        return np.repeat(np.repeat(w, k, axis=1), k, axis=0)


def render_map(rgb: np.ndarray, i: int = 0, cell_px: int = RENDER_CELL_PX) -> np.ndarray:
    """``(11*cell_px, 11*cell_px, 3) uint8``: env ``i``'s whole map from the stacked canvases ``rgb``."""
    canvas = rgb[i * CANVAS_CELLS:(i + 1) * CANVAS_CELLS].reshape(CANVAS, CANVAS, 3)
    m = canvas[PAD:PAD + MAP_SIZE, PAD:PAD + MAP_SIZE]
    return np.repeat(np.repeat(m, cell_px, axis=0), cell_px, axis=1)
