"""Partially observable hierarchical domains: multi-goal gridworld, four-rooms, Montezuma."""
from hdrqn_ros.envs.domain import OBS_SHAPE, OBS_SIZE, StepBatch
from hdrqn_ros.envs.registration import ENV_IDS, make_batch, register_envs

__all__ = ["ENV_IDS", "OBS_SHAPE", "OBS_SIZE", "StepBatch", "make_batch", "register_envs"]
