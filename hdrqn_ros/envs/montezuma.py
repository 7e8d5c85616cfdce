"""Montezuma's Revenge, first room (thesis section 4.1.1, eq. 4.4-4.6, Tables 4.2/4.3).

``MontezumaBatch`` steps ``N`` ALE instances (``ale_py.ALEInterface``) and fulfils the
domain contract of :mod:`hdrqn_ros.envs.domain`; ``MontezumaEnv`` is the single
``gymnasium.Env``, a view of a batch of one. See ``docs/montezuma.md`` for the RAM
addresses, the coordinate mapping, the subgoal boxes and how they were verified.
"""
from __future__ import annotations

import secrets

import gymnasium as gym
import numpy as np

from hdrqn_ros.envs.critic import MONTEZUMA_CRITIC, InternalCritic
from hdrqn_ros.envs.domain import NO_SUBGOAL, OBS_SHAPE, OBS_SIZE, StepBatch, check_actions

# --- ALE facts (verified in docs/montezuma.md and test/test_montezuma.py) -------------
SCREEN_H, SCREEN_W = 210, 160
RAM_ROOM = 3  # current room; the first room is 1
RAM_X = 42  # agent x (grows to the right)
RAM_Y = 43  # agent y (grows upwards): 235 top floor, 192 middle floors, 148 bottom floor
RAM_INVENTORY = 65  # inventory bits; picking up the first room's key sets 0x02
INVENTORY_KEY_BIT = 0x02
START_ROOM = 1
KEY_SCORE = 100  # eq. 4.6
DOOR_SCORE = 300
VIEW = 70  # side of the agent-centred crop in screen pixels (thesis section 4.5.1)

# RAM (x, y) -> screen pixel of the agent sprite's centre: the sprite occupies columns
# x-1 .. x+7 (by facing) and rows 308-y .. 327-y (hat to shoes), see docs/montezuma.md.
PIX_COL_OFFSET = 3  # col = x + 3
PIX_ROW_OFFSET = 317  # row = 317 - y


def ram_to_pixel(x, y):
    """Screen pixel ``(row, col)`` of the agent's centre for RAM position ``(x, y)``."""
    return PIX_ROW_OFFSET - np.asarray(y, dtype=np.int64), np.asarray(x, dtype=np.int64) + PIX_COL_OFFSET


SUBGOAL_NAMES = (
    "left-door",
    "top-mid-ladder",
    "right-door",
    "top-right-ladder",
    "bottom-right-ladder",
    "bottom-left-ladder",
    "key",
)
"""Table 4.2, in subgoal index order."""

# Subgoal boxes in RAM coordinates, inclusive: (x_min, x_max, y_min, y_max). The agent is
# "at" subgoal g while its RAM (x, y) lies inside box g. How they were chosen:
# docs/montezuma.md. The boxes are pairwise disjoint.
SUBGOAL_BOXES = np.array(
    [
        [0, 30, 230, 255],  # left-door: the agent stops against the closed door at x=24
        [70, 84, 230, 255],  # top-mid-ladder: top of the middle ladder (start: 77, 235)
        [124, 152, 230, 255],  # right-door: the agent stops against the door at x=130
        [126, 140, 186, 200],  # top-right-ladder: right ladder top (133, 192)
        [126, 140, 148, 156],  # bottom-right-ladder: right ladder foot (133, 148)
        [14, 28, 148, 156],  # bottom-left-ladder: left ladder foot (21, 148)
        [4, 18, 198, 220],  # key: jumping into the key from the left platform (x 7..20)
    ],
    dtype=np.int64,
)
NUM_SUBGOALS = len(SUBGOAL_NAMES)
KEY_SUBGOAL = 6
SUBGOAL_NEIGHBOURS = ((1,), (0, 2, 3), (1,), (1, 4), (3, 5), (4, 6), (5,))
"""For each subgoal, the subgoals reachable from it without passing through another box
(the room's paths: left door - middle ladder top - right door on the top floor; middle
ladder and rope - right ladder top - right ladder foot - skull floor - left ladder foot -
left ladder and jump - key). The phase-1 table of section 4.5 reports reaching each
subgoal from these."""

