"""A kinematic robot on the gridworld / four-rooms map: the core of the loopback robot.

Like Nav2's ``nav2_loopback_sim``: no physics, only kinematics, no ROS. Conventions:

* Map frame, metres. Map cell (row ``r``, col ``c``) of the 11x11 map (``MAP_SIZE``) has its
  centre at ``x = (c + 0.5) * cell``, ``y = (MAP_SIZE - 1 - r + 0.5) * cell`` (``cell`` =
  ``cell_size_m``, default 0.25 m): row 0 is the top (the largest y), so the gridworld's "up"
  (row - 1) is +y and "right" (col + 1) is +x. The map covers ``[0, 11 cell] x [0, 11 cell]``.
* Pose ``(x, y, yaw)``: m, m, rad; yaw 0 faces +x, counter-clockwise positive, in (-pi, pi].
  Velocities are body-frame ``(vx, vy, wz)``: m/s forward, m/s to the left, rad/s.
* The robot is a disc of ``robot_radius_m`` (under half a cell, so it fits the one-cell
  corridors); walls and the map's edge stop it at contact.
* Costmaps hold Nav2's ``OccupancyGrid`` values, cell by cell at ``resolution_m`` (default
  0.05 m, 5 costmap cells per map cell): 100 wall, 0 free, -1 outside the map, and with an
  ``inflation_radius_m`` Nav2's inflation costs around the walls (1..98, 99 within
  ``robot_radius_m``; :mod:`hdrqn_ros.robot.nav2_costmap`).
* Frames as on a Nav2 robot (REP 105): the map frame above, an odometry frame ``odom`` and
  the robot's ``base_link``. ``map -> odom`` starts at ``map_to_odom``; odometry reads each
  motion with a relative error ``odom_error`` (distance, rotation), so ``map -> odom``
  drifts while the robot moves, and ``map -> odom -> base_link`` is always the true pose
  (localisation is perfect). A new episode puts the robot at its start; odometry stays
  continuous and ``map -> odom`` jumps, as on an initial pose. Poses ``(x, y, yaw)``
  compose with :func:`compose`.

Each episode's layout (the robot's start cell and the goals' cells) is the simulator's for
the same seed, fires left out (:class:`~hdrqn_ros.envs.grid_batch.GridWorldBatch` with
``obstacles=False``).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from hdrqn_ros.envs.grid_batch import GridWorldBatch
from hdrqn_ros.envs.grid_layout import ACTION_DELTAS, MAP_SIZE
from hdrqn_ros.robot.nav2_costmap import inflate

FREE_COST, WALL_COST, UNKNOWN_COST = 0, 100, -1
Pose2 = tuple[float, float, float]
"""(x m, y m, yaw rad): a pose, or the transform from a child frame to its parent."""


@dataclass(frozen=True)
class Layout:
    """One episode's places."""

    episode: int  # 0, 1, ... since construction
    agent_cell: tuple[int, int]  # (row, col)
    goal_cells: tuple[tuple[int, int], ...]  # (row, col) of goal 0, 1, ...
    goal_xy: np.ndarray  # (n_goals, 2) float, m, map frame: the goal cells' centres


@dataclass(frozen=True)
class Costmap:
    """An OccupancyGrid's content."""

    origin_xy: tuple[float, float]  # m, in the costmap's frame: lower-left corner of cell (0, 0)
    resolution_m: float
    width: int
    height: int
    data: np.ndarray  # (height, width) int8, row 0 at the origin's y (OccupancyGrid row-major order)


def _number(name: str, value, positive: bool = False) -> float:
    """``value`` as a float; ValueError naming ``name`` unless it is a finite (positive) number."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok or not math.isfinite(value) or (positive and value <= 0):
        raise ValueError(f"{name} must be a {'positive' if positive else 'finite'} number, got {value!r}")
    return float(value)


def compose(a: Pose2, b: Pose2) -> Pose2:
    """``a * b``: pose ``b`` given in the frame whose pose is ``a``, expressed in ``a``'s parent."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], math.remainder(a[2] + b[2], 2 * math.pi)


