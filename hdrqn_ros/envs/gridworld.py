"""Multiple goals in a gridworld / four-rooms (thesis section 4.1.1), vectorised with numpy.

:class:`GridWorldBatch` steps ``N`` environments as one numpy operation (the
:class:`~hdrqn_ros.envs.domain.DomainBatch` contract); :class:`GridWorldEnv` is the single
``gymnasium.Env``, a view of a batch of one. See ``docs/environments.md`` for the rules.

Internals: each environment keeps a *padded code canvas*: the 11x11 map surrounded by a
5-cell margin of "outside" cells (a 21x21 array, flattened), so that every egocentric
window (3, 5 or 11 cells) is a plain slice of it, plus the same canvas in RGB. A step only
rewrites the few cells that changed; an observation is a gather of the ``view x view``
window of the RGB canvas followed by a nearest-neighbour upscale to 44x44 (pixel ``i``
shows window cell ``floor(i * view / 44)``), done as two ``np.repeat`` calls.
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from hdrqn_ros.critic import GRID_CRITIC, InternalCritic
from hdrqn_ros.envs.domain import NO_SUBGOAL, OBS_SIZE, StepBatch, check_actions

# --------------------------------------------------------------------------- constants
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
_DELTA_FLAT = tuple(dr * CANVAS + dc for dr, dc in ACTION_DELTAS)
_DELTA_ARR = np.array(_DELTA_FLAT, dtype=np.intp)
LAYOUTS = ("gridworld", "fourrooms")
VIEWS = (3, 5, 11, "full")
FOURROOMS_DOORS = ((3, 5), (7, 5), (5, 3), (5, 7))
RENDER_CELL_PX = 32
"""Pixels per cell of ``render()`` (``render_mode='rgb_array'``)."""


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


def _pad_index(r, c):
    """Flat index in the padded canvas of map cell ``(r, c)``."""
    return (np.asarray(r) + PAD) * CANVAS + (np.asarray(c) + PAD)


def _upscale_counts(view_cells: int) -> np.ndarray:
    """How many of the 44 pixels show each of the ``view_cells`` window cells."""
    return np.bincount((np.arange(OBS_SIZE) * view_cells) // OBS_SIZE, minlength=view_cells)


_WINDOW_TABLES: dict = {}


def _window_table(view) -> np.ndarray:
    """``(121, v*v) intp``: for each map cell (``r*11+c``) the padded-canvas indices of the
    window centred on it, row-major (for ``'full'`` every row is the whole map)."""
    if view not in _WINDOW_TABLES:
        if view == "full":
            rows, cols = np.meshgrid(np.arange(MAP_SIZE), np.arange(MAP_SIZE), indexing="ij")
            one = _pad_index(rows, cols).reshape(-1)
            table = np.repeat(one[None, :], MAP_SIZE * MAP_SIZE, axis=0)
        else:
            h = view // 2
            d = np.arange(-h, h + 1)
            dr, dc = np.meshgrid(d, d, indexing="ij")
            cells = np.arange(MAP_SIZE * MAP_SIZE)
            r, c = cells // MAP_SIZE, cells % MAP_SIZE
            table = _pad_index(r[:, None] + dr.reshape(1, -1), c[:, None] + dc.reshape(1, -1))
        _WINDOW_TABLES[view] = np.ascontiguousarray(table, dtype=np.intp)
    return _WINDOW_TABLES[view]


# map from padded flat index to map cell id r*11+c (-1 outside the map)
_PAD_TO_CELL = np.full(CANVAS_CELLS, -1, dtype=np.intp)
for _r in range(MAP_SIZE):
    for _c in range(MAP_SIZE):
        _PAD_TO_CELL[int(_pad_index(_r, _c))] = _r * MAP_SIZE + _c
del _r, _c


def _check_view(view):
    if isinstance(view, str):
        if view != "full":
            raise ValueError(f"invalid view {view!r}; expected one of {VIEWS}")
        return view
    if isinstance(view, (bool, np.bool_)) or not isinstance(view, (int, np.integer)) or int(view) not in (3, 5, 11):
        raise ValueError(f"invalid view {view!r}; expected one of {VIEWS}")
    return int(view)


# --------------------------------------------------------------------------- batch core
class GridWorldBatch:
    """``num_envs`` multi-goal gridworld / four-rooms environments stepped together.

    Parameters: ``layout`` 'gridworld' or 'fourrooms'; ``n_goals`` 2 or 3; ``view`` the
    side of the agent-centred window in cells (3, 5, 11) or ``'full'`` (the whole map,
    allocentric); ``max_steps`` the step limit (default 50, or 100 for three goals in
    four-rooms).

    Stepping an environment whose episode is over raises ``RuntimeError`` (there is no
    auto-reset; use :meth:`reset_where`). Env ``i`` of a batch reset with seed ``s`` draws
    from its own generator seeded with ``s + i``.
    """

    num_actions = len(ACTIONS)

    def __init__(self, num_envs: int = 1, layout: str = "gridworld", n_goals: int = 2, view=5,
                 max_steps: int | None = None):
        if isinstance(num_envs, (bool, np.bool_)) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
        if isinstance(n_goals, (bool, np.bool_)) or n_goals not in (2, 3):
            raise ValueError(f"n_goals must be 2 or 3, got {n_goals!r}")
        self.view = _check_view(view)
        if max_steps is None:
            max_steps = default_max_steps(layout, int(n_goals))
        elif isinstance(max_steps, (bool, np.bool_)) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer or None, got {max_steps!r}")
        self.num_envs = N = int(num_envs)
        self.layout = layout
        self.n_goals = G = int(n_goals)
        self.num_subgoals = G
        self.subgoal_names = GOAL_NAMES[:G]
        # every goal can be walked to from every other one
        self.subgoal_neighbours = tuple(tuple(h for h in range(G) if h != g) for g in range(G))
        self.max_steps = int(max_steps)
        self.walls = layout_walls(layout)

        base = np.full(CANVAS_CELLS, OUTSIDE, dtype=np.uint8)
        base[_pad_index(*np.nonzero(np.ones_like(self.walls)))] = FREE
        base[_pad_index(*np.nonzero(self.walls))] = WALL
        self._base_codes = base
        self._base_rgb = PALETTE[base]
        self._free_cells = np.sort(_pad_index(*np.nonzero(~self.walls))).astype(np.intp)

        self._win = _window_table(self.view)
        v = MAP_SIZE if self.view == "full" else self.view
        self._v = v
        self._counts = _upscale_counts(v)
        self._row_off = np.arange(N, dtype=np.intp) * CANVAS_CELLS

        # state (positions are flat indices into the padded canvas)
        self._codes = np.tile(base, (N, 1))
        self._codes_flat = self._codes.reshape(-1)
        self._rgb = np.tile(self._base_rgb, (N, 1))  # (N*441, 3)
        self._agent = np.zeros(N, dtype=np.intp)
        self._goals = np.zeros((N, G), dtype=np.intp)
        self._fires = np.zeros((N, NUM_OBSTACLES), dtype=np.intp)
        self._collected = np.zeros((N, G), dtype=bool)
        self._n_collected = np.zeros(N, dtype=np.int64)
        self._in_order = np.ones(N, dtype=bool)
        self._next_goal = np.zeros(N, dtype=np.int64)
        self._t = np.zeros(N, dtype=np.int64)
        self._done = np.ones(N, dtype=bool)  # not reset yet
        self._rngs = [np.random.default_rng() for _ in range(N)]
        self._critic = GRID_CRITIC

    # ----------------------------------------------------------------- public state
    @property
    def agent_pos(self) -> np.ndarray:
        """``(N, 2) int32``: (row, col) of each agent on the 11x11 map."""
        return self._rowcol(self._agent)

    @property
    def goal_pos(self) -> np.ndarray:
        """``(N, n_goals, 2) int32``: (row, col) of each goal (kept after collection)."""
        return self._rowcol(self._goals)

    @property
    def obstacle_pos(self) -> np.ndarray:
        """``(N, 2, 2) int32``: (row, col) of each obstacle (fire)."""
        return self._rowcol(self._fires)

    @property
    def goals_collected(self) -> np.ndarray:
        """``(N, n_goals) bool``: which goals have been collected this episode."""
        return self._collected.copy()

    @property
    def next_goal(self) -> np.ndarray:
        """``(N,) int64``: the lowest-index goal not yet collected (the one to collect next
        in the right order); ``n_goals`` once all are collected."""
        return self._next_goal.copy()

    @property
    def in_order(self) -> np.ndarray:
        """``(N,) bool``: every goal so far was collected in the right order."""
        return self._in_order.copy()

    @property
    def steps(self) -> np.ndarray:
        """``(N,) int64``: steps taken in the current episode."""
        return self._t.copy()

    @property
    def done(self) -> np.ndarray:
        """``(N,) bool``: the episode is over (or the env was never reset)."""
        return self._done.copy()

    def codes(self) -> np.ndarray:
        """``(N, 11, 11) uint8``: the map as cell codes (FREE, WALL, GOAL0+g, FIRE, AGENT)."""
        c = self._codes.reshape(self.num_envs, CANVAS, CANVAS)
        return c[:, PAD:PAD + MAP_SIZE, PAD:PAD + MAP_SIZE].copy()

    @staticmethod
    def _rowcol(flat) -> np.ndarray:
        flat = np.asarray(flat)
        return np.stack([flat // CANVAS - PAD, flat % CANVAS - PAD], axis=-1).astype(np.int32)

    def critic(self) -> InternalCritic:
        return self._critic

    # ----------------------------------------------------------------- resets
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start a new episode in every env. With ``seed``, env ``i`` is re-seeded with
        ``seed + i``; without, each env's generator continues. Returns ``(N, 44, 44, 3)``."""
        if seed is not None:
            if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
                raise ValueError(f"seed must be a non-negative integer or None, got {seed!r}")
            self._rngs = [np.random.default_rng(int(seed) + i) for i in range(self.num_envs)]
        for i in range(self.num_envs):
            self._reset_env(i)
        return self.render_obs()

    def reset_where(self, mask) -> np.ndarray:
        """Start a new episode in the envs where ``mask`` (``(N,) bool``); returns all ``N``
        current observations."""
        m = np.asarray(mask)
        if m.shape != (self.num_envs,):
            raise ValueError(f"mask must have shape ({self.num_envs},), got {m.shape}")
        if m.dtype != bool:
            raise ValueError(f"mask must be boolean, got dtype {m.dtype}")
        for i in np.flatnonzero(m):
            self._reset_env(int(i))
        return self.render_obs()

    def _reset_env(self, i: int) -> None:
        G = self.n_goals
        rng = self._rngs[i]
        cells = self._free_cells[rng.choice(len(self._free_cells), size=1 + G + NUM_OBSTACLES, replace=False)]
        self._place(i, int(cells[0]), cells[1:1 + G], cells[1 + G:], np.zeros(G, dtype=bool))

    def _place(self, i, agent, goals, fires, collected) -> None:
        """Rebuild env ``i``'s canvas from positions (padded flat indices)."""
        codes = self._codes[i]
        codes[:] = self._base_codes
        for g in range(self.n_goals):
            if not collected[g]:
                codes[goals[g]] = GOAL0 + g
        codes[fires] = FIRE
        codes[agent] = AGENT
        self._rgb[i * CANVAS_CELLS:(i + 1) * CANVAS_CELLS] = PALETTE[codes]
        self._agent[i] = agent
        self._goals[i] = goals
        self._fires[i] = fires
        self._collected[i] = collected
        self._n_collected[i] = int(np.count_nonzero(collected))
        self._in_order[i] = bool(np.all(collected[: self._n_collected[i]]))
        self._next_goal[i] = int(np.argmin(collected)) if not collected.all() else self.n_goals
        self._t[i] = 0
        self._done[i] = False

    def set_state(self, i: int, agent, goals, obstacles, collected=None, steps: int = 0) -> None:
        """Put env ``i`` in a hand-built state (for tests and demos): ``agent`` (row, col),
        ``goals`` ``n_goals`` (row, col), ``obstacles`` two (row, col), ``collected`` which
        goals are already collected (``in_order`` is set as if they were collected in order
        when they form a prefix). All cells must be distinct free cells (a collected goal's
        cell may hold another object)."""
        G = self.n_goals
        goals = np.asarray(goals, dtype=np.intp).reshape(-1, 2)
        obstacles = np.asarray(obstacles, dtype=np.intp).reshape(-1, 2)
        agent = np.asarray(agent, dtype=np.intp).reshape(2)
        if goals.shape != (G, 2):
            raise ValueError(f"goals must be {G} (row, col) pairs, got shape {goals.shape}")
        if obstacles.shape != (NUM_OBSTACLES, 2):
            raise ValueError(f"obstacles must be {NUM_OBSTACLES} (row, col) pairs, got shape {obstacles.shape}")
        collected = np.zeros(G, dtype=bool) if collected is None else np.asarray(collected, dtype=bool).reshape(G)
        live = [tuple(agent)] + [tuple(p) for p in obstacles] + [tuple(g) for g, c in zip(goals, collected) if not c]
        all_cells = live + [tuple(g) for g in goals]
        for r, c in all_cells:
            if not (0 <= r < MAP_SIZE and 0 <= c < MAP_SIZE) or self.walls[r, c]:
                raise ValueError(f"cell {(int(r), int(c))} is not a free cell of the {self.layout} map")
        if len(set(live)) != len(live):
            raise ValueError(f"objects must be on distinct cells, got {live}")
        self._place(int(i), int(_pad_index(*agent)), _pad_index(goals[:, 0], goals[:, 1]),
                    _pad_index(obstacles[:, 0], obstacles[:, 1]), collected)
        self._t[i] = int(steps)

    # ----------------------------------------------------------------- step
    def step(self, actions) -> StepBatch:
        """Move every agent (0 up, 1 down, 2 left, 3 right) and report the outcome."""
        N = self.num_envs
        a = check_actions(actions, N, 4)
        if self._done.any():
            raise RuntimeError(
                f"env(s) {np.flatnonzero(self._done).tolist()} are done (or were never reset); "
                "call reset_where(done) before stepping them again"
            )
        off = self._row_off
        old = self._agent
        new = old + _DELTA_ARR[a]
        cf = self._codes_flat
        cell = cf[off + new]
        wall = cell == WALL
        if wall.any():
            new = np.where(wall, old, new)
            cell = np.where(wall, AGENT, cell)
        cf[off + old] = FREE
        cf[off + new] = AGENT
        rgb = self._rgb
        rgb[off + old] = PALETTE[FREE]
        rgb[off + new] = PALETTE[AGENT]
        self._agent = new

        hit = cell == FIRE
        is_goal = (cell >= GOAL0) & (cell < GOAL0 + self.n_goals)
        on_goal = self._goals == new[:, None]  # (N, G): a goal's cell, collected or not
        at = np.where(on_goal.any(axis=1), on_goal.argmax(axis=1), NO_SUBGOAL).astype(np.int32)
        extrinsic = np.zeros(N, dtype=np.float32)
        if is_goal.any():
            idx = np.flatnonzero(is_goal)
            k = cell[idx].astype(np.int64) - GOAL0
            right = (k == self._n_collected[idx]) & (k == self._next_goal[idx])
            extrinsic[idx] = np.where(right, 1.0, 0.01)
            self._collected[idx, k] = True
            self._n_collected[idx] += 1
            self._in_order[idx] &= right
            col = self._collected[idx]
            self._next_goal[idx] = np.where(col.all(axis=1), self.n_goals, np.argmin(col, axis=1))
        if hit.any():
            for i in np.flatnonzero(hit):
                i = int(i)
                self._respawn_fire(i, 0 if self._fires[i, 0] == new[i] else 1)
        classical = extrinsic - hit.astype(np.float32)
        self._t += 1
        terminated = self._n_collected == self.n_goals
        truncated = (self._t >= self.max_steps) & ~terminated
        self._done = terminated | truncated
        return StepBatch(
            obs=self.render_obs(),
            classical=classical,
            extrinsic=extrinsic,
            terminated=terminated,
            truncated=truncated,
            agent_pos=self._rowcol(new),
            at_subgoal=at,
            collected=is_goal,
            hit_obstacle=hit,
            life_lost=np.zeros(N, dtype=bool),
            success=terminated & self._in_order,
        )

    def _respawn_fire(self, i: int, j: int) -> None:
        """Move obstacle ``j`` of env ``i`` (which the agent just stepped on) to a random
        free cell: not a wall, the agent, a remaining goal or the other obstacle."""
        codes = self._codes[i]
        cands = self._free_cells[codes[self._free_cells] == FREE]
        p = int(cands[self._rngs[i].integers(len(cands))])
        self._fires[i, j] = p
        codes[p] = FIRE
        self._rgb[i * CANVAS_CELLS + p] = PALETTE[FIRE]

    def step_one(self, action):
        """The lean path of a batch of one (used by :class:`GridWorldEnv`): the same rules
        as :meth:`step`, on Python scalars. Returns ``(obs, classical, extrinsic,
        terminated, truncated, at_subgoal, collected, hit_obstacle, success)``."""
        if self.num_envs != 1:
            raise ValueError(f"step_one needs a batch of one, this one has {self.num_envs} envs")
        if type(action) is not int:
            action = int(check_actions(action, 1, 4)[0])
        elif not 0 <= action < 4:
            raise ValueError(f"action {action} out of range [0, 4)")
        if self._done[0]:
            raise RuntimeError("the episode is over (or the env was never reset); call reset() first")
        codes = self._codes[0]
        old = int(self._agent[0])
        new = old + _DELTA_FLAT[action]
        cell = int(codes[new])
        if cell == WALL:
            new, cell = old, AGENT
        codes[old] = FREE
        codes[new] = AGENT
        rgb = self._rgb
        rgb[old] = PALETTE[FREE]
        rgb[new] = PALETTE[AGENT]
        self._agent[0] = new
        goals = self._goals[0]
        at = next((g for g in range(self.n_goals) if goals[g] == new), NO_SUBGOAL)
        extrinsic = 0.0
        hit = cell == FIRE
        collected = GOAL0 <= cell < GOAL0 + self.n_goals
        if hit:
            self._respawn_fire(0, 0 if self._fires[0, 0] == new else 1)
        elif collected:
            n = int(self._n_collected[0])
            right = at == n and at == int(self._next_goal[0])
            extrinsic = 1.0 if right else 0.01
            col = self._collected[0]
            col[at] = True
            self._n_collected[0] = n + 1
            if not right:
                self._in_order[0] = False
            if at == self._next_goal[0]:
                nxt = at + 1
                while nxt < self.n_goals and col[nxt]:
                    nxt += 1
                self._next_goal[0] = nxt
        t = int(self._t[0]) + 1
        self._t[0] = t
        terminated = int(self._n_collected[0]) == self.n_goals
        truncated = (not terminated) and t >= self.max_steps
        self._done[0] = terminated or truncated
        cls = float(np.float32(extrinsic)) - (1.0 if hit else 0.0)
        return (self._render_one(new), cls, float(np.float32(extrinsic)), terminated, truncated, at, collected,
                hit, terminated and bool(self._in_order[0]))

    # ----------------------------------------------------------------- rendering
    def _render_cells(self, cell_ids: np.ndarray) -> np.ndarray:
        """Windows centred on map cells ``cell_ids`` (N,) of each env -> (N, 44, 44, 3)."""
        N, v, k = self.num_envs, self._v, self._counts
        ix = self._win[cell_ids]
        ix += self._row_off[:, None]
        w = self._rgb.take(ix, axis=0).reshape(N, v, v, 3)
        return np.repeat(np.repeat(w, k, axis=2), k, axis=1)

    def _render_one(self, center: int) -> np.ndarray:
        v, k = self._v, self._counts
        w = self._rgb.take(self._win[_PAD_TO_CELL[center]], axis=0).reshape(v, v, 3)
        return np.repeat(np.repeat(w, k, axis=1), k, axis=0)

    def render_obs(self) -> np.ndarray:
        """``(N, 44, 44, 3) uint8``: each env's current observation."""
        return self._render_cells(_PAD_TO_CELL[self._agent])

    def subgoal_images(self, subgoals) -> np.ndarray:
        """``(N, 44, 44, 3) uint8``: the current state rendered with the same view, centred
        on goal ``subgoals[i]`` of env ``i`` (its cell is remembered after collection; a
        collected goal is no longer drawn). With ``view='full'`` it is the full map."""
        s = np.asarray(subgoals)
        if s.shape == () and self.num_envs == 1:
            s = s.reshape(1)
        if s.shape != (self.num_envs,):
            raise ValueError(f"subgoals must have shape ({self.num_envs},), got {s.shape}")
        if not np.issubdtype(s.dtype, np.integer) or ((s < 0) | (s >= self.n_goals)).any():
            raise ValueError(f"subgoals must be integers in [0, {self.n_goals}), got {s.tolist()}")
        centers = self._goals[np.arange(self.num_envs), s]
        return self._render_cells(_PAD_TO_CELL[centers])

    def render_map(self, i: int = 0, cell_px: int = RENDER_CELL_PX) -> np.ndarray:
        """``(11*cell_px, 11*cell_px, 3) uint8``: env ``i``'s whole map, allocentric."""
        rgb = self._rgb[i * CANVAS_CELLS:(i + 1) * CANVAS_CELLS].reshape(CANVAS, CANVAS, 3)
        m = rgb[PAD:PAD + MAP_SIZE, PAD:PAD + MAP_SIZE]
        return np.repeat(np.repeat(m, cell_px, axis=0), cell_px, axis=1)


