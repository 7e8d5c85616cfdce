"""Registered environment ids and the factory of batch cores used by the trainer."""
from __future__ import annotations

import gymnasium as gym

GRID_IDS: dict[str, dict] = {
    "hdrqn/GridWorld-2Goals-v0": {"layout": "gridworld", "n_goals": 2},
    "hdrqn/GridWorld-3Goals-v0": {"layout": "gridworld", "n_goals": 3},
    "hdrqn/FourRooms-2Goals-v0": {"layout": "fourrooms", "n_goals": 2},
    "hdrqn/FourRooms-3Goals-v0": {"layout": "fourrooms", "n_goals": 3},
}
MONTEZUMA_IDS: dict[str, dict] = {"hdrqn/MontezumaRevenge-v0": {}}
ENV_IDS = tuple(GRID_IDS) + tuple(MONTEZUMA_IDS)


def register_envs() -> None:
    """Register every ``hdrqn/...`` id with gymnasium (idempotent)."""
    for env_id, kwargs in GRID_IDS.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="hdrqn_ros.envs.gridworld:GridWorldEnv", kwargs=kwargs)
    for env_id, kwargs in MONTEZUMA_IDS.items():
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="hdrqn_ros.envs.montezuma:MontezumaEnv", kwargs=kwargs)


def make_batch(env_id: str, num_envs: int = 1, **kwargs):
    """Create the batch core of ``env_id`` stepping ``num_envs`` environments.

    ``kwargs`` override the id's defaults (e.g. ``view=3``). Raises ``ValueError`` for an
    unknown id or a bad ``num_envs``.
    """
    if not isinstance(num_envs, int) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    if env_id in GRID_IDS:
        from hdrqn_ros.envs.gridworld import GridWorldBatch

        return GridWorldBatch(num_envs=num_envs, **{**GRID_IDS[env_id], **kwargs})
    if env_id in MONTEZUMA_IDS:
        from hdrqn_ros.envs.montezuma import MontezumaBatch

        return MontezumaBatch(num_envs=num_envs, **{**MONTEZUMA_IDS[env_id], **kwargs})
    raise ValueError(f"unknown env id {env_id!r}; known ids: {', '.join(ENV_IDS)}")