def inverse(a: Pose2) -> Pose2:
    """The pose ``b`` with ``compose(a, b) == (0, 0, 0)``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return -c * a[0] - s * a[1], s * a[0] - c * a[1], math.remainder(-a[2], 2 * math.pi)


def _pose2(name: str, value) -> Pose2:
    """``value`` as (x, y, yaw); ValueError naming ``name`` unless it is three finite numbers."""
    try:
        values = [] if isinstance(value, (str, bytes)) else list(value)
    except TypeError:
        values = []
    if len(values) != 3:
        raise ValueError(f"{name} must be [x, y, yaw] (m, m, rad), got {value!r}")
    x, y, yaw = (_number(name, v) for v in values)
    return x, y, math.remainder(yaw, 2 * math.pi)


def _arc(vx: float, vy: float, wz: float, t: float) -> tuple[float, float]:
    """Body-frame displacement (m) after holding (vx, vy, wz) for ``t`` s (exact, on a circle)."""
    if wz == 0.0:
        return vx * t, vy * t
    along, across = math.sin(wz * t) / wz, 2.0 * math.sin(wz * t / 2) ** 2 / wz  # sin/w, (1 - cos)/w
    return vx * along - vy * across, vx * across + vy * along


class LoopbackWorld:
    """The robot's pose and motion on the map, one episode's layout at a time."""

    def __init__(self, layout: str = "gridworld", n_goals: int = 2, seed: int = 0, *, cell_size_m: float = 0.25,
                 resolution_m: float = 0.05, robot_radius_m: float = 0.12, nav_speed_m_s: float = 0.25,
                 holonomic: bool = True, start_yaw: float = 0.0, map_to_odom: Pose2 = (0.0, 0.0, 0.0),
                 odom_error: tuple[float, float] = (0.0, 0.0), inflation_radius_m: float = 0.0,
                 cost_scaling_factor: float = 3.0):
        if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.cell = _number("cell_size_m", cell_size_m, positive=True)
        self.resolution = _number("resolution_m", resolution_m, positive=True)
        self.radius = _number("robot_radius_m", robot_radius_m, positive=True)
        self.nav_speed = _number("nav_speed_m_s", nav_speed_m_s, positive=True)
        if self.radius >= self.cell / 2:
            raise ValueError(f"robot_radius_m must be under half a cell ({self.cell / 2} m), got {robot_radius_m}")
        if not isinstance(holonomic, (bool, np.bool_)):
            raise ValueError(f"holonomic must be true or false, got {holonomic!r}")
        self.start_yaw = math.remainder(_number("start_yaw", start_yaw), 2 * math.pi)
        self._map_to_odom = _pose2("map_to_odom", map_to_odom)
        if isinstance(odom_error, (str, bytes)) or len(odom_error) != 2:
            raise ValueError(f"odom_error must be [distance, rotation] (relative errors), got {odom_error!r}")
        self.odom_error = tuple(_number("odom_error", e) for e in odom_error)
        if any(abs(e) >= 1 for e in self.odom_error):
            raise ValueError(f"odom_error must be relative errors in (-1, 1), got {odom_error!r}")
        self.inflation_radius = _number("inflation_radius_m", inflation_radius_m)
        self.cost_scaling = _number("cost_scaling_factor", cost_scaling_factor)
        if self.inflation_radius < 0 or self.cost_scaling < 0:
            raise ValueError(f"inflation_radius_m and cost_scaling_factor must be >= 0, got {inflation_radius_m!r} "
                             f"and {cost_scaling_factor!r}")
        self.sim = GridWorldBatch(1, layout=layout, n_goals=n_goals, obstacles=False)  # draws the layouts
        self.walls = self.sim.walls  # (11, 11) bool
        self.seed, self.holonomic = int(seed), bool(holonomic)
        self.layout: Layout | None = None
        self.time_s = 0.0
        self.x = self.y = 0.0
        self.yaw = self.start_yaw
        self._velocity = (0.0, 0.0, 0.0)  # body frame, what the last advance achieved
        self._command: tuple[float, float, float] | None = None
        self._command_left_s = 0.0
        self._path: deque[tuple[float, float]] = deque()  # the navigator's waypoints, m
        self._global: Costmap | None = None
        self._local: tuple[tuple, Costmap] | None = None  # the last local costmap and what it was made of

    # -- geometry --------------------------------------------------------------------------------------
    def cell_centre(self, row: int, col: int) -> tuple[float, float]:
        """(x, y) m of the centre of map cell (row, col)."""
        return (col + 0.5) * self.cell, (MAP_SIZE - 1 - row + 0.5) * self.cell

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the map cell holding (x, y) m (may lie off the map)."""
        return MAP_SIZE - 1 - math.floor(y / self.cell), math.floor(x / self.cell)

    def _blocked(self, row: int, col: int) -> bool:
        return not (0 <= row < MAP_SIZE and 0 <= col < MAP_SIZE) or bool(self.walls[row, col])

    def _fits(self, x: float, y: float) -> bool:
        """The disc at (x, y) overlaps no wall cell and stays on the map (touching is allowed)."""
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
        resets); the robot stands at its start cell's centre facing ``start_yaw``, stopped.
        Odometry does not see the jump (REP 105: ``odom`` is continuous): ``map -> odom``
        moves instead, as AMCL's does on an initial pose."""
        episode = 0 if self.layout is None else self.layout.episode + 1
        if episode == 0:
            self.sim.reset(seed=self.seed)
        else:
            self.sim.reset_where(np.ones(1, bool))
        agent = tuple(int(v) for v in self.sim.agent_pos[0])
        goals = tuple(tuple(int(v) for v in g) for g in self.sim.goal_pos[0])
        odom = self.odom_pose
        self.layout = Layout(episode, agent, goals, np.array([self.cell_centre(*g) for g in goals]))
        (self.x, self.y), self.yaw = self.cell_centre(*agent), self.start_yaw
        if episode > 0:
            self._map_to_odom = compose(self.pose, inverse(odom))
        self.stop()
        return self.layout

    # -- motion ------------------------------------------------------------------------------------------
    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y) m and yaw rad, map frame."""
        return self.x, self.y, self.yaw

    @property
    def map_to_odom(self) -> Pose2:
        """The odometry frame's pose in the map frame (the ``map -> odom`` transform)."""
        return self._map_to_odom

    @property
    def odom_pose(self) -> Pose2:
        """The robot's pose in the odometry frame (the ``odom -> base_link`` transform)."""
        return compose(inverse(self._map_to_odom), self.pose)

    @property
    def velocity(self) -> tuple[float, float, float]:
        """Body-frame (vx, vy) m/s and wz rad/s averaged over the last advance (what odometry
        reports; 0 while stopped or blocked)."""
        return self._velocity

    @property
    def moving(self) -> bool:
        """A command or a navigation is under way."""
        return self._command is not None or bool(self._path)

    def stop(self) -> None:
        """Drop any command and navigation; the robot stands still."""
        self._command, self._command_left_s, self._velocity = None, 0.0, (0.0, 0.0, 0.0)
        self._path.clear()

    def command(self, vx: float, vy: float, wz: float, duration_s: float) -> None:
        """Hold body-frame velocity (vx, vy m/s, wz rad/s) for ``duration_s`` simulated
        seconds from now, then stop (a deadman timeout); replaces any command or navigation.
        A differential-drive robot (``holonomic`` false) ignores ``vy``."""
        velocity = tuple(_number(f"velocity {name}", v) for name, v in (("vx", vx), ("vy", vy), ("wz", wz)))
        duration = _number("duration_s", duration_s, positive=True)
        self.stop()
        self._command = (velocity[0], velocity[1] if self.holonomic else 0.0, velocity[2])
        self._command_left_s = duration

    def navigate_to(self, x: float, y: float) -> None:
        """Drive along a shortest 4-connected path of free cells, through their centres,
        then to (x, y) m, at ``nav_speed_m_s``, and stop there (a navigator stand-in);
        replaces any command or navigation. ValueError for a point in a wall, off the map,
        closer to a wall than ``robot_radius_m`` or unreachable."""
        x, y = _number("goal x", x), _number("goal y", y)
        goal = self.cell_of(x, y)
        if self._blocked(*goal):
            raise ValueError(f"goal ({x:.3f}, {y:.3f}) is in a wall or off the map (cell {goal})")
        if not self._fits(x, y):
            raise ValueError(f"goal ({x:.3f}, {y:.3f}) is closer to a wall than robot_radius_m ({self.radius} m)")
        cells = self._shortest_path(self.cell_of(self.x, self.y), goal)
        self.stop()
        self._path.extend(self.cell_centre(*c) for c in cells)
        self._path.append((x, y))

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
            for dr, dc in ACTION_DELTAS:
                nxt = (cell[0] + dr, cell[1] + dc)
                if nxt not in came_from and not self._blocked(*nxt):
                    came_from[nxt] = cell
                    frontier.append(nxt)
        raise ValueError(f"no free path from cell {start} to cell {goal}")

    def advance(self, dt_s: float) -> None:
        """Integrate ``dt_s`` simulated seconds. A command moves exactly along its circle (or
        line), its last interval clipped to its duration, so the end pose does not depend
        on the tick unless a wall stops it."""
        dt = _number("dt_s", dt_s, positive=True)
        before = self.pose
        if self._command is not None:
            self._velocity = self._follow_command(dt)
        elif self._path:
            self._velocity = self._follow_path(dt)
        else:
            self._velocity = (0.0, 0.0, 0.0)
        self.time_s += dt
        if any(self.odom_error):
            self._odometry_error(before)

    def _odometry_error(self, before: Pose2) -> None:
        """Odometry reads the motion since ``before`` with its relative error, so ``map -> odom``
        moves by what it read wrong."""
        dx, dy, dyaw = compose(inverse(before), self.pose)  # the motion in the body frame at ``before``
        distance, rotation = 1.0 + self.odom_error[0], 1.0 + self.odom_error[1]
        odom_before = compose(inverse(self._map_to_odom), before)
        odom_now = compose(odom_before, (dx * distance, dy * distance, dyaw * rotation))
        self._map_to_odom = compose(self.pose, inverse(odom_now))

    def _follow_command(self, dt: float) -> tuple[float, float, float]:
        step = min(dt, self._command_left_s)
        vx, vy, wz = self._command
        bx, by = _arc(vx, vy, wz, step)
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        done = self._move(bx * c - by * s, bx * s + by * c)  # a wall cuts the chord; turning goes on
        self.yaw = math.remainder(self.yaw + wz * step, 2 * math.pi)
        self._command_left_s -= step
        if self._command_left_s <= 1e-12:
            self._command = None
        return vx * done * step / dt, vy * done * step / dt, wz * step / dt

    def _follow_path(self, dt: float) -> tuple[float, float, float]:
        x0, y0 = self.x, self.y
        budget = self.nav_speed * dt
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
        dx, dy, c, s = self.x - x0, self.y - y0, math.cos(self.yaw), math.sin(self.yaw)
        return (dx * c + dy * s) / dt, (-dx * s + dy * c) / dt, 0.0

    def _move(self, dx: float, dy: float) -> float:
        """Translate by (dx, dy) m, cut at the first contact with a wall; returns the fraction
        moved. Checked in pieces of a quarter radius, so that no move jumps a wall."""
        x0, y0, length = self.x, self.y, math.hypot(dx, dy)
        pieces = max(1, math.ceil(length / (self.radius / 4)))
        free = 0.0
        for i in range(1, pieces + 1):
            blocked = i / pieces
            if not self._fits(x0 + blocked * dx, y0 + blocked * dy):
                for _ in range(40):  # bisect to the contact, to ~1e-12 of the piece
                    mid = (free + blocked) / 2
                    free, blocked = (mid, blocked) if self._fits(x0 + mid * dx, y0 + mid * dy) else (free, mid)
                free = 0.0 if free * length < 1e-9 else free  # already touching: blocked, not creeping
                break
            free = blocked
        self.x, self.y = x0 + free * dx, y0 + free * dy
        return free

    # -- costmaps --------------------------------------------------------------------------------------
    def _costmap(self, origin_x: float, origin_y: float, width: int, height: int,
                 frame_in_map: Pose2 = (0.0, 0.0, 0.0)) -> Costmap:
        """The costmap of the given cells of a frame whose pose in the map is ``frame_in_map``,
        each cell a wall or free as the map at its centre, then inflated."""
        gx, gy = np.meshgrid(origin_x + (np.arange(width) + 0.5) * self.resolution,
                             origin_y + (np.arange(height) + 0.5) * self.resolution)  # (height, width)
        c, s = math.cos(frame_in_map[2]), math.sin(frame_in_map[2])
        xs, ys = frame_in_map[0] + c * gx - s * gy, frame_in_map[1] + s * gx + c * gy
        cols = np.floor(xs / self.cell + 1e-9).astype(np.int64)
        rows = (MAP_SIZE - 1 - np.floor(ys / self.cell + 1e-9)).astype(np.int64)
        inside = (rows >= 0) & (rows < MAP_SIZE) & (cols >= 0) & (cols < MAP_SIZE)
        wall = self.walls[rows.clip(0, MAP_SIZE - 1), cols.clip(0, MAP_SIZE - 1)]
        data = np.where(inside, np.where(wall, WALL_COST, FREE_COST), UNKNOWN_COST).astype(np.int8)
        data = inflate(data, self.resolution, self.radius, self.inflation_radius, self.cost_scaling)
        return Costmap((origin_x, origin_y), self.resolution, width, height, data)

    def local_costmap(self, size_m: float = 3.0, in_odom: bool = False) -> Costmap:
        """A rolling ``size_m`` x ``size_m`` window centred on the robot, in the map frame or
        (``in_odom``) the odometry frame, its origin snapped to the resolution grid (as Nav2's
        rolling local costmap). The same window as the last call's is that costmap again."""
        size = _number("size_m", size_m, positive=True)
        res, cells = self.resolution, max(1, round(size / self.resolution))
        frame = self._map_to_odom if in_odom else (0.0, 0.0, 0.0)
        x, y, _ = compose(inverse(frame), self.pose)
        origin = (math.floor((x - size / 2) / res + 1e-9) * res, math.floor((y - size / 2) / res + 1e-9) * res)
        key = (origin, cells, frame)
        if self._local is None or self._local[0] != key:
            self._local = key, self._costmap(*origin, cells, cells, frame)
        return self._local[1]

    def global_costmap(self) -> Costmap:
        """The whole map, origin (0, 0), in the map frame."""
        if self._global is None:
            cells = round(MAP_SIZE * self.cell / self.resolution)
            self._global = self._costmap(0.0, 0.0, cells, cells)
        return self._global