# --------------------------------------------------------------------------- single env
class GridWorldEnv(gym.Env):
    """One multi-goal gridworld / four-rooms environment (a view of a batch of one).

    Observation: ``(44, 44, 3) uint8`` RGB agent-centred window; actions: 0 up, 1 down,
    2 left, 3 right. ``reward`` is the classical reward (eq. 4.3); ``info`` carries
    ``extrinsic`` (eq. 4.2), ``intrinsic`` (eq. 4.1, for the current subgoal, see
    :meth:`set_subgoal`), ``subgoal_reached``, ``at_subgoal``, ``hit_obstacle``,
    ``life_lost``, ``agent_pos``, ``success`` (and ``classical``, ``subgoal``).
    When the current subgoal is reached the subgoal becomes the next goal in order.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 8}

    def __init__(self, layout: str = "gridworld", n_goals: int = 2, view=5, max_steps: int | None = None,
                 render_mode: str | None = None):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.batch = GridWorldBatch(1, layout=layout, n_goals=n_goals, view=view, max_steps=max_steps)
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(0, 255, (OBS_SIZE, OBS_SIZE, 3), np.uint8)
        self.action_space = gym.spaces.Discrete(4)
        c = self.batch.critic()
        self._crit = (float(c.goal_reward), float(c.wrong_subgoal_penalty), float(c.obstacle_penalty))
        self._subgoal = 0

    @property
    def subgoal(self) -> int:
        """The goal index the current option pursues."""
        return self._subgoal

    @property
    def next_goal(self) -> int:
        return int(self.batch._next_goal[0])

    def set_subgoal(self, g: int) -> None:
        """Set the current subgoal (goal index in ``[0, n_goals)``)."""
        if isinstance(g, (bool, np.bool_)) or not isinstance(g, (int, np.integer)) or not 0 <= g < self.batch.n_goals:
            raise ValueError(f"subgoal must be an integer in [0, {self.batch.n_goals}), got {g!r}")
        self._subgoal = int(g)

    def subgoal_image(self, g: int | None = None) -> np.ndarray:
        """``(44, 44, 3) uint8``: the goal-centred image of goal ``g`` (default: the current
        subgoal)."""
        if g is None:
            g = self._subgoal
        elif isinstance(g, (bool, np.bool_)) or not isinstance(g, (int, np.integer)) or not 0 <= g < self.batch.n_goals:
            raise ValueError(f"subgoal must be an integer in [0, {self.batch.n_goals}), got {g!r}")
        return self.batch.subgoal_images(np.array([g]))[0]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs = self.batch.reset(seed)[0]
        self._subgoal = min(self.next_goal, self.batch.n_goals - 1)
        info = {
            "extrinsic": 0.0, "classical": 0.0, "intrinsic": 0.0, "subgoal_reached": False,
            "at_subgoal": NO_SUBGOAL, "hit_obstacle": False, "life_lost": False,
            "agent_pos": self.batch.agent_pos[0], "success": False, "subgoal": self._subgoal,
        }
        return obs, info

    def step(self, action):
        b = self.batch
        obs, classical, extrinsic, terminated, truncated, at, collected, hit, success = b.step_one(action)
        goal_r, wrong_r, obst_r = self._crit
        reached = at == self._subgoal
        intrinsic = goal_r if reached else (wrong_r if collected else 0.0)
        if hit:
            intrinsic += obst_r
        if reached:
            self._subgoal = min(int(b._next_goal[0]), b.n_goals - 1)
        p = int(b._agent[0])
        info = {
            "extrinsic": extrinsic, "classical": classical, "intrinsic": intrinsic, "subgoal_reached": reached,
            "at_subgoal": at, "hit_obstacle": hit, "life_lost": False,
            "agent_pos": np.array((p // CANVAS - PAD, p % CANVAS - PAD), dtype=np.int32),
            "success": success, "subgoal": self._subgoal,
        }
        return obs, classical, terminated, truncated, info

    def render(self):
        if self.render_mode == "rgb_array":
            return self.batch.render_map(0)
        return None
