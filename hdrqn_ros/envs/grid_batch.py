"""The gridworld / four-rooms batch core: :class:`GridWorldBatch` steps ``N`` environments
as one numpy operation (the :class:`~hdrqn_ros.envs.domain.DomainBatch` contract).

State lives in padded canvases (:mod:`~hdrqn_ros.envs.grid_layout`), one row per env, in
codes and in RGB; a step only rewrites the few cells that changed, and observations are
windows of the RGB canvas (:mod:`~hdrqn_ros.envs.grid_render`). What collecting a goal does
is one table (:mod:`~hdrqn_ros.envs.grid_rules`) that the vectorised :meth:`~GridWorldBatch.step`
and the scalar :meth:`~GridWorldBatch.step_one` (the single env's fast path) both read.
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.envs.critic import GRID_CRITIC, InternalCritic
from hdrqn_ros.envs.domain import NO_SUBGOAL, StepBatch, check_actions
from hdrqn_ros.envs.grid_layout import (ACTIONS, AGENT, CANVAS, CANVAS_CELLS, DELTA_FLAT, FIRE, FREE, GOAL0,
                                        GOAL_NAMES, LAYOUTS, MAP_SIZE, NUM_OBSTACLES, OUTSIDE, PAD, PALETTE, WALL,
                                        check_view, default_max_steps, layout_walls, pad_index, rowcol)
from hdrqn_ros.envs.grid_render import RENDER_CELL_PX, WindowRenderer, render_map
from hdrqn_ros.envs.grid_rules import GOAL_RULES

_DELTA_ARR = np.array(DELTA_FLAT, dtype=np.intp)


class GridWorldBatch:
    """``num_envs`` multi-goal gridworld / four-rooms environments stepped together.

    Parameters: ``layout`` 'gridworld' or 'fourrooms'; ``n_goals`` 2 or 3; ``view`` the
    side of the agent-centred window in cells (3, 5, 11) or ``'full'`` (the whole map,
    allocentric); ``max_steps`` the step limit (default 50, or 100 for three goals in
    four-rooms); ``obstacles`` False: no fires (the layouts of agent and goals stay those
    the same seed draws with fires: the fires' cells are drawn and left free; for
    comparing with a robot, which has no fire).

    Stepping an environment whose episode is over raises ``RuntimeError`` (there is no
    auto-reset; use :meth:`reset_where`). Env ``i`` of a batch reset with seed ``s`` draws
    from its own generator seeded with ``s + i``.
    """

    num_actions = len(ACTIONS)

    def __init__(self, num_envs: int = 1, layout: str = "gridworld", n_goals: int = 2, view=5,
                 max_steps: int | None = None, obstacles: bool = True):
        if isinstance(num_envs, (bool, np.bool_)) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; expected one of {LAYOUTS}")
        if isinstance(n_goals, (bool, np.bool_)) or n_goals not in (2, 3):
            raise ValueError(f"n_goals must be 2 or 3, got {n_goals!r}")
        self.view = check_view(view)
        if max_steps is None:
            max_steps = default_max_steps(layout, int(n_goals))
        elif isinstance(max_steps, (bool, np.bool_)) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer or None, got {max_steps!r}")
        self.num_envs = N = int(num_envs)
        self.layout = layout
        self.n_goals = G = int(n_goals)
        self.num_subgoals = G
        self.return_bound = float(G)  # +1 per goal, each collected once
        self.subgoal_names = GOAL_NAMES[:G]
        # every goal can be walked to from every other one
        self.subgoal_neighbours = tuple(tuple(h for h in range(G) if h != g) for g in range(G))
        self.max_steps = int(max_steps)
        if not isinstance(obstacles, (bool, np.bool_)):
            raise ValueError(f"obstacles must be true or false, got {obstacles!r}")
        self.num_obstacles = NUM_OBSTACLES if obstacles else 0
        self.walls = layout_walls(layout)

        base = np.full(CANVAS_CELLS, OUTSIDE, dtype=np.uint8)
        base[pad_index(*np.nonzero(np.ones_like(self.walls)))] = FREE
        base[pad_index(*np.nonzero(self.walls))] = WALL
        self._base_codes = base
        self._base_rgb = PALETTE[base]
        self._free_cells = np.sort(pad_index(*np.nonzero(~self.walls))).astype(np.intp)
        self._renderer = WindowRenderer(self.view, N)
        self._row_off = np.arange(N, dtype=np.intp) * CANVAS_CELLS
        self._rules = GOAL_RULES[G]

        # state (positions are flat indices into the padded canvas)
        self._codes = np.tile(base, (N, 1))
        self._codes_flat = self._codes.reshape(-1)
        self._rgb = np.tile(self._base_rgb, (N, 1))  # (N*441, 3)
        self._agent = np.zeros(N, dtype=np.intp)
        self._goals = np.zeros((N, G), dtype=np.intp)
        self._fires = np.zeros((N, self.num_obstacles), dtype=np.intp)
        self._mask = np.zeros(N, dtype=np.int64)  # goals collected, bit g: goal g (see GoalRules)
        self._in_order = np.ones(N, dtype=bool)
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
        """``(N, num_obstacles, 2) int32``: (row, col) of each obstacle (fire; none without obstacles)."""
        return self._rowcol(self._fires)

    @property
    def goals_collected(self) -> np.ndarray:
        """``(N, n_goals) bool``: which goals have been collected this episode."""
        return self._rules.collected[self._mask]

    @property
    def next_goal(self) -> np.ndarray:
        """``(N,) int64``: the lowest-index goal not yet collected (the one to collect next
        in the right order); ``n_goals`` once all are collected."""
        return self._rules.next_goal[self._mask]

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

    _rowcol = staticmethod(rowcol)

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
        self._place(i, int(cells[0]), cells[1:1 + G], cells[1 + G:1 + G + self.num_obstacles], np.zeros(G, dtype=bool))

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
        self._mask[i] = int(collected @ self._rules.bit_values)
        self._in_order[i] = bool(np.all(collected[: np.count_nonzero(collected)]))
        self._t[i] = 0
        self._done[i] = False

    def set_state(self, i: int, agent, goals, obstacles, collected=None, steps: int = 0) -> None:
        """Put env ``i`` in a hand-built state (for tests and demos): ``agent`` (row, col),
        ``goals`` ``n_goals`` (row, col), ``obstacles`` two (row, col) (none without
        obstacles), ``collected`` which
        goals are already collected (``in_order`` is set as if they were collected in order
        when they form a prefix). All cells must be distinct free cells (a collected goal's
        cell may hold another object)."""
        G = self.n_goals
        goals = np.asarray(goals, dtype=np.intp).reshape(-1, 2)
        obstacles = np.asarray(obstacles, dtype=np.intp).reshape(-1, 2)
        agent = np.asarray(agent, dtype=np.intp).reshape(2)
        if goals.shape != (G, 2):
            raise ValueError(f"goals must be {G} (row, col) pairs, got shape {goals.shape}")
        if obstacles.shape != (self.num_obstacles, 2):
            raise ValueError(f"obstacles must be {self.num_obstacles} (row, col) pairs, got shape {obstacles.shape}")
        collected = np.zeros(G, dtype=bool) if collected is None else np.asarray(collected, dtype=bool).reshape(G)
        live = [tuple(agent)] + [tuple(p) for p in obstacles] + [tuple(g) for g, c in zip(goals, collected) if not c]
        all_cells = live + [tuple(g) for g in goals]
        for r, c in all_cells:
            if not (0 <= r < MAP_SIZE and 0 <= c < MAP_SIZE) or self.walls[r, c]:
                raise ValueError(f"cell {(int(r), int(c))} is not a free cell of the {self.layout} map")
        if len(set(live)) != len(live):
            raise ValueError(f"objects must be on distinct cells, got {live}")
        self._place(int(i), int(pad_index(*agent)), pad_index(goals[:, 0], goals[:, 1]),
                    pad_index(obstacles[:, 0], obstacles[:, 1]), collected)
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
        if is_goal.any():  # the goal rules (GoalRules), as step_one reads them
            idx = np.flatnonzero(is_goal)
            k = cell[idx].astype(np.int64) - GOAL0
            m = self._mask[idx]
            extrinsic[idx] = self._rules.extrinsic[m, k]
            self._in_order[idx] &= self._rules.right[m, k]
            self._mask[idx] = m | (1 << k)
        if hit.any():
            for i in np.flatnonzero(hit):
                i = int(i)
                self._respawn_fire(i, 0 if self._fires[i, 0] == new[i] else 1)
        classical = extrinsic - hit.astype(np.float32)
        self._t += 1
        terminated = self._mask == self._rules.all_collected
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
        as :meth:`step` (the same :class:`GoalRules` tables), on Python scalars. Returns
        ``(obs, classical, extrinsic, terminated, truncated, at_subgoal, collected,
        hit_obstacle, success, agent_pos)``."""
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
        new = old + DELTA_FLAT[action]
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
        rules = self._rules
        if hit:
            self._respawn_fire(0, 0 if self._fires[0, 0] == new else 1)
        elif collected:  # the goal rules, as step reads them
            m, k = int(self._mask[0]), cell - GOAL0
            extrinsic = rules.extrinsic_py[m][k]
            if not rules.right_py[m][k]:
                self._in_order[0] = False
            self._mask[0] = m | (1 << k)
        t = int(self._t[0]) + 1
        self._t[0] = t
        terminated = int(self._mask[0]) == rules.all_collected
        truncated = (not terminated) and t >= self.max_steps
        self._done[0] = terminated or truncated
        pos = np.array((new // CANVAS - PAD, new % CANVAS - PAD), dtype=np.int32)
        return (self._renderer.window_one(self._rgb, new), extrinsic - (1.0 if hit else 0.0), extrinsic,
                terminated, truncated, at, collected, hit, terminated and bool(self._in_order[0]), pos)

    # ----------------------------------------------------------------- rendering
    def render_obs(self) -> np.ndarray:
        """``(N, 44, 44, 3) uint8``: each env's current observation."""
        return self._renderer.windows(self._rgb, self._agent)

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
        return self._renderer.windows(self._rgb, self._goals[np.arange(self.num_envs), s])

    def render_map(self, i: int = 0, cell_px: int = RENDER_CELL_PX) -> np.ndarray:
        """``(11*cell_px, 11*cell_px, 3) uint8``: env ``i``'s whole map, allocentric."""
        return render_map(self._rgb, i, cell_px)