class AmclUpdates:
    """When an AMCL-like localiser publishes ``/amcl_pose``: on an initial pose, and when its
    filter updates, which it does once odometry moved more than ``update_min_d`` (m) along x
    or y of the odometry frame, or turned more than ``update_min_a`` (rad), since the last
    update (Nav2 AMCL's rule; defaults 0.25 m and 0.2 rad)."""

    def __init__(self, update_min_d: float = 0.25, update_min_a: float = 0.2):
        self.update_min_d = _number("update_min_d", update_min_d)
        self.update_min_a = _number("update_min_a", update_min_a)
        if self.update_min_d < 0 or self.update_min_a < 0:
            raise ValueError(f"update_min_d and update_min_a must be >= 0, got {update_min_d!r}, {update_min_a!r}")
        self._last: Pose2 | None = None  # odometry at the last update

    def initial_pose(self, odom_pose: Pose2) -> None:
        """An initial pose: the filter restarts here (publish now)."""
        self._last = odom_pose

    def due(self, odom_pose: Pose2) -> bool:
        """The filter updates at odometry ``odom_pose`` (publish now); false before any initial pose."""
        if self._last is None:
            return False
        dx, dy = odom_pose[0] - self._last[0], odom_pose[1] - self._last[1]
        dyaw = math.remainder(odom_pose[2] - self._last[2], 2 * math.pi)
        if abs(dx) > self.update_min_d or abs(dy) > self.update_min_d or abs(dyaw) > self.update_min_a:
            self._last = odom_pose
            return True
        return False