ACTION_NAMES = (
    "NOOP", "FIRE", "UP", "RIGHT", "LEFT", "DOWN", "UPRIGHT", "UPLEFT", "DOWNRIGHT",
    "DOWNLEFT", "UPFIRE", "RIGHTFIRE", "LEFTFIRE", "DOWNFIRE", "UPRIGHTFIRE", "UPLEFTFIRE",
    "DOWNRIGHTFIRE", "DOWNLEFTFIRE",
)
"""Table 4.3: the 18 joystick combinations, ALE's full action set order."""
NUM_ACTIONS = len(ACTION_NAMES)

# Nearest-neighbour index map 70 -> 44: output pixel i samples source (i + 0.5) * 70 / 44.
_RESIZE_IDX = np.floor((np.arange(OBS_SIZE) + 0.5) * VIEW / OBS_SIZE).astype(np.int64) - VIEW // 2


def subgoal_at(x, y) -> np.ndarray:
    """Index of the subgoal box containing RAM position(s) ``(x, y)``, else ``NO_SUBGOAL``."""
    x = np.asarray(x, dtype=np.int64)[..., None]
    y = np.asarray(y, dtype=np.int64)[..., None]
    b = SUBGOAL_BOXES
    inside = (x >= b[:, 0]) & (x <= b[:, 1]) & (y >= b[:, 2]) & (y <= b[:, 3])
    return np.where(inside.any(-1), inside.argmax(-1), NO_SUBGOAL).astype(np.int32)


def subgoal_box_pixels() -> np.ndarray:
    """Boxes in screen pixels, ``(NUM_SUBGOALS, 4)``: (row_min, row_max, col_min, col_max)
    of the agent-centre pixels whose RAM position lies in the box."""
    b = SUBGOAL_BOXES
    return np.stack(
        [PIX_ROW_OFFSET - b[:, 3], PIX_ROW_OFFSET - b[:, 2], b[:, 0] + PIX_COL_OFFSET, b[:, 1] + PIX_COL_OFFSET], 1
    )


