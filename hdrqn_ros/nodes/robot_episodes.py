"""A robot's episodes, step by step, as the environment node's ``env_step`` records (``robot_environment``).

:class:`RobotEpisodes` asks the task (:class:`~hdrqn_ros.robot.ordered_visits.OrderedVisits`)
what each step did, keeps the latest step's ``env_step`` record (``wire.STEP_FIELDS``), the
episode's return and decision times, and logs each finished episode and appends it to the
episode log (:class:`~hdrqn_ros.robot.episode_log.EpisodeLog`). No rclpy: the node
publishes the records.
"""
from __future__ import annotations

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.gridworld import GOAL_NAMES
from hdrqn_ros.protocol import wire
from hdrqn_ros.robot.episode_log import EpisodeLog
from hdrqn_ros.robot.ordered_visits import OrderedVisits


class RobotEpisodes:
    """One robot's episodes, numbered from 0; ``logger`` has ``info`` (the node's)."""

    def __init__(self, task: OrderedVisits, log: EpisodeLog, logger):
        self.task, self.log, self.logger = task, log, logger
        self.record: dict = {}  # the latest step's env_step fields
        self.first_key = 0  # the key of the episode's first step
        self.episode, self.env_steps, self.episode_return = -1, 0, 0.0
        self.decision_s: list[float] = []  # this episode's wall seconds from a step to its action

    def start(self, key: int, goal_xy, robot_xy) -> None:
        """The next episode, at the places ``goal_xy`` ``(n, 2)`` with the robot at ``robot_xy``
        (m, the pose's frame); its first step's record has ``key``."""
        self.episode += 1
        self.first_key = key
        self.task.start(goal_xy)
        self.episode_return, self.decision_s = 0.0, []
        self.record = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        self.record.update(key=key, prev_key=0, env_steps=self.env_steps, episode=self.episode,
                           at_subgoal=self.task.where(robot_xy), decision_point=1)

    @property
    def t(self) -> int:
        """The latest step's ``t`` (steps into the episode)."""
        return int(self.record["t"])

    def step(self, key: int, action: int, goal_xy, robot_xy, on_lethal: bool, aimed: int = NO_SUBGOAL,
             stop: bool = False) -> dict:
        """The step ``key`` that ``action`` led to: the robot at ``robot_xy`` and the places at
        ``goal_xy`` ``(n, 2)`` (m, the pose's frame; a frame of their own may move), under the
        option aiming at place ``aimed``; ``stop`` truncates the episode. Returns the task's outcome."""
        self.task.goal_xy = goal_xy
        outcome = self.task.step(robot_xy, on_lethal, aimed)
        if stop and not outcome["terminated"]:
            outcome.update(truncated=True, decision_point=False)
        self.env_steps += 1
        self.record = {"key": key, "prev_key": self.record["key"], "env_steps": self.env_steps,
                       "episode": self.episode, "t": self.task.t, "action": action, **outcome}
        self.episode_return += outcome["extrinsic"]
        return outcome

    def end(self, success: bool) -> None:
        """The episode is over: logged and appended to the episode log."""
        visits = self.task.visits
        self.log.add(self.episode, success, self.task.t, visits, self.episode_return, self.decision_s)
        names = ", ".join(GOAL_NAMES[g] if g < len(GOAL_NAMES) else str(g) for g in visits) or "nothing"
        self.logger.info(f"episode {self.episode}: visited {names} in {self.task.t} steps, "
                         f"{'in order' if success else 'not in order'} "
                         f"(success {self.log.successes} of {self.log.done})")
