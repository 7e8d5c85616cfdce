"""``sub_controller`` node: the agent's lower level, choosing each primitive ``action``.

Lock-step with the environment node (``observation_source: topic``): from the observation
stacked with the option's subgoal image (flat DQN/DRQN: the observation alone), for the
environment node's whole batch in one forward pass; for hDRQNv2 it also hands the
meta-controller its LSTM state (``sub_state``) where an option may end. Or free-running on
a Nav2 local costmap (``costmap``: :mod:`hdrqn_ros.nodes.costmap_controller`). With an
``action_table`` its actions also drive the robot on ``cmd_vel``: each as an exact motion
primitive, a cell or 90 degrees in closed loop (``drive: primitives``:
:class:`~hdrqn_ros.nodes.primitive_driver.PrimitiveDriver`), or as one command held for the
step (``drive: commands``: :class:`~hdrqn_ros.nodes.nav_adapters.VelocityDriver`).
"""
from __future__ import annotations

import time

import numpy as np
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray, Int64MultiArray

from hdrqn_ros.agents.specs import stack_subgoal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.nodes.controller_node import CONTROLLER_PARAMETERS, ControllerNode
from hdrqn_ros.nodes.graph_parameters import odd_cells
from hdrqn_ros.nodes.costmap_controller import OBSERVATION_PARAMETERS, CostmapSubController
from hdrqn_ros.nodes.lockstep import LockStepController
from hdrqn_ros.nodes.nav import ActionTable, SubgoalTable
from hdrqn_ros.nodes.nav_adapters import SUBGOAL_TABLE, VELOCITY_PARAMETERS, VelocityDriver
from hdrqn_ros.nodes.parameters import NodeConfigError
from hdrqn_ros.nodes.primitive_driver import PRIMITIVE_PARAMETERS, PrimitiveDriver
from hdrqn_ros.nodes.qos import STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import all_done, done

PARAMETERS = {**CONTROLLER_PARAMETERS, **OBSERVATION_PARAMETERS, **VELOCITY_PARAMETERS, **PRIMITIVE_PARAMETERS,
              **SUBGOAL_TABLE}
"""``subgoal_table``: with ``observation_source: costmap``, where each subgoal's image is centred."""


class LockStepSubController(LockStepController):
    """Answers each step with one action per environment, once its observation (and, where an
    option starts, the meta-controller's subgoal and the subgoal images) has come."""

    def __init__(self, node: ControllerNode, driver: VelocityDriver | None):
        super().__init__(node)
        self.driver = driver
        self.hierarchical = node.spec.hierarchical
        self.subgoal_image = np.zeros((self.num_envs, OBS_SIZE, OBS_SIZE, 3), np.uint8)  # each option's
        self.pub_action = node.create_publisher(Int64MultiArray, wire.ACTION, STEP_QOS)
        self.pub_state = node.create_publisher(Float64MultiArray, wire.SUB_STATE, STEP_QOS) \
            if node.spec.meta_input == "state" else None
        self.subscribe(Image, wire.OBSERVATION, self._on_observation)
        self.acted_key = 0  # the last step key this node chose an action for
        self.state_sent_key = -1  # the last acted_key whose LSTM state went to the meta-controller
        if self.hierarchical:
            self.subscribe(Int64MultiArray, wire.SUBGOAL, self._on_subgoal)
            self.subscribe(Float64MultiArray, wire.CRITIC, self.on_critic)
            self.subscribe(Image, wire.SUBGOAL_IMAGES,
                           lambda msg: self.on_image(wire.SUBGOAL_IMAGES, msg, OBS_SIZE * self.net.num_subgoals))

    def _on_observation(self, msg: Image) -> None:
        if self.driver is not None:
            self.driver.observed(msg.header.frame_id)
        self.on_image(wire.OBSERVATION, msg)

    def _on_subgoal(self, msg: Int64MultiArray) -> None:
        chosen = self.decode(wire.SUBGOAL, lambda: wire.read_subgoals(msg, self.net.num_subgoals, self.num_envs))
        if chosen is not None:
            self.put(wire.SUBGOAL, *chosen)

    def received(self, rows: list[dict]) -> None:
        """hDRQNv2: where an option may end (a decision point, the episode's end), hand the
        meta-controller our LSTM state after the previous action (its input) before the
        critic has even decided; again for a repeated step."""
        self._hand_over_state(rows, again=True)

    def pump(self) -> None:
        """Then, for the step now waiting: the critic may end an option where no decision point
        is (its ``option_timeout``): hand the state over for it too, once."""
        super().pump()
        if self.queue:
            self._hand_over_state(self.queue[0], again=False)

    def _hand_over_state(self, rows: list[dict], again: bool) -> None:
        """Publish ``sub_state`` for our last action if an option may end at the step after it
        (``rows``): a decision point, the episode's end, or the critic's ``option_done``. Not
        ``again``: only if not yet published for that action.

        A process that has not acted yet, started (or respawned) after the action before
        ``rows``, hands over the state it has, fresh: the state of the process that took that
        action died with it, and without one the meta-controller would wait for ever while we
        wait for its subgoal."""
        if self.pub_state is None or (not again and self.state_sent_key == self.acted_key):
            return
        critic = self.inbox.get(wire.CRITIC, int(rows[0]["key"]))
        never_acted = self.acted_key == 0
        after = [int(row["prev_key"]) for i, row in enumerate(rows)
                 if row["t"] > 0 and (never_acted or int(row["prev_key"]) == self.acted_key)
                 and (row["decision_point"] or done(row) or (critic is not None and critic[i]["option_done"]))]
        if after:
            self.pub_state.publish(wire.make_states(ROS_MESSAGES, after[0], self.policy.sub_end_state()))
            self.state_sent_key = self.acted_key

    def ready(self, rows: list[dict]) -> bool:
        key = int(rows[0]["key"])
        if all_done(rows):
            return True
        if not self.inbox.has(wire.OBSERVATION, key):
            return False
        if not self.hierarchical:
            return True
        starts = self.option_starts(rows)
        if starts is None:
            return False
        return not starts.any() or (self.inbox.has(wire.SUBGOAL, key) and self.inbox.has(wire.SUBGOAL_IMAGES, key))

    def process(self, rows: list[dict]) -> list:
        """One action per environment (-1 where its episode ended at this step), and its
        velocity command; when every episode ended, only the zero command."""
        key = int(rows[0]["key"])
        if all_done(rows):
            return [] if self.driver is None else [self.driver.command(None, key)]
        obs = self.inbox.get(wire.OBSERVATION, key)
        self.policy.start_episodes(np.array([row["t"] == 0 for row in rows]))
        x = obs
        if self.hierarchical:
            starts = self.option_starts(rows)
            if starts.any():
                chosen, images = self.inbox.get(wire.SUBGOAL, key), self.inbox.get(wire.SUBGOAL_IMAGES, key)
                self.policy.start_options(starts, chosen[starts])
                for i in np.flatnonzero(starts):
                    g = int(chosen[i])
                    self.subgoal_image[i] = images[i, g * OBS_SIZE:(g + 1) * OBS_SIZE]
            x = stack_subgoal(obs, self.subgoal_image)
        started = time.perf_counter()
        actions = self.policy.act(x, self.net.epsilon, self.net.rng)
        self.diagnostics.decision(time.perf_counter() - started)
        actions[[done(row) for row in rows]] = -1
        self.acted_key = key
        replies = [] if self.driver is None else [self.driver.command(int(actions[0]), key)]
        replies.append((self.pub_action, wire.make_records(ROS_MESSAGES, wire.INTS, wire.ACTION_FIELDS,
                                                           [[key, a] for a in actions])))
        return replies


