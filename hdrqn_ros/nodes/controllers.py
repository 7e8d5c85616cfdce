"""``meta_controller`` and ``sub_controller`` nodes: the two levels of the agent.

meta_controller: at each option's start (the critic says ``option_done``, or a new
episode) chooses a subgoal from the observation (hDRQNv1, hDQN) or from the
sub-controller's LSTM state at the end of the last option (hDRQNv2), and publishes the
current ``subgoal`` for every step. sub_controller: chooses each primitive ``action``
from the observation stacked with the option's subgoal image (flat DQN/DRQN: the
observation alone); for hDRQNv2 it also publishes its LSTM state (``sub_state``).
Both explore with the learner's epsilons (or a fixed ``epsilon`` parameter) and take new
weights from the learner's latched weights topics, or act from an exported ONNX policy
(``policy``: numpy and onnxruntime only, torch is never imported, frozen weights).
"""
from __future__ import annotations

import numpy as np

from hdrqn_ros.agents.policy import HierarchicalPolicy
from hdrqn_ros.deploy.specs import ALGO_SPECS, STATE_SIZE, stack_subgoal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.middleware import LATCHED_QOS, Middleware
from hdrqn_ros.nodes import nav
from hdrqn_ros.protocol import wire
from hdrqn_ros.nodes.common import ENV_DEFAULTS, NodeConfigError, make_acting_network, run_node
from hdrqn_ros.protocol.follower import StepFollower, done
from hdrqn_ros.training.checkpoint import CheckpointError

_ONE = np.ones(1, bool)  # the rows mask of a node's policy: its one environment

CONTROLLER_PARAMETERS = {**ENV_DEFAULTS, "epsilon": -1.0, "checkpoint": "", "policy": "", "meta_state": "c"}
"""``epsilon`` < 0: explore with the learner's schedule (1.0 until it is heard from);
``checkpoint``: initial weights (``RUN_DIR/checkpoints/last.pt``); ``policy``: instead, an
exported policy directory (``hdrqn export``; torch-free, frozen; its algo, sizes and
hDRQNv2 ``meta_state`` must be the node's); ``meta_state``: which LSTM state hDRQNv2's
meta-controller reads, ``c`` or ``h``. The Nav2 adapters add
:data:`~hdrqn_ros.nodes.nav.META_PARAMETERS` / :data:`~hdrqn_ros.nodes.nav.SUB_PARAMETERS`."""


class _Controller(StepFollower):
    role = ""

    nav_parameters: dict = {}

    def __init__(self, mw: Middleware, name: str):
        node = mw.create_node(name)
        super().__init__(node)
        params = self.params = node.declare_parameters({**CONTROLLER_PARAMETERS, **self.nav_parameters})
        if params["meta_state"] not in ("c", "h"):
            raise NodeConfigError(f"meta_state must be 'c' or 'h', got {params['meta_state']!r}")
        self.net = make_acting_network(node, self.role, params, default_epsilon=1.0)
        self.spec = ALGO_SPECS[params["algo"]]
        # this node's level of the policy, for its one environment
        sub, meta = (self.net, None) if self.role == "sub" else (None, self.net)
        self.policy = HierarchicalPolicy(1, sub, meta, self.spec.meta_input, params["meta_state"])
        if params.get("observation_source", "topic") == "topic":  # lock-step with the environment node
            node.create_subscription(wire.FLOATS, wire.ENV_STEP, self.on_env_step, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.CREDIT, self._on_credit, LATCHED_QOS)

    def _on_credit(self, msg) -> None:
        credit = self.decode(wire.CREDIT, lambda: wire.read_record(msg, wire.CREDIT_FIELDS))
        if credit is not None:
            self.net.on_credit(credit)

    def _on_image(self, topic: str, msg, height: int = OBS_SIZE) -> None:
        got = self.decode(topic, lambda: wire.read_image(msg, height, OBS_SIZE))
        if got is not None:
            self.put(topic, got[0], got[1])

    def option_starts(self, key: int) -> bool | None:
        """Whether the critic ended the option at ``key`` (a new one starts); ``None``: not heard yet."""
        critic = self.inbox.get(wire.CRITIC, key)
        return None if critic is None else bool(critic["option_done"])

    def reset(self) -> None:
        super().reset()
        self.policy.start_episodes(_ONE)


