"""Multiple goals in a gridworld / four-rooms (thesis section 4.1.1), vectorised with numpy.

:class:`GridWorldBatch` steps ``N`` environments as one numpy operation (the
:class:`~hdrqn_ros.envs.domain.DomainBatch` contract; :mod:`~hdrqn_ros.envs.grid_batch`);
:class:`GridWorldEnv` is the single ``gymnasium.Env``, a view of a batch of one. See
``docs/environments.md`` for the rules. The maps, the padded canvas and the cell codes are
in :mod:`~hdrqn_ros.envs.grid_layout`, rendering in :mod:`~hdrqn_ros.envs.grid_render`, the
goal rules in :mod:`~hdrqn_ros.envs.grid_rules`; this module gathers their public names.
"""
from __future__ import annotations

import gymnasium as gym
import numpy as np

from hdrqn_ros.envs.domain import NO_SUBGOAL, OBS_SIZE
from hdrqn_ros.envs.grid_batch import GridWorldBatch
from hdrqn_ros.envs.grid_layout import (ACTION_DELTAS, ACTIONS, AGENT, CANVAS, CANVAS_CELLS, FIRE, FOURROOMS_DOORS,
                                        FREE, GOAL0, GOAL_NAMES, LAYOUTS, MAP_SIZE, NUM_OBSTACLES, OUTSIDE, PAD,
                                        PALETTE, VIEWS, WALL, default_max_steps, layout_walls)
from hdrqn_ros.envs.grid_render import RENDER_CELL_PX
from hdrqn_ros.envs.grid_rules import GoalRules

__all__ = ["GridWorldBatch", "GridWorldEnv", "GoalRules", "layout_walls", "default_max_steps", "MAP_SIZE", "PAD",
           "CANVAS", "CANVAS_CELLS", "FREE", "WALL", "GOAL0", "FIRE", "AGENT", "OUTSIDE", "PALETTE", "GOAL_NAMES",
           "NUM_OBSTACLES", "ACTIONS", "ACTION_DELTAS", "LAYOUTS", "VIEWS", "FOURROOMS_DOORS", "RENDER_CELL_PX"]


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
                 render_mode: str | None = None, obstacles: bool = True):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.batch = GridWorldBatch(1, layout=layout, n_goals=n_goals, view=view, max_steps=max_steps,
                                    obstacles=obstacles)
        self.render_mode = render_mode
        self.observation_space = gym.spaces.Box(0, 255, (OBS_SIZE, OBS_SIZE, 3), np.uint8)
        self.action_space = gym.spaces.Discrete(4)
        critic = self.batch.critic()
        self._crit = (float(critic.goal_reward), float(critic.wrong_subgoal_penalty), float(critic.obstacle_penalty))
        self._subgoal = 0

    @property
    def subgoal(self) -> int:
        """The goal index the current option pursues."""
        return self._subgoal

    @property
    def next_goal(self) -> int:
        """The lowest-index goal not yet collected (``n_goals`` once all are)."""
        return int(self.batch.next_goal[0])

    def set_subgoal(self, subgoal: int) -> None:
        """Set the current subgoal (goal index in ``[0, n_goals)``)."""
        if (isinstance(subgoal, (bool, np.bool_)) or not isinstance(subgoal, (int, np.integer))
                or not 0 <= subgoal < self.batch.n_goals):
            raise ValueError(f"subgoal must be an integer in [0, {self.batch.n_goals}), got {subgoal!r}")
        self._subgoal = int(subgoal)

    def subgoal_image(self, subgoal: int | None = None) -> np.ndarray:
        """``(44, 44, 3) uint8``: the goal-centred image of goal ``subgoal`` (default: the current
        subgoal)."""
        if subgoal is None:
            subgoal = self._subgoal
        elif (isinstance(subgoal, (bool, np.bool_)) or not isinstance(subgoal, (int, np.integer))
              or not 0 <= subgoal < self.batch.n_goals):
            raise ValueError(f"subgoal must be an integer in [0, {self.batch.n_goals}), got {subgoal!r}")
        return self.batch.subgoal_images(np.array([subgoal]))[0]

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
        batch = self.batch
        obs, classical, extrinsic, terminated, truncated, at, collected, hit, success, pos = batch.step_one(action)
        goal_r, wrong_r, obst_r = self._crit
        reached = at == self._subgoal
        intrinsic = goal_r if reached else (wrong_r if collected else 0.0)
        if hit:
            intrinsic += obst_r
        if reached:
            self._subgoal = min(int(batch.next_goal[0]), batch.n_goals - 1)
        info = {
            "extrinsic": extrinsic, "classical": classical, "intrinsic": intrinsic, "subgoal_reached": reached,
            "at_subgoal": at, "hit_obstacle": hit, "life_lost": False,
            "agent_pos": pos,
            "success": success, "subgoal": self._subgoal,
        }
        return obs, classical, terminated, truncated, info

    def render(self):
        if self.render_mode == "rgb_array":
            return self.batch.render_map(0)
        return None