class SubControllerNode(ControllerNode):
    """The ``sub_controller`` node: lock-step or on a costmap, driving the robot with an ``action_table``."""

    role = "sub"

    def __init__(self, **kwargs):
        super().__init__("sub_controller", PARAMETERS, **kwargs)
        self.driver: VelocityDriver | None = None

    def check_parameters(self) -> None:
        params, num_envs = self.params, self.params["num_envs"]
        if num_envs != 1 and (params["action_table"] or params["subgoal_table"]):
            raise NodeConfigError(f"action_table and subgoal_table drive one robot: num_envs must be 1, got {num_envs}")
        if params["observation_source"] == "costmap":
            if num_envs != 1:
                raise NodeConfigError(f"observation_source costmap acts for one robot: num_envs must be 1, "
                                      f"got {num_envs}")
            if not odd_cells(params["view"]):
                raise NodeConfigError(f"observation_source costmap needs a numeric view, got {params['view']!r}")

    def build_parts(self) -> None:
        params = self.params
        self.driver = self._driver(ActionTable.load(params["action_table"], self.net.num_actions)) \
            if params["action_table"] else None
        if params["observation_source"] == "costmap":
            places = SubgoalTable.load(params["subgoal_table"], self.net.num_subgoals) if params["subgoal_table"] \
                else None
            self.controller = CostmapSubController(self, self.driver, places)
        else:
            self.controller = LockStepSubController(self, self.driver)

    def _driver(self, table: ActionTable) -> VelocityDriver:
        params = self.params
        if params["drive"] == "commands":
            return VelocityDriver(self, table)
        try:
            return PrimitiveDriver(self, table)
        except ImportError as exc:  # tf2_msgs is not on PyPI: scripts/install builds it
            raise NodeConfigError(f"drive primitives with pose_source tf needs tf2_msgs: {exc}; or set pose_source "
                                  f"odometry (odom_topic {params['odom_topic']!r}) or drive commands") from exc

    def stop(self) -> None:
        """Stop acting, and stop the robot (the zero command)."""
        if self.driver is not None:
            self.driver.halt()

    def teardown(self) -> None:
        super().teardown()
        if self.driver is not None:
            self.driver.release()
        self.driver = None

    def problems(self) -> list[str]:
        return super().problems() + (self.driver.problems() if self.driver is not None else [])

    def health(self) -> tuple[int, str, dict[str, str]]:
        level, message, values = super().health()
        return level, message, {**values, **(self.driver.values() if self.driver is not None else {})}