class SubControllerNode(_Controller):
    """Lock-step with the environment node (``observation_source: topic``), or free-running
    on a Nav2 local costmap (``costmap``): one action per costmap update, toward the latest
    ``subgoal`` (its image is the costmap window centred on the subgoal table's pose)."""

    role = "sub"
    nav_parameters = {**nav.SUB_PARAMETERS, "subgoal_table": ""}

    def __init__(self, mw: Middleware):
        super().__init__(mw, "sub_controller")
        node, params = self.node, self.params
        self.subgoal_image = np.zeros((OBS_SIZE, OBS_SIZE, 3), np.uint8)
        self.pub_action = node.create_publisher(wire.INTS, wire.ACTION, wire.STEP_QOS)
        self.pub_state = node.create_publisher(wire.FLOATS, wire.SUB_STATE, wire.STEP_QOS) \
            if self.spec.meta_input == "state" else None
        self.actions = nav.ActionTable.load(params["action_table"], self.net.num_actions) \
            if params["action_table"] else None
        self.pub_cmd = node.create_publisher(self.actions.type_name, params["cmd_vel_topic"]) if self.actions else None
        self.goals = nav.SubgoalTable.load(params["subgoal_table"], self.net.num_subgoals) \
            if params["subgoal_table"] else None
        self.free_subgoal = -1  # costmap mode: the latest subgoal heard
        self.costmaps = 0
        source = params["observation_source"]
        if source == "costmap":
            if not params["view"].isdigit():
                raise NodeConfigError(f"observation_source costmap needs a numeric view, got {params['view']!r}")
            node.create_subscription(nav.OCCUPANCY_GRID, params["costmap_topic"], self._on_costmap, LATCHED_QOS)
        elif source != "topic":
            raise NodeConfigError(f"observation_source must be 'topic' or 'costmap', got {source!r}")
        else:
            node.create_subscription(wire.IMAGE, wire.OBSERVATION, lambda m: self._on_image(wire.OBSERVATION, m),
                                     wire.STEP_QOS)
        self.acted_key = 0  # the last step key this node chose an action for
        if self.spec.hierarchical:
            node.create_subscription(wire.INTS, wire.SUBGOAL, self._on_subgoal, wire.STEP_QOS)
            if source == "topic":
                node.create_subscription(wire.FLOATS, wire.CRITIC, self._on_critic, wire.STEP_QOS)
                node.create_subscription(wire.IMAGE, wire.SUBGOAL_IMAGES, lambda m: self._on_image(
                    wire.SUBGOAL_IMAGES, m, OBS_SIZE * self.net.num_subgoals), wire.STEP_QOS)

    def _on_subgoal(self, msg) -> None:
        choice = self.decode(wire.SUBGOAL, lambda: wire.read_record(msg, wire.SUBGOAL_FIELDS, np.int64))
        if choice is not None and self.decode(wire.SUBGOAL, lambda: wire.check_index(
                choice["subgoal"], self.net.num_subgoals, "subgoal")) is not None:
            if self.params["observation_source"] == "costmap":
                self.free_subgoal = int(choice["subgoal"])
            else:
                self.put(wire.SUBGOAL, choice["key"], choice)

    def _on_costmap(self, msg) -> None:
        """Free-running: act on each costmap update (no environment node, no lock-step)."""
        view = int(self.params["view"])
        obs = self.decode(self.params["costmap_topic"], lambda: nav.costmap_to_observation(msg, view_cells=view))
        if obs is None:
            return
        self.costmaps += 1
        key = wire.key_of(msg.header.stamp) or self.costmaps
        x = obs
        if self.spec.hierarchical:
            if self.free_subgoal < 0:
                return  # no subgoal yet
            if self.free_subgoal != self.policy.subgoal[0]:  # a new option
                self.policy.start_options(_ONE, np.array([self.free_subgoal]))
            if self.goals is not None:
                self.subgoal_image = nav.costmap_to_observation(
                    msg, robot_xy=self.goals.poses[self.free_subgoal][:2], view_cells=view)
            x = stack_subgoal(obs, self.subgoal_image)
        action = int(self.policy.act(x[None], self.net.epsilon, self.net.rng)[0])
        self.pub_action.publish(wire.make_record(self.node, wire.INTS, wire.ACTION_FIELDS, [key, action]))
        if self.pub_cmd is not None:
            self.pub_cmd.publish(self.actions.twist_msg(self.node, action, key))

    def _on_critic(self, msg) -> None:
        verdict = self.decode(wire.CRITIC, lambda: wire.read_record(msg, wire.CRITIC_FIELDS))
        if verdict is not None:
            self.put(wire.CRITIC, verdict["key"], verdict)

    def received(self, step: dict) -> None:
        """hDRQNv2: where an option may end, hand the meta-controller our LSTM state after the
        previous action (its input), before the critic has even decided."""
        may_end = step["t"] > 0 and (step["decision_point"] or done(step))
        if self.pub_state is not None and may_end and int(step["prev_key"]) == self.acted_key:
            self.pub_state.publish(wire.make_state(self.node, self.acted_key, self.policy.sub_end_state()[0]))

    def ready(self, step: dict) -> bool:
        key = int(step["key"])
        if done(step):
            return True
        if not self.inbox.has(wire.OBSERVATION, key):
            return False
        if not self.spec.hierarchical:
            return True
        starts = self.option_starts(key)
        if not starts:
            return starts is not None
        return self.inbox.has(wire.SUBGOAL, key) and self.inbox.has(wire.SUBGOAL_IMAGES, key)

    def process(self, step: dict) -> list:
        if done(step):
            return []
        key = int(step["key"])
        obs = self.inbox.get(wire.OBSERVATION, key)
        if step["t"] == 0:
            self.policy.start_episodes(_ONE)
        x = obs
        if self.spec.hierarchical:
            if self.option_starts(key):
                subgoal = int(self.inbox.get(wire.SUBGOAL, key)["subgoal"])
                self.policy.start_options(_ONE, np.array([subgoal]))
                self.subgoal_image = self.inbox.get(wire.SUBGOAL_IMAGES, key)[subgoal * OBS_SIZE:
                                                                              (subgoal + 1) * OBS_SIZE]
            x = stack_subgoal(obs, self.subgoal_image)
        action = int(self.policy.act(x[None], self.net.epsilon, self.net.rng)[0])
        self.acted_key = key
        replies = [(self.pub_action, wire.make_record(self.node, wire.INTS, wire.ACTION_FIELDS, [key, action]))]
        if self.pub_cmd is not None:
            replies.append((self.pub_cmd, self.actions.twist_msg(self.node, action, key)))
        return replies

    def close(self) -> None:
        """Stop the robot: a zero velocity command."""
        if self.pub_cmd is not None:
            self.pub_cmd.publish(self.actions.stop_msg(self.node))


