"""Nav2's costmap values: the inflation layer's costs and their OccupancyGrid translation. No ROS.

Facts from nav2_costmap_2d (Jazzy): a costmap cell holds 0..255; 254 is a lethal obstacle,
253 "inscribed" (the robot's centre there means a collision), 255 unknown, 0 free. The
inflation layer gives a cell at distance ``d`` (m, centre to centre, from the nearest lethal
cell) the cost 254 at ``d = 0``, 253 for ``d <= inscribed_radius``, else
``int(252 * exp(-cost_scaling_factor * (d - inscribed_radius)))``, and leaves cells beyond
``inflation_radius`` alone; an unknown cell takes only an inscribed (or lethal) cost. The
published ``nav_msgs/OccupancyGrid`` translates 0 -> 0, 253 -> 99, 254 -> 100, 255 -> -1 and
1..252 -> ``1 + 97 * (cost - 1) // 251`` (1..98).
"""
from __future__ import annotations

import math

import numpy as np

FREE, INSCRIBED, LETHAL, NO_INFORMATION = 0, 253, 254, 255
"""nav2_costmap_2d's special costs."""
OCCUPANCY_FREE, OCCUPANCY_INSCRIBED, OCCUPANCY_LETHAL, OCCUPANCY_UNKNOWN = 0, 99, 100, -1
"""The same costs in a published OccupancyGrid."""


def occupancy_values(costs: np.ndarray) -> np.ndarray:
    """OccupancyGrid values (int8, same shape) of costmap costs (0..255)."""
    costs = np.asarray(costs, np.int64)
    if costs.size and (costs.min() < 0 or costs.max() > 255):
        raise ValueError(f"costs must be in 0..255, got {costs.min()}..{costs.max()}")
    graded = 1 + 97 * (costs - 1) // 251
    out = np.where(costs == FREE, OCCUPANCY_FREE, graded)
    out = np.where(costs == INSCRIBED, OCCUPANCY_INSCRIBED, out)
    out = np.where(costs == LETHAL, OCCUPANCY_LETHAL, out)
    return np.where(costs == NO_INFORMATION, OCCUPANCY_UNKNOWN, out).astype(np.int8)


def inflation_cost(distance_m: np.ndarray, inscribed_radius_m: float, cost_scaling_factor: float) -> np.ndarray:
    """The inflation layer's cost (uint8) of cells ``distance_m`` (m) from the nearest lethal cell."""
    d = np.asarray(distance_m, np.float64)
    graded = (INSCRIBED - 1) * np.exp(-cost_scaling_factor * np.maximum(d - inscribed_radius_m, 0.0))
    cost = np.where(d <= inscribed_radius_m, INSCRIBED, np.floor(graded))
    return np.where(d == 0, LETHAL, cost).astype(np.uint8)


def _shifted(values: np.ndarray, offset: int, axis: int, fill: float) -> np.ndarray:
    """``values`` moved by ``offset`` cells along ``axis`` (out[i] = values[i + offset]), ``fill`` beyond."""
    out = np.full(values.shape, fill)
    n = values.shape[axis]
    if abs(offset) < n:
        src = [slice(None)] * values.ndim
        dst = [slice(None)] * values.ndim
        src[axis] = slice(max(offset, 0), n + min(offset, 0))
        dst[axis] = slice(max(-offset, 0), n - max(offset, 0))
        out[tuple(dst)] = values[tuple(src)]
    return out


def distance_to_lethal(lethal: np.ndarray, max_cells: int) -> np.ndarray:
    """``(H, W)`` float: the Euclidean distance (cells, centre to centre) of each cell to the
    nearest ``lethal`` cell; ``inf`` where that is over ``max_cells``. Exact up to
    ``max_cells``: the nearest lethal cell of each column within ``max_cells`` rows, then the
    best of the columns within ``max_cells``."""
    lethal = np.asarray(lethal, bool)
    far = float(max_cells + 1)
    vertical = np.where(lethal, 0.0, far)
    for k in range(1, max_cells + 1):
        for offset in (k, -k):
            vertical = np.minimum(vertical, np.where(_shifted(lethal, offset, 0, False), float(k), far))
    squared = vertical ** 2
    best = squared.copy()
    for k in range(1, max_cells + 1):
        for offset in (k, -k):
            best = np.minimum(best, k * k + _shifted(squared, offset, 1, far * far))
    distance = np.sqrt(best)
    return np.where(distance <= max_cells, distance, np.inf)


def inflate(occupancy: np.ndarray, resolution_m: float, inscribed_radius_m: float, inflation_radius_m: float,
            cost_scaling_factor: float) -> np.ndarray:
    """The OccupancyGrid values (int8, ``(H, W)``) of a grid of lethal (100), free (0) and
    unknown (-1) cells after Nav2's inflation layer; ``inflation_radius_m`` 0: unchanged."""
    occupancy = np.asarray(occupancy, np.int8)
    if not np.isin(occupancy, (OCCUPANCY_FREE, OCCUPANCY_LETHAL, OCCUPANCY_UNKNOWN)).all():
        raise ValueError("inflate takes a grid of lethal (100), free (0) and unknown (-1) cells only")
    for name, value in (("resolution_m", resolution_m), ("inscribed_radius_m", inscribed_radius_m),
                        ("inflation_radius_m", inflation_radius_m), ("cost_scaling_factor", cost_scaling_factor)):
        if not math.isfinite(value) or value < 0 or (name == "resolution_m" and value == 0):
            raise ValueError(f"{name} must be a {'positive' if name == 'resolution_m' else 'non-negative'} "
                             f"number, got {value!r}")
    if inflation_radius_m == 0:
        return occupancy.copy()
    lethal, unknown = occupancy == OCCUPANCY_LETHAL, occupancy == OCCUPANCY_UNKNOWN
    max_cells = max(0, math.ceil(inflation_radius_m / resolution_m - 1e-9))
    distance_m = distance_to_lethal(lethal, max_cells) * resolution_m
    cost = np.where(np.isfinite(distance_m), inflation_cost(np.where(np.isfinite(distance_m), distance_m, 0.0),
                                                            inscribed_radius_m, cost_scaling_factor), FREE)
    cost = np.where(unknown, np.where(cost >= INSCRIBED, cost, NO_INFORMATION), cost)
    return occupancy_values(cost)
