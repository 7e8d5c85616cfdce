"""``meta_controller`` node: the agent's upper level, choosing each option's subgoal.

Lock-step with the environment node: at each option's start (the critic says
``option_done``, or a new episode) it chooses a subgoal from the observation (hDRQNv1,
hDQN) or from the sub-controller's LSTM state at the end of the last option (hDRQNv2), for
the environment node's whole batch in one forward pass, and publishes it on ``subgoal``.
With the robot's places (``subgoal_table`` or ``subgoal_poses_topic``) each new option's
place also goes to the navigator: as one ``navigate_to_pose`` goal whose result ends the
option (``navigation: action``, :class:`~hdrqn_ros.nodes.navigate_goals.NavigateGoals`; an
option waits for the action server and the places), or as a ``goal_pose`` message (``navigation: topic``,
:class:`~hdrqn_ros.nodes.nav_adapters.GoalPoses`). The active goal is cancelled when the
episode ends, and when the node is deactivated or stops.
"""
from __future__ import annotations

import time

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Int64MultiArray

from hdrqn_ros.agents.specs import ALGO_SPECS, STATE_SIZE
from hdrqn_ros.nodes.controller_node import CONTROLLER_PARAMETERS, ControllerNode
from hdrqn_ros.nodes.lockstep import LockStepController
from hdrqn_ros.nodes.nav_adapters import GOAL_PARAMETERS, GoalPoses, SubgoalPlaces
from hdrqn_ros.nodes.navigate_goals import NavigateGoals
from hdrqn_ros.nodes.parameters import NodeConfigError
from hdrqn_ros.nodes.qos import STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import all_done

PARAMETERS = {**CONTROLLER_PARAMETERS, **GOAL_PARAMETERS}


class LockStepMetaController(LockStepController):
    """Answers each step where an option starts with the subgoals of the environments that
    start one (``new_option`` 1) once its input has come: the observation, or (hDRQNv2) the
    sub-controller's state after the action that ended the option, and the navigator's action
    server (``goals``: where the places go, if anywhere). Other steps get no answer."""

    def __init__(self, node: ControllerNode, goals: GoalPoses | NavigateGoals | None):
        super().__init__(node)
        self.goals = goals
        self.state_input = node.spec.meta_input == "state"
        self.pub_subgoal = node.create_publisher(Int64MultiArray, wire.SUBGOAL, STEP_QOS)
        self.subscribe(Float64MultiArray, wire.CRITIC, self.on_critic)
        if self.state_input:
            self.subscribe(Float64MultiArray, wire.SUB_STATE, self._on_sub_state)
        else:
            self.subscribe(Image, wire.OBSERVATION, lambda msg: self.on_image(wire.OBSERVATION, msg))

    def _on_sub_state(self, msg: Float64MultiArray) -> None:
        def read() -> tuple[int, np.ndarray]:
            key, states = wire.read_states(msg, STATE_SIZE)
            if len(states) != self.num_envs:
                raise wire.ProtocolError(f"sub_state holds {len(states)} environment(s)' states, "
                                         f"expected {self.num_envs}")
            return key, states

        got = self.decode(wire.SUB_STATE, read)
        if got is not None:
            self.put(wire.SUB_STATE, *got)

    def ready(self, rows: list[dict]) -> bool:
        if all_done(rows):
            return True
        starts = self.option_starts(rows)
        if starts is None:
            return False
        if not starts.any():
            return True
        if self.goals is not None and not self.goals.ready():
            return False
        if not self.state_input:
            return self.inbox.has(wire.OBSERVATION, int(rows[0]["key"]))
        ended = [int(row["prev_key"]) for row, start in zip(rows, starts) if start and row["t"] > 0]
        return not ended or self.inbox.has(wire.SUB_STATE, ended[0])

    def process(self, rows: list[dict]) -> list:
        """A ``subgoal`` (and the navigator's goal) where options start; nothing on other steps."""
        key = int(rows[0]["key"])
        if all_done(rows) and self.goals is not None:
            self.goals.end_episode()
        starts = None if all_done(rows) else self.option_starts(rows)
        if starts is None or not starts.any():
            return []
        fresh = starts & np.array([row["t"] == 0 for row in rows])
        ended = starts & ~fresh
        self.policy.start_episodes(fresh)
        if ended.any():  # the previous options ended: where they stand, and (hDRQNv2) the sub-controller's state
            prev = int(rows[int(np.flatnonzero(ended)[0])]["prev_key"])
            sub_end = self.inbox.get(wire.SUB_STATE, prev)[ended] if self.state_input else None
            self.policy.end_options(ended, np.array([int(row["at_subgoal"]) for row in rows]), sub_end)
        obs = None if self.state_input else self.inbox.get(wire.OBSERVATION, key)
        started = time.perf_counter()
        chosen, _ = self.policy.choose_subgoals(starts, obs, self.net.epsilon, self.net.rng)
        self.diagnostics.decision(time.perf_counter() - started)
        subgoals = np.full(self.num_envs, -1, np.int64)
        subgoals[starts] = chosen
        replies = [(self.pub_subgoal, wire.make_records(ROS_MESSAGES, wire.INTS, wire.SUBGOAL_FIELDS,
                                                        [[key, g, int(s)] for g, s in zip(subgoals, starts)]))]
        if self.goals is not None:
            replies += self.goals.replies(int(subgoals[0]), key)
        return replies

    def problems(self) -> list[str]:
        return [] if self.goals is None else self.goals.problems()


class MetaControllerNode(ControllerNode):
    """The ``meta_controller`` node of a hierarchical agent, with navigation goals given the robot's places."""

    role = "meta"

    def __init__(self, **kwargs):
        super().__init__("meta_controller", PARAMETERS, **kwargs)
        self.goals: GoalPoses | NavigateGoals | None = None

    def check_parameters(self) -> None:
        params = self.params
        if not ALGO_SPECS[params["algo"]].hierarchical:
            raise NodeConfigError(f"{params['algo']} is a flat agent: it has no meta-controller")
        if (params["subgoal_table"] or params["subgoal_poses_topic"]) and params["num_envs"] != 1:
            raise NodeConfigError(f"subgoal_table and subgoal_poses_topic drive one robot: num_envs must be 1, "
                                  f"got {params['num_envs']}")
        if params["subgoal_table"] and params["subgoal_poses_topic"]:
            raise NodeConfigError("give the places as subgoal_table or as subgoal_poses_topic, not both")

    def build_parts(self) -> None:
        params = self.params
        self.goals = None
        if params["subgoal_table"] or params["subgoal_poses_topic"]:
            places = SubgoalPlaces(self, self.net.num_subgoals)
            self.goals = NavigateGoals(self, places, self._goals_ready) if params["navigation"] == "action" \
                else GoalPoses(self, places)
        self.controller = LockStepMetaController(self, self.goals)

    def _goals_ready(self) -> None:
        """Goals can go out (the action server is there): take a step that waited for it."""
        if self.active and self.controller is not None:
            self.controller.pump()

    def stop(self) -> None:
        """Deactivated or stopping: the active navigation goal is cancelled."""
        if self.goals is not None:
            self.goals.stop()

    def teardown(self) -> None:
        if self.goals is not None:
            self.goals.release()
        super().teardown()

    def close(self) -> None:
        """The process stops: the active goal is cancelled, and the cancel answered (at most 2 s)."""
        goals = self.goals
        super().close()
        if goals is not None:
            goals.settle(self.executor)

    def health(self) -> tuple[int, str, dict[str, str]]:
        level, message, values = super().health()
        return level, message, {**values, **(self.goals.values() if self.goals is not None else {})}