class MetaControllerNode(_Controller):
    """With a ``subgoal_table`` it also publishes each new option's subgoal as a
    ``geometry_msgs/PoseStamped`` on ``goal_pose_topic`` (Nav2's ``goal_pose``)."""

    role = "meta"
    nav_parameters = nav.META_PARAMETERS

    def __init__(self, mw: Middleware):
        super().__init__(mw, "meta_controller")
        if not self.spec.hierarchical:
            raise NodeConfigError(f"{self.params['algo']} is a flat agent: it has no meta-controller")
        node, params = self.node, self.params
        self.goals = nav.SubgoalTable.load(params["subgoal_table"], self.net.num_subgoals) \
            if params["subgoal_table"] else None
        self.pub_goal = node.create_publisher(nav.POSE_STAMPED, params["goal_pose_topic"]) if self.goals else None
        self.pub_subgoal = node.create_publisher(wire.INTS, wire.SUBGOAL, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.CRITIC, self._on_critic, wire.STEP_QOS)
        if self.spec.meta_input == "state":
            node.create_subscription(wire.FLOATS, wire.SUB_STATE, self._on_sub_state, wire.STEP_QOS)
        else:
            node.create_subscription(wire.IMAGE, wire.OBSERVATION, lambda m: self._on_image(wire.OBSERVATION, m),
                                     wire.STEP_QOS)

    def _on_critic(self, msg) -> None:
        verdict = self.decode(wire.CRITIC, lambda: wire.read_record(msg, wire.CRITIC_FIELDS))
        if verdict is not None:
            self.put(wire.CRITIC, verdict["key"], verdict)

    def _on_sub_state(self, msg) -> None:
        got = self.decode(wire.SUB_STATE, lambda: wire.read_state(msg, STATE_SIZE))
        if got is not None:
            self.put(wire.SUB_STATE, *got)

    def ready(self, step: dict) -> bool:
        key, prev = int(step["key"]), int(step["prev_key"])
        if done(step):
            return True
        starts = self.option_starts(key)
        if not starts:
            return starts is not None
        if self.spec.meta_input == "image":
            return self.inbox.has(wire.OBSERVATION, key)
        return step["t"] == 0 or self.inbox.has(wire.SUB_STATE, prev)

    def process(self, step: dict) -> list:
        """A ``subgoal`` (and ``goal_pose``) when an option starts; nothing on other steps."""
        key = int(step["key"])
        if done(step) or not self.option_starts(key):
            return []
        state_input = self.spec.meta_input == "state"
        if step["t"] == 0:
            self.policy.start_episodes(_ONE)
        else:  # the previous option ended: where it stands, and (hDRQNv2) the sub-controller's state
            sub_end = self.inbox.get(wire.SUB_STATE, int(step["prev_key"]))[None] if state_input else None
            self.policy.end_options(_ONE, np.array([int(step["at_subgoal"])]), sub_end)
        obs = None if state_input else self.inbox.get(wire.OBSERVATION, key)[None]
        chosen, _ = self.policy.choose_subgoals(_ONE, obs, self.net.epsilon, self.net.rng)
        subgoal = int(chosen[0])
        replies = [(self.pub_subgoal, wire.make_record(self.node, wire.INTS, wire.SUBGOAL_FIELDS, [key, subgoal, 1]))]
        if self.pub_goal is not None:
            stamp = wire.Stamp.of(key)
            replies.append((self.pub_goal, self.goals.pose_msg(self.node, subgoal, stamp.sec, stamp.nanosec)))
        return replies


CONTROLLER_INPUT_ERRORS = (CheckpointError, nav.NavConfigError)
"""A controller's bad input besides :data:`~hdrqn_ros.nodes.common.STARTUP_ERRORS`: a
checkpoint it cannot load, a navigation table it cannot use."""


def main_sub(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: SubControllerNode(mw), argv, CONTROLLER_INPUT_ERRORS)


def main_meta(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: MetaControllerNode(mw), argv, CONTROLLER_INPUT_ERRORS)