def subgoal_centres_pixels() -> np.ndarray:
    """Centre (row, col) in screen pixels of each subgoal box, ``(NUM_SUBGOALS, 2)`` int."""
    p = subgoal_box_pixels()
    return np.stack([(p[:, 0] + p[:, 1]) // 2, (p[:, 2] + p[:, 3]) // 2], 1)


def crop_view(frames: np.ndarray, rows, cols) -> np.ndarray:
    """70x70 crops of ``frames (N,210,160,3)`` centred on pixels ``(rows, cols)``, resized to
    44x44 by nearest neighbour; pixels outside the screen are black."""
    rows = np.asarray(rows, dtype=np.int64).reshape(-1, 1) + _RESIZE_IDX  # (N, 44)
    cols = np.asarray(cols, dtype=np.int64).reshape(-1, 1) + _RESIZE_IDX
    rv = (rows >= 0) & (rows < frames.shape[1])
    cv = (cols >= 0) & (cols < frames.shape[2])
    n = np.arange(frames.shape[0])[:, None, None]
    out = frames[n, np.clip(rows, 0, frames.shape[1] - 1)[:, :, None], np.clip(cols, 0, frames.shape[2] - 1)[:, None, :]]
    out[~(rv[:, :, None] & cv[:, None, :])] = 0
    return out


def reward_events(ale_reward, inv_before, inv_after, key_before):
    """Key/door events of one step from the ALE reward and the inventory byte.

    Returns ``(key_taken, door_opened)`` (bool arrays): the key is taken when the
    inventory's key bit appears for the first time this episode (``key_before`` False);
    a door opens when the step's score gain includes the 300 points of a door.
    """
    inv_before = np.asarray(inv_before, dtype=np.int64)
    inv_after = np.asarray(inv_after, dtype=np.int64)
    key_taken = ((inv_after & INVENTORY_KEY_BIT) != 0) & ((inv_before & INVENTORY_KEY_BIT) == 0)
    key_taken &= ~np.asarray(key_before, dtype=bool)
    door_opened = np.asarray(ale_reward) >= DOOR_SCORE
    return key_taken, door_opened


def extrinsic_reward(key_taken, door_opened) -> np.ndarray:
    """Eq. 4.5: 1 when the agent obtains the key or opens a door, else 0."""
    return (np.asarray(key_taken) | np.asarray(door_opened)).astype(np.float32)


def _load_ale():
    try:
        import ale_py
        from ale_py import ALEInterface, LoggerMode, roms
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(
            "Montezuma's Revenge needs the Arcade Learning Environment: pip install ale-py "
            "(ale-py >= 0.9 ships the Atari ROMs)"
        ) from exc
    try:
        rom = roms.get_rom_path("montezuma_revenge")
    except Exception as exc:  # pragma: no cover
        rom = None
        err = exc
    else:
        err = None
    if rom is None:  # pragma: no cover
        raise RuntimeError(
            f"ale-py {getattr(ale_py, '__version__', '?')} has no Montezuma's Revenge ROM"
            f"{f' ({err})' if err else ''}; install ale-py >= 0.9, which ships the ROMs: "
            "pip install -U ale-py"
        )
    ALEInterface.setLoggerMode(LoggerMode.Error)
    return ALEInterface, rom


class MontezumaBatch:
    """``N`` Montezuma's Revenge games, first room only (the domain's batch core).

    ``frame_skip`` emulator frames per agent step (rewards summed; the skip stops early on
    a life loss or game over); ``repeat_action_probability`` is ALE's sticky-action
    probability; ``max_steps`` agent steps per episode before ``truncated``. An episode
    ends (``terminated``) on game over or when the agent leaves the first room. A life
    loss sets ``life_lost`` for that step and the episode goes on.
    """

    num_actions = NUM_ACTIONS
    num_subgoals = NUM_SUBGOALS
    subgoal_names = SUBGOAL_NAMES
    subgoal_neighbours = SUBGOAL_NEIGHBOURS
    action_names = ACTION_NAMES
    return_bound = 3.0  # eq. 4.5: the key and the room's two doors, +1 each

    def __init__(
        self,
        num_envs: int = 1,
        frame_skip: int = 4,
        repeat_action_probability: float = 0.0,
        max_steps: int = 500,
    ):
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if not isinstance(frame_skip, (int, np.integer)) or frame_skip < 1:
            raise ValueError(f"frame_skip must be a positive integer, got {frame_skip!r}")
        if not 0.0 <= float(repeat_action_probability) <= 1.0:
            raise ValueError(f"repeat_action_probability must be in [0, 1], got {repeat_action_probability!r}")
        if not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        self.num_envs = int(num_envs)
        self.frame_skip = int(frame_skip)
        self.repeat_action_probability = float(repeat_action_probability)
        self.max_steps = int(max_steps)
        ale_cls, self._rom = _load_ale()
        base = secrets.randbits(31)
        self._ales = []
        for i in range(self.num_envs):
            ale = ale_cls()
            self._ales.append(ale)
            self._seed_ale(i, base + i)
        self._actions = self._ales[0].getLegalActionSet()  # full set, Table 4.3 order
        n = self.num_envs
        self.frames = np.zeros((n, SCREEN_H, SCREEN_W, 3), np.uint8)
        self._ram = np.zeros((n, 128), np.uint8)
        self.steps = np.zeros(n, np.int64)
        self.key_obtained = np.zeros(n, bool)
        self.lives = np.zeros(n, np.int64)
        self._observe_all()

    # -- internals -------------------------------------------------------------------
    def _seed_ale(self, i: int, seed: int) -> None:
        ale = self._ales[i]
        ale.setInt("random_seed", int(seed) % (2**31))
        ale.setFloat("repeat_action_probability", self.repeat_action_probability)
        ale.setInt("frame_skip", 1)
        ale.loadROM(self._rom)

    def _observe(self, i: int) -> None:
        ale = self._ales[i]
        ale.getScreenRGB(self.frames[i])
        self._ram[i] = ale.getRAM()

    def _observe_all(self) -> None:
        for i in range(self.num_envs):
            self._observe(i)

    def _restart(self, i: int) -> None:
        self._ales[i].reset_game()
        self.steps[i] = 0
        self.key_obtained[i] = False
        self.lives[i] = self._ales[i].lives()
        self._observe(i)

    @property
    def agent_pos(self) -> np.ndarray:
        """(N, 2) int32 RAM (x, y) of each agent now."""
        return self._ram[:, [RAM_X, RAM_Y]].astype(np.int32)

    @property
    def room(self) -> np.ndarray:
        return self._ram[:, RAM_ROOM].astype(np.int32)

    def current_subgoal(self) -> np.ndarray:
        """(N,) int32: the box containing each agent now (NO_SUBGOAL outside the boxes or
        outside the first room)."""
        at = subgoal_at(self._ram[:, RAM_X], self._ram[:, RAM_Y])
        return np.where(self.room == START_ROOM, at, NO_SUBGOAL).astype(np.int32)

    def observations(self) -> np.ndarray:
        """(N, 44, 44, 3) uint8: the 70x70 view centred on each agent, resized."""
        r, c = ram_to_pixel(self._ram[:, RAM_X], self._ram[:, RAM_Y])
        return crop_view(self.frames, r, c)

    # -- contract --------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> np.ndarray:
        """Restart every game; with ``seed``, env ``i`` is seeded with ``seed + i``."""
        for i in range(self.num_envs):
            if seed is not None:
                self._seed_ale(i, int(seed) + i)
            self._restart(i)
        return self.observations()

    def reset_where(self, mask) -> np.ndarray:
        mask = np.asarray(mask, dtype=bool).reshape(-1)
        if mask.shape != (self.num_envs,):
            raise ValueError(f"mask must have shape ({self.num_envs},), got {mask.shape}")
        for i in np.flatnonzero(mask):
            self._restart(int(i))
        return self.observations()

    def step(self, actions) -> StepBatch:
        a = check_actions(actions, self.num_envs, self.num_actions)
        n = self.num_envs
        classical = np.zeros(n, np.float32)
        life_lost = np.zeros(n, bool)
        game_over = np.zeros(n, bool)
        inv_before = self._ram[:, RAM_INVENTORY].copy()
        for i in range(n):
            ale = self._ales[i]
            act = self._actions[a[i]]
            lives = self.lives[i]
            total = 0.0
            for _ in range(self.frame_skip):
                total += ale.act(act)
                if ale.game_over():
                    game_over[i] = True
                    break
                if ale.lives() < lives:
                    break
            now = ale.lives()
            life_lost[i] = now < lives or game_over[i]
            self.lives[i] = now
            classical[i] = total
            self._observe(i)
        self.steps += 1
        key_taken, door_opened = reward_events(
            classical, inv_before, self._ram[:, RAM_INVENTORY], self.key_obtained
        )
        self.key_obtained |= key_taken
        left_room = self.room != START_ROOM
        terminated = game_over | left_room
        truncated = ~terminated & (self.steps >= self.max_steps)
        return StepBatch(
            obs=self.observations(),
            classical=classical,
            extrinsic=extrinsic_reward(key_taken, door_opened),
            terminated=terminated,
            truncated=truncated,
            agent_pos=self.agent_pos,
            at_subgoal=self.current_subgoal(),
            collected=key_taken.copy(),
            hit_obstacle=np.zeros(n, bool),
            life_lost=life_lost,
            success=self.key_obtained.copy(),
        )

    def subgoal_images(self, subgoals) -> np.ndarray:
        """(N, 44, 44, 3): the 70x70 view of the current frame centred on each env's
        subgoal box, resized like the observation."""
        g = np.asarray(subgoals).reshape(-1)
        if g.shape != (self.num_envs,):
            raise ValueError(f"subgoals must have shape ({self.num_envs},), got {g.shape}")
        if not np.issubdtype(g.dtype, np.integer) or ((g < 0) | (g >= NUM_SUBGOALS)).any():
            raise ValueError(f"subgoals must be integers in [0, {NUM_SUBGOALS}), got {g.tolist()}")
        c = subgoal_centres_pixels()[g]
        return crop_view(self.frames, c[:, 0], c[:, 1])

    def critic(self) -> InternalCritic:
        return MONTEZUMA_CRITIC

    def close(self) -> None:
        self._ales = []


class MontezumaEnv(gym.Env):
    """Single Montezuma's Revenge env (first room), a view of a :class:`MontezumaBatch`
    of one. Reward: the classical reward (eq. 4.6); ``info`` carries the others."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 15}

    def __init__(self, render_mode: str | None = None, **kwargs):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.batch = MontezumaBatch(num_envs=1, **kwargs)
        self.observation_space = gym.spaces.Box(0, 255, OBS_SHAPE, np.uint8)
        self.action_space = gym.spaces.Discrete(NUM_ACTIONS)
        self._critic = self.batch.critic()
        self.subgoal = KEY_SUBGOAL

    def set_subgoal(self, subgoal: int) -> None:
        if not isinstance(subgoal, (int, np.integer)) or not 0 <= subgoal < NUM_SUBGOALS:
            raise ValueError(f"subgoal must be an integer in [0, {NUM_SUBGOALS}), got {subgoal!r}")
        self.subgoal = int(subgoal)

    def subgoal_image(self, subgoal: int | None = None) -> np.ndarray:
        subgoal = self.subgoal if subgoal is None else subgoal
        return self.batch.subgoal_images(np.array([subgoal]))[0]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        obs = self.batch.reset(seed=seed)[0]
        self.subgoal = KEY_SUBGOAL
        at = int(self.batch.current_subgoal()[0])
        info = {
            "extrinsic": 0.0,
            "classical": 0.0,
            "intrinsic": 0.0,
            "subgoal_reached": False,
            "at_subgoal": at,
            "hit_obstacle": False,
            "life_lost": False,
            "agent_pos": self.batch.agent_pos[0].copy(),
            "success": False,
        }
        return obs, info

    def step(self, action):
        if np.ndim(action) != 0:
            raise ValueError(f"action must be a single integer in [0, {NUM_ACTIONS}), got {action!r}")
        stepped = self.batch.step(np.asarray(action).reshape(1))
        judged = self._critic.evaluate(stepped, np.array([self.subgoal]))
        info = {
            "extrinsic": float(stepped.extrinsic[0]),
            "classical": float(stepped.classical[0]),
            "intrinsic": float(judged.intrinsic[0]),
            "subgoal_reached": bool(judged.reached[0]),
            "at_subgoal": int(stepped.at_subgoal[0]),
            "hit_obstacle": bool(stepped.hit_obstacle[0]),
            "life_lost": bool(stepped.life_lost[0]),
            "agent_pos": stepped.agent_pos[0].copy(),
            "success": bool(stepped.success[0]),
        }
        return (stepped.obs[0], float(stepped.classical[0]), bool(stepped.terminated[0]), bool(stepped.truncated[0]),
                info)

    def render(self):
        if self.render_mode == "rgb_array":
            return self.batch.frames[0].copy()
        return None

    def close(self):
        self.batch.close()
