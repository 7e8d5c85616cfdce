"""A kinematic robot on the gridworld / four-rooms map: the core of the loopback robot.

Like Nav2's ``nav2_loopback_sim``: no physics, only kinematics. Map frame in metres: map
cell (row ``r``, col ``c``) of the 11x11 map has its centre at ``x = (c + 0.5) * cell``,
``y = (10 - r + 0.5) * cell`` (row 0 is the top, the largest y), so the gridworld's "up"
is +y and "right" +x. The robot is a disc of ``robot_radius_m`` (a hair under half a cell,
so it fits the one-cell corridors); walls stop it at contact. Each episode's layout (the
robot's start cell and the goals' cells) is the simulator's for the same seed, fires left
out (:class:`~hdrqn_ros.envs.grid_batch.GridWorldBatch` with ``obstacles=False``). Costmaps
use Nav2's ``OccupancyGrid`` values: 100 wall, 0 free, -1 outside the map. No ROS.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from hdrqn_ros.envs.grid_batch import GridWorldBatch
from hdrqn_ros.envs.grid_layout import MAP_SIZE

FREE_COST, WALL_COST, UNKNOWN_COST = 0, 100, -1


@dataclass(frozen=True)
class Layout:
    """One episode's places."""

    episode: int
    agent_cell: tuple[int, int]  # (row, col)
    goal_cells: tuple[tuple[int, int], ...]
    goal_xy: np.ndarray  # (n_goals, 2) m, map frame, cell centres


@dataclass(frozen=True)
class Costmap:
    """An OccupancyGrid's content: ``data`` (height, width) int8, row 0 at the origin's y."""

    origin_xy: tuple[float, float]  # m, lower-left corner of cell (0, 0)
    resolution_m: float
    width: int
    height: int
    data: np.ndarray


def _finite(name: str, *values: float) -> None:
    if not all(math.isfinite(float(v)) for v in values):
        raise ValueError(f"{name} must be finite, got {values}")


