"""The internal critic (thesis section 3.6): intrinsic reward and subgoal termination.

It is a pure function of what the environment reports about the agent
(:class:`~hdrqn_ros.envs.domain.StepBatch`) and the subgoal each environment's option is
pursuing. The ``critic`` node wraps the same object.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hdrqn_ros.envs.domain import StepBatch


@dataclass
class CriticResult:
    intrinsic: np.ndarray  # (N,) float32 intrinsic reward
    reached: np.ndarray  # (N,) bool, the option's subgoal was achieved at this step
    option_done: np.ndarray  # (N,) bool, the option ends (reached, life lost or episode over)


@dataclass(frozen=True)
class InternalCritic:
    """Domain-aware intrinsic reward.

    ``goal_reward`` is given for reaching the place of the option's subgoal (a goal's cell
    counts also after the goal was collected: a subgoal is a place, thesis 3.5);
    ``wrong_subgoal_penalty`` for collecting another goal (the option goes on);
    ``obstacle_penalty`` for hitting an obstacle (the option goes on). Gridworld and four-rooms use (1, -1, -1) (eq. 4.1);
    Montezuma's Revenge uses (1, 0, 0) (eq. 4.4) and ends the option on a life loss.
    """

    goal_reward: float = 1.0
    wrong_subgoal_penalty: float = -1.0
    obstacle_penalty: float = -1.0
    life_loss_ends_option: bool = False

    def evaluate(self, step: StepBatch, subgoals: np.ndarray) -> CriticResult:
        """``subgoals``: (N,) int, the subgoal of each environment's current option."""
        subgoals = np.asarray(subgoals).reshape(-1)
        if subgoals.shape != step.at_subgoal.shape:
            raise ValueError(f"subgoals must have shape {step.at_subgoal.shape}, got {subgoals.shape}")
        reached = step.at_subgoal == subgoals
        other = (step.at_subgoal >= 0) & ~reached & step.collected
        intrinsic = np.where(reached, self.goal_reward, 0.0)
        intrinsic += np.where(other, self.wrong_subgoal_penalty, 0.0)
        intrinsic += np.where(step.hit_obstacle, self.obstacle_penalty, 0.0)
        option_done = reached | step.done
        if self.life_loss_ends_option:
            option_done |= step.life_lost
        return CriticResult(intrinsic.astype(np.float32), reached, option_done)


def sub_controller_terminal(reached: np.ndarray, terminated: np.ndarray, life_lost: np.ndarray,
                            option_done: np.ndarray) -> np.ndarray:
    """(N,) bool: the sub-controller's TD target does not bootstrap at this step.

    An option ends with a terminal transition for the sub-controller when its subgoal is
    reached, when the episode terminates, or when a life is lost and that ends the option
    (Montezuma, thesis 4.5): the next frame is a death animation the option will not go on
    from, so dying must cost the sub-controller the value it would have bootstrapped. An
    option cut by the step limit (``truncated``, no life lost) still bootstraps. Only data
    that both the in-process rollout and the node graph have go in (``option_done`` is the
    critic's output, ``life_lost`` the environment's).
    """
    return (np.asarray(reached, bool) | np.asarray(terminated, bool)
            | (np.asarray(life_lost, bool) & np.asarray(option_done, bool)))


GRID_CRITIC = InternalCritic(1.0, -1.0, -1.0, life_loss_ends_option=False)
"""Eq. 4.1: +1 for the subgoal, -1 for another goal or an obstacle."""
MONTEZUMA_CRITIC = InternalCritic(1.0, 0.0, 0.0, life_loss_ends_option=True)
"""Eq. 4.4: +1 for reaching the subgoal's box, 0 otherwise; a life loss ends the option."""