class LoopbackWorld:
    """The robot's pose and motion on the map, one episode's layout at a time."""

    def __init__(self, layout: str = "gridworld", n_goals: int = 2, seed: int = 0, *, cell_size_m: float = 0.25,
                 resolution_m: float = 0.05, robot_radius_m: float = 0.12, nav_speed_m_s: float = 0.25,
                 holonomic: bool = True):
        for name, value in (("cell_size_m", cell_size_m), ("resolution_m", resolution_m),
                            ("robot_radius_m", robot_radius_m), ("nav_speed_m_s", nav_speed_m_s)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if robot_radius_m >= cell_size_m / 2:
            raise ValueError(f"robot_radius_m must be under half a cell ({cell_size_m / 2} m), got {robot_radius_m}")
        self.sim = GridWorldBatch(1, layout=layout, n_goals=n_goals, obstacles=False)  # draws the layouts
        self.walls = self.sim.walls  # (11, 11) bool
        self.seed, self.cell, self.resolution = int(seed), float(cell_size_m), float(resolution_m)
        self.radius, self.nav_speed, self.holonomic = float(robot_radius_m), float(nav_speed_m_s), bool(holonomic)
        self.layout: Layout | None = None
        self.time_s = 0.0
        self.x = self.y = self.yaw = 0.0
        self._velocity = (0.0, 0.0, 0.0)  # body frame, what the last advance achieved
        self._command: tuple[float, float, float] | None = None
        self._command_left_s = 0.0
        self._path: deque[tuple[float, float]] = deque()  # the navigator's waypoints

    # -- geometry --------------------------------------------------------------------------------------
    def cell_centre(self, row: int, col: int) -> tuple[float, float]:
        return (col + 0.5) * self.cell, (MAP_SIZE - 1 - row + 0.5) * self.cell

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the map cell holding (x, y) (may lie off the map)."""
        return MAP_SIZE - 1 - math.floor(y / self.cell), math.floor(x / self.cell)

    def _blocked(self, row: int, col: int) -> bool:
        return not (0 <= row < MAP_SIZE and 0 <= col < MAP_SIZE) or bool(self.walls[row, col])

    def _fits(self, x: float, y: float) -> bool:
        """The disc at (x, y) overlaps no wall cell and stays on the map."""
        r, c = self.cell_of(x, y)
        for row in range(r - 1, r + 2):
            for col in range(c - 1, c + 2):
                if not self._blocked(row, col):
                    continue
                left, bottom = col * self.cell, (MAP_SIZE - 1 - row) * self.cell
                dx = max(left - x, 0.0, x - (left + self.cell))
                dy = max(bottom - y, 0.0, y - (bottom + self.cell))
                if dx * dx + dy * dy < self.radius * self.radius:
                    return False
        return True

    # -- episodes --------------------------------------------------------------------------------------
    def new_episode(self) -> Layout:
        """The next layout (episode ``k``: the simulator's after reset(seed) and ``k`` more
        resets); the robot stands at its start cell's centre facing +x, stopped."""
        episode = 0 if self.layout is None else self.layout.episode + 1
        if episode == 0:
            self.sim.reset(seed=self.seed)
        else:
            self.sim.reset_where(np.ones(1, bool))
        agent = tuple(int(v) for v in self.sim.agent_pos[0])
        goals = tuple(tuple(int(v) for v in g) for g in self.sim.goal_pos[0])
        self.layout = Layout(episode, agent, goals, np.array([self.cell_centre(*g) for g in goals]))
        (self.x, self.y), self.yaw = self.cell_centre(*agent), 0.0
        self.stop()
        return self.layout

    # -- motion ------------------------------------------------------------------------------------------
    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y) m and yaw rad, map frame."""
        return self.x, self.y, self.yaw

    @property
    def velocity(self) -> tuple[float, float, float]:
        """Body-frame (vx, vy) m/s and wz rad/s over the last advance (0 while stopped or blocked)."""
        return self._velocity

    @property
    def moving(self) -> bool:
        return self._command is not None or bool(self._path)

    def stop(self) -> None:
        self._command, self._command_left_s, self._velocity = None, 0.0, (0.0, 0.0, 0.0)
        self._path.clear()

    def command(self, vx: float, vy: float, wz: float, duration_s: float) -> None:
        """Hold body-frame velocity (vx, vy m/s, wz rad/s) for ``duration_s`` simulated
        seconds, then stop (a deadman timeout); replaces any command or navigation. A
        differential-drive robot (``holonomic`` false) ignores ``vy``."""
        _finite("velocity", vx, vy, wz)
        if not (math.isfinite(duration_s) and duration_s > 0):
            raise ValueError(f"duration_s must be a positive number, got {duration_s!r}")
        self.stop()
        self._command = (float(vx), float(vy) if self.holonomic else 0.0, float(wz))
        self._command_left_s = float(duration_s)

    def navigate_to(self, x: float, y: float) -> None:
        """Drive along a shortest 4-connected path of free cells, through their centres,
        then to (x, y), at ``nav_speed_m_s`` (a navigator stand-in); replaces any command."""
        _finite("goal", x, y)
        goal = self.cell_of(x, y)
        if self._blocked(*goal):
            raise ValueError(f"goal ({x:.3f}, {y:.3f}) is in a wall or off the map (cell {goal})")
        cells = self._shortest_path(self.cell_of(self.x, self.y), goal)
        self.stop()
        self._path.extend(self.cell_centre(*c) for c in cells)
        self._path.append((float(x), float(y)))

    def _shortest_path(self, start: tuple[int, int], goal: tuple[int, int]) -> list[tuple[int, int]]:
        """The cells from ``start`` to ``goal`` (both included), breadth first."""
        came_from: dict[tuple[int, int], tuple[int, int] | None] = {start: None}
        frontier = deque([start])
        while frontier:
            cell = frontier.popleft()
            if cell == goal:
                path = []
                while cell is not None:
                    path.append(cell)
                    cell = came_from[cell]
                return path[::-1]
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                nxt = (cell[0] + dr, cell[1] + dc)
                if nxt not in came_from and not self._blocked(*nxt):
                    came_from[nxt] = cell
                    frontier.append(nxt)
        raise ValueError(f"no free path from cell {start} to cell {goal}")

    def advance(self, dt_s: float) -> None:
        """Integrate ``dt_s`` simulated seconds (a command's last interval is clipped to its
        duration, so it moves exactly speed x duration unless a wall stops it)."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive number, got {dt_s!r}")
        x0, y0, yaw0 = self.x, self.y, self.yaw
        if self._command is not None:
            step = min(dt_s, self._command_left_s)
            vx, vy, wz = self._command
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            self._move((vx * c - vy * s) * step, (vx * s + vy * c) * step)
            self.yaw = math.remainder(self.yaw + wz * step, 2 * math.pi)
            self._command_left_s -= step
            if self._command_left_s <= 1e-12:
                self._command = None
        elif self._path:
            budget = self.nav_speed * dt_s
            while self._path and budget > 0:
                tx, ty = self._path[0]
                distance = math.hypot(tx - self.x, ty - self.y)
                if distance <= budget:
                    self.x, self.y = tx, ty
                    self._path.popleft()
                    budget -= distance
                else:
                    self._move((tx - self.x) * budget / distance, (ty - self.y) * budget / distance)
                    budget = 0.0
        dx, dy = self.x - x0, self.y - y0
        c, s = math.cos(yaw0), math.sin(yaw0)
        self._velocity = ((dx * c + dy * s) / dt_s, (-dx * s + dy * c) / dt_s,
                          math.remainder(self.yaw - yaw0, 2 * math.pi) / dt_s)
        self.time_s += dt_s

    def _move(self, dx: float, dy: float) -> None:
        """Translate by (dx, dy), cut at the first contact with a wall."""
        if self._fits(self.x + dx, self.y + dy):
            self.x, self.y = self.x + dx, self.y + dy
            return
        free, blocked = 0.0, 1.0
        for _ in range(40):  # the largest free fraction of the move, to ~1e-12 of it
            mid = (free + blocked) / 2
            free, blocked = (mid, blocked) if self._fits(self.x + mid * dx, self.y + mid * dy) else (free, mid)
        self.x, self.y = self.x + free * dx, self.y + free * dy

    # -- costmaps --------------------------------------------------------------------------------------
    def _costs(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Cost of the points (xs[None, :], ys[:, None]): wall 100, free 0, off the map -1."""
        cols = np.floor(xs / self.cell).astype(np.int64)[None, :]
        rows = (MAP_SIZE - 1 - np.floor(ys / self.cell)).astype(np.int64)[:, None]
        inside = (rows >= 0) & (rows < MAP_SIZE) & (cols >= 0) & (cols < MAP_SIZE)
        wall = self.walls[rows.clip(0, MAP_SIZE - 1), cols.clip(0, MAP_SIZE - 1)]
        return np.where(inside, np.where(wall, WALL_COST, FREE_COST), UNKNOWN_COST).astype(np.int8)

    def _costmap(self, origin_x: float, origin_y: float, width: int, height: int) -> Costmap:
        res = self.resolution
        data = self._costs(origin_x + (np.arange(width) + 0.5) * res, origin_y + (np.arange(height) + 0.5) * res)
        return Costmap((origin_x, origin_y), res, width, height, data)

    def local_costmap(self, size_m: float = 3.0) -> Costmap:
        """A rolling ``size_m`` square window centred on the robot, its origin snapped to
        the resolution grid (as Nav2's rolling local costmap)."""
        if not (math.isfinite(size_m) and size_m > 0):
            raise ValueError(f"size_m must be a positive number, got {size_m!r}")
        cells = max(1, round(size_m / self.resolution))
        res = self.resolution
        return self._costmap(math.floor((self.x - size_m / 2) / res + 1e-9) * res,
                             math.floor((self.y - size_m / 2) / res + 1e-9) * res, cells, cells)

    def global_costmap(self) -> Costmap:
        """The whole map, origin (0, 0)."""
        cells = round(MAP_SIZE * self.cell / self.resolution)
        return self._costmap(0.0, 0.0, cells, cells)
