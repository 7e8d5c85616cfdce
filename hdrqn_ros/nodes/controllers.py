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
With ``num_envs`` > 1 both act on the environment node's whole batch in one forward pass.
"""
from __future__ import annotations

import time

import numpy as np

from hdrqn_ros.nodes.diagnostics import OK, WARN, Diagnostics, policy_source

from hdrqn_ros.agents.policy import HierarchicalPolicy
from hdrqn_ros.deploy.specs import ALGO_SPECS, STATE_SIZE, stack_subgoal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.middleware import LATCHED_QOS, Middleware, ParameterRule
from hdrqn_ros.nodes import nav
from hdrqn_ros.protocol import wire
from hdrqn_ros.nodes.common import (ENV_DEFAULTS, ENV_RULES, NodeConfigError, check_num_envs, live_parameters,
                                    make_acting_network, run_node)
from hdrqn_ros.protocol.follower import StepFollower, all_done, done
from hdrqn_ros.training.checkpoint import CheckpointError

_ONE = np.ones(1, bool)  # the rows mask of a free-running (costmap) sub-controller's one environment

CONTROLLER_PARAMETERS = {**ENV_DEFAULTS, "epsilon": -1.0, "checkpoint": "", "policy": "", "meta_state": "c",
                         "num_envs": 1, "quiet_input_s": 10.0}
"""``epsilon`` < 0: explore with the learner's schedule (1.0 until it is heard from);
``checkpoint``: initial weights (``RUN_DIR/checkpoints/last.pt``); ``policy``: instead, an
exported policy directory (``hdrqn export``; torch-free, frozen; its algo, sizes and
hDRQNv2 ``meta_state`` must be the node's); ``meta_state``: which LSTM state hDRQNv2's
meta-controller reads, ``c`` or ``h``; ``num_envs``: the environment node's batch size
(the same on every node of a group); ``quiet_input_s``: wall seconds without any input
after which the node says (once per quiet spell) what it waits for and which node would
publish it. The Nav2 adapters add
:data:`~hdrqn_ros.nodes.nav.META_PARAMETERS` / :data:`~hdrqn_ros.nodes.nav.SUB_PARAMETERS`."""

CONTROLLER_RULES = {
    **ENV_RULES,
    "epsilon": ParameterRule("exploration rate; < 0: the learner's schedule (1.0 until it is heard from)", live=True,
                             low=-1.0, high=1.0),
    "checkpoint": ParameterRule("initial weights (RUN_DIR/checkpoints/last.pt; '': random until the learner's)"),
    "policy": ParameterRule("instead of checkpoint: an exported policy directory (hdrqn export; frozen, no torch)"),
    "meta_state": ParameterRule("hdrqn-v2: which LSTM state the meta-controller reads", choices=("c", "h")),
    "quiet_input_s": ParameterRule("wall seconds without any input before the node says what it waits for",
                                   live=True, positive=True),
    "subgoal_table": ParameterRule("YAML table of the places, subgoal index -> pose ('': off)"),
    "subgoal_poses_topic": ParameterRule("instead of subgoal_table: a latched geometry_msgs/PoseArray of the places"),
    "goal_pose_topic": ParameterRule("where each new option's place goes (geometry_msgs/PoseStamped)"),
    "action_table": ParameterRule("YAML table, action index -> velocity command ('': drive nothing)"),
    "cmd_vel_topic": ParameterRule("where velocity commands go"),
    "observation_source": ParameterRule("topic: the environment's observation; costmap: free-running on costmap_topic",
                                        choices=("topic", "costmap")),
    "costmap_topic": ParameterRule("the nav_msgs/OccupancyGrid observed with observation_source costmap"),
    "stale_after_s": ParameterRule("wall seconds without an observation after which the robot is stopped (zero "
                                   "command)",
                                   live=True, positive=True),
}
"""Descriptions and rules of the controllers' parameters (``ros2 param describe``); live:
``epsilon`` (takes effect at the next decision), ``quiet_input_s``, ``stale_after_s``."""


class _Controller(StepFollower):
    role = ""

    nav_parameters: dict = {}
    active = True
    """Acting (a managed node acts only while active: :mod:`hdrqn_ros.nodes.managed`)."""

    def __init__(self, mw: Middleware, name: str):
        node = mw.create_node(name)
        params = self.params = node.declare_parameters({**CONTROLLER_PARAMETERS, **self.nav_parameters},
                                                       rules=CONTROLLER_RULES)
        n = check_num_envs(params["num_envs"])
        super().__init__(node, num_envs=n)
        if params["meta_state"] not in ("c", "h"):
            raise NodeConfigError(f"meta_state must be 'c' or 'h', got {params['meta_state']!r}")
        if not params["quiet_input_s"] > 0:
            raise NodeConfigError(f"quiet_input_s must be > 0, got {params['quiet_input_s']!r}")
        self.heard: dict[str, tuple[float, str]] = {}  # input -> (last heard, wall s; who publishes it)
        self.quiet_reported: set[str] = set()
        node.create_timer(1.0, self._report_quiet_inputs)
        self.net = make_acting_network(node, self.role, params, default_epsilon=1.0)
        live_parameters(node, params, CONTROLLER_RULES, self._apply)
        self.source = policy_source(params)
        self.rejected_before = 0  # messages rejected up to the last diagnostics
        self.diagnostics = Diagnostics(node, self._health)
        self.spec = ALGO_SPECS[params["algo"]]
        # this node's level of the policy, for the environments of the batch
        sub, meta = (self.net, None) if self.role == "sub" else (None, self.net)
        self.policy = HierarchicalPolicy(n, sub, meta, self.spec.meta_input, params["meta_state"])
        self.every_env = np.ones(n, bool)
        if params.get("observation_source", "topic") == "topic":  # lock-step with the environment node
            self.expect(wire.ENV_STEP, "the environment node (environment, or robot_environment on a robot)")
            node.create_subscription(wire.FLOATS, wire.ENV_STEP, self._on_env_step, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.CREDIT, self._on_credit, LATCHED_QOS)

    def problems(self) -> list[str]:
        """What is wrong now, in words (the diagnostics' WARN message; none: OK)."""
        now = time.monotonic()
        found = [f"nothing on {self.node.resolve_topic(topic)} for {now - last:.0f} s: waiting for {publisher}"
                 for topic, (last, publisher) in self.heard.items() if topic in self.quiet_reported]
        if (rejected := self.rejected - self.rejected_before) > 0:
            found.append(f"{rejected} message(s) rejected in the last second (see the log)")
        self.rejected_before = self.rejected
        return found

    def _health(self) -> tuple[int, str, dict[str, str]]:
        values = {"algo": self.params["algo"], "policy": self.source, "epsilon": f"{self.net.epsilon:g}",
                  "messages_rejected": str(self.rejected)}
        if not self.active:
            return OK, "inactive (managed node: activate to act)", values
        found = self.problems()
        return (WARN, "; ".join(found), values) if found else (OK, "acting", values)

    def activate(self) -> None:
        """Act from the next step on (what arrived while inactive is forgotten)."""
        self.reset()
        now = time.monotonic()
        self.heard = {topic: (now, publisher) for topic, (_, publisher) in self.heard.items()}
        self.quiet_reported.clear()
        self.active = True

    def deactivate(self) -> None:
        """Stop acting: later steps are ignored."""
        self.active = False

    def _apply(self, name: str, value) -> None:
        """A live parameter changed: ``epsilon`` holds from the next decision on."""
        if name == "epsilon":
            self.net.set_fixed_epsilon(value)

    def expect(self, topic: str, publisher: str) -> None:
        """``topic`` is an input published by ``publisher``: report when none comes."""
        self.heard[topic] = (time.monotonic(), publisher)

    def hear(self, topic: str) -> None:
        self.heard[topic] = (time.monotonic(), self.heard[topic][1])
        self.quiet_reported.discard(topic)

    def _report_quiet_inputs(self) -> None:
        if not self.active:
            return
        now = time.monotonic()
        for topic, (last, publisher) in self.heard.items():
            if now - last >= self.params["quiet_input_s"] and topic not in self.quiet_reported:
                self.quiet_reported.add(topic)
                self.node.logger.warning("nothing on %s for %.0f s: waiting for %s", self.node.resolve_topic(topic),
                                         now - last, publisher)

    def _on_env_step(self, msg) -> None:
        if not self.active:
            return
        self.hear(wire.ENV_STEP)
        self.on_env_step(msg)

    def _on_credit(self, msg) -> None:
        credit = self.decode(wire.CREDIT, lambda: wire.read_record(msg, wire.CREDIT_FIELDS))
        if credit is not None:
            self.net.on_credit(credit)

    def _on_image(self, topic: str, msg, height: int = OBS_SIZE) -> None:
        """(N, height, 44, 3): the environments' images, stacked top to bottom on the wire."""
        got = self.decode(topic, lambda: wire.read_images(msg, height, OBS_SIZE, self.num_envs))
        if got is not None:
            self.put(topic, got[0], got[1])

    def _on_critic(self, msg) -> None:
        def read() -> list[dict]:
            verdicts = wire.read_records(msg, wire.CRITIC_FIELDS)
            if len(verdicts) != self.num_envs:
                raise wire.ProtocolError(f"critic holds {len(verdicts)} environment(s)' records, "
                                         f"expected {self.num_envs}")
            return verdicts

        verdicts = self.decode(wire.CRITIC, read)
        if verdicts is not None:
            self.put(wire.CRITIC, verdicts[0]["key"], verdicts)

    def option_starts(self, rows: list[dict]) -> np.ndarray | None:
        """(N,) bool: where the critic ended the option at this step and the episode goes on
        (a new option starts); ``None``: the critic not heard yet."""
        critic = self.inbox.get(wire.CRITIC, int(rows[0]["key"]))
        if critic is None:
            return None
        return np.array([bool(c["option_done"]) and not done(row) for c, row in zip(critic, rows)])

    def reset(self) -> None:
        super().reset()
        self.policy.start_episodes(self.every_env)


class SubControllerNode(_Controller):
    """Lock-step with the environment node (``observation_source: topic``), or free-running
    on a Nav2 local costmap (``costmap``): one action per costmap update, toward the latest
    ``subgoal`` (its image is the costmap window centred on the subgoal table's pose)."""

    role = "sub"
    nav_parameters = {**nav.SUB_PARAMETERS, "subgoal_table": ""}

    def __init__(self, mw: Middleware):
        super().__init__(mw, "sub_controller")
        node, params = self.node, self.params
        self.subgoal_image = np.zeros((self.num_envs, OBS_SIZE, OBS_SIZE, 3), np.uint8)  # each option's
        self.pub_action = node.create_publisher(wire.INTS, wire.ACTION, wire.STEP_QOS)
        self.pub_state = node.create_publisher(wire.FLOATS, wire.SUB_STATE, wire.STEP_QOS) \
            if self.spec.meta_input == "state" else None
        if self.num_envs != 1 and (params["action_table"] or params["subgoal_table"]):
            raise NodeConfigError(f"action_table and subgoal_table drive one robot: num_envs must be 1, "
                                  f"got {self.num_envs}")
        self.actions = nav.ActionTable.load(params["action_table"], self.net.num_actions) \
            if params["action_table"] else None
        self.pub_cmd = node.create_publisher(self.actions.type_name, params["cmd_vel_topic"]) if self.actions else None
        if not params["stale_after_s"] > 0:
            raise NodeConfigError(f"stale_after_s must be > 0, got {params['stale_after_s']!r}")
        self.observed_at: float | None = None  # wall time (monotonic s) the last observation arrived
        self.moving = False  # the last command published was not the zero one
        if self.pub_cmd is not None:
            node.create_timer(0.05, self._stop_if_stale)
        self.goals = nav.SubgoalTable.load(params["subgoal_table"], self.net.num_subgoals) \
            if params["subgoal_table"] else None
        self.free_subgoal = -1  # costmap mode: the latest subgoal heard
        self.costmaps = 0
        source = params["observation_source"]
        if source == "costmap":
            if self.num_envs != 1:
                raise NodeConfigError(f"observation_source costmap acts for one robot: num_envs must be 1, "
                                      f"got {self.num_envs}")
            if not params["view"].isdigit():
                raise NodeConfigError(f"observation_source costmap needs a numeric view, got {params['view']!r}")
            self.expect(params["costmap_topic"], "the robot's local costmap (Nav2's local_costmap, costmap_topic)")
            node.create_subscription(nav.OCCUPANCY_GRID, params["costmap_topic"], self._on_costmap, LATCHED_QOS)
        elif source != "topic":
            raise NodeConfigError(f"observation_source must be 'topic' or 'costmap', got {source!r}")
        else:
            node.create_subscription(wire.IMAGE, wire.OBSERVATION, self._on_observation, wire.STEP_QOS)
        self.acted_key = 0  # the last step key this node chose an action for
        self.state_sent_key = -1  # the last acted_key whose LSTM state went to the meta-controller
        if self.spec.hierarchical:
            if source == "costmap":
                self.expect(wire.SUBGOAL, "the meta_controller")
            node.create_subscription(wire.INTS, wire.SUBGOAL, self._on_subgoal, wire.STEP_QOS)
            if source == "topic":
                node.create_subscription(wire.FLOATS, wire.CRITIC, self._on_critic, wire.STEP_QOS)
                node.create_subscription(wire.IMAGE, wire.SUBGOAL_IMAGES, lambda m: self._on_image(
                    wire.SUBGOAL_IMAGES, m, OBS_SIZE * self.net.num_subgoals), wire.STEP_QOS)

    def _on_observation(self, msg) -> None:
        self.observed_at = time.monotonic()
        self._on_image(wire.OBSERVATION, msg)

    def _command(self, action: int | None, stamp=(0, 0)):
        """The velocity command of ``action`` (``None``: the zero command); remembers whether it moves."""
        msg = self.actions.stop_msg(self.node, stamp) if action is None else \
            self.actions.twist_msg(self.node, action, stamp)
        self.moving = action is not None and any(self.actions.commands[action].values())
        return msg

    def stop(self, why: str) -> None:
        """Publish the zero command (once while stopped), saying why."""
        if self.pub_cmd is not None and self.moving:
            self.pub_cmd.publish(self._command(None))
            self.node.logger.info("zero command on %s: %s", self.node.resolve_topic(self.params["cmd_vel_topic"]), why)

    def problems(self) -> list[str]:
        found = super().problems()
        if self.params["observation_source"] == "costmap" and self.spec.hierarchical and self.free_subgoal < 0:
            found.append(f"no subgoal yet on {self.node.resolve_topic(wire.SUBGOAL)} (is the meta_controller running?)")
        if self._stale():
            found.append(f"the observation is older than stale_after_s ({self.params['stale_after_s']} s): "
                         f"the robot is stopped")
        return found

    def _stale(self) -> bool:
        return self.pub_cmd is not None and self.observed_at is not None and \
            time.monotonic() - self.observed_at > self.params["stale_after_s"]

    def _stop_if_stale(self) -> None:
        if self.moving and self._stale():
            self.stop(f"the observation is {time.monotonic() - self.observed_at:.1f} s old "
                      f"(stale_after_s {self.params['stale_after_s']})")

    def _on_subgoal(self, msg) -> None:
        if self.params["observation_source"] == "costmap":
            self.hear(wire.SUBGOAL)
        chosen = self.decode(wire.SUBGOAL, lambda: wire.read_subgoals(msg, self.net.num_subgoals, self.num_envs))
        if chosen is None:
            return
        if self.params["observation_source"] == "costmap":
            self.free_subgoal = int(chosen[1][0])
        else:
            self.put(wire.SUBGOAL, *chosen)

    def _on_costmap(self, msg) -> None:
        """Free-running: act on each costmap update (no environment node, no lock-step)."""
        if not self.active:
            return
        view = int(self.params["view"])
        self.hear(self.params["costmap_topic"])
        obs = self.decode(self.params["costmap_topic"], lambda: nav.costmap_to_observation(msg, view_cells=view))
        if obs is None:
            return
        self.observed_at = time.monotonic()
        self.costmaps += 1
        key = wire.key_of(msg.header.stamp) or self.costmaps
        x = obs
        if self.spec.hierarchical:
            if self.free_subgoal < 0:
                return  # no subgoal yet
            if self.free_subgoal != self.policy.subgoal[0]:  # a new option
                self.policy.start_options(_ONE, np.array([self.free_subgoal]))
            if self.goals is not None:
                self.subgoal_image[0] = nav.costmap_to_observation(
                    msg, robot_xy=self.goals.poses[self.free_subgoal][:2], view_cells=view)
            x = stack_subgoal(obs, self.subgoal_image[0])
        started = time.perf_counter()
        action = int(self.policy.act(x[None], self.net.epsilon, self.net.rng)[0])
        self.diagnostics.decision(time.perf_counter() - started)
        self.pub_action.publish(wire.make_record(self.node, wire.INTS, wire.ACTION_FIELDS, [key, action]))
        if self.pub_cmd is not None:
            self.pub_cmd.publish(self._command(action, key))

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
            self.pub_state.publish(wire.make_states(self.node, after[0], self.policy.sub_end_state()))
            self.state_sent_key = self.acted_key

    def ready(self, rows: list[dict]) -> bool:
        key = int(rows[0]["key"])
        if all_done(rows):
            return True
        if not self.inbox.has(wire.OBSERVATION, key):
            return False
        if not self.spec.hierarchical:
            return True
        starts = self.option_starts(rows)
        if starts is None:
            return False
        return not starts.any() or (self.inbox.has(wire.SUBGOAL, key) and self.inbox.has(wire.SUBGOAL_IMAGES, key))

    def process(self, rows: list[dict]) -> list:
        """One action per environment (-1 where its episode ended at this step); nothing
        when every episode ended."""
        if all_done(rows):
            if self.pub_cmd is not None:  # the episode ended: stop the robot
                return [(self.pub_cmd, self._command(None, int(rows[0]["key"])))]
            return []
        key = int(rows[0]["key"])
        obs = self.inbox.get(wire.OBSERVATION, key)
        self.policy.start_episodes(np.array([row["t"] == 0 for row in rows]))
        x = obs
        if self.spec.hierarchical:
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
        replies = [(self.pub_cmd, self._command(int(actions[0]), key))] if self.pub_cmd is not None else []
        replies.append((self.pub_action, wire.make_records(self.node, wire.INTS, wire.ACTION_FIELDS,
                                                           [[key, a] for a in actions])))
        return replies

    def deactivate(self) -> None:
        """Stop acting, and stop the robot (the zero command)."""
        super().deactivate()
        self.close()

    def close(self) -> None:
        """Stop the robot: a zero velocity command, delivered before the node goes (at most 2 s)."""
        if self.pub_cmd is not None:
            self.pub_cmd.publish(self._command(None))
            if not self.node.wait_for_delivery(self.pub_cmd, 2.0):
                self.node.logger.warning("the zero command on %s was not acknowledged by every subscriber within 2 s",
                                         self.node.resolve_topic(self.params["cmd_vel_topic"]))


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
        places = params["subgoal_table"] or params["subgoal_poses_topic"]
        if places and self.num_envs != 1:
            raise NodeConfigError(f"subgoal_table and subgoal_poses_topic drive one robot: num_envs must be 1, "
                                  f"got {self.num_envs}")
        if params["subgoal_table"] and params["subgoal_poses_topic"]:
            raise NodeConfigError("give the places as subgoal_table or as subgoal_poses_topic, not both")
        self.goals = nav.SubgoalTable.load(params["subgoal_table"], self.net.num_subgoals) \
            if params["subgoal_table"] else None
        if params["subgoal_poses_topic"]:
            node.create_subscription(nav.POSE_ARRAY, params["subgoal_poses_topic"], self._on_places, LATCHED_QOS)
        self.pub_goal = node.create_publisher(nav.POSE_STAMPED, params["goal_pose_topic"]) if places else None
        self.pub_subgoal = node.create_publisher(wire.INTS, wire.SUBGOAL, wire.STEP_QOS)
        node.create_subscription(wire.FLOATS, wire.CRITIC, self._on_critic, wire.STEP_QOS)
        if self.spec.meta_input == "state":
            node.create_subscription(wire.FLOATS, wire.SUB_STATE, self._on_sub_state, wire.STEP_QOS)
        else:
            node.create_subscription(wire.IMAGE, wire.OBSERVATION, lambda m: self._on_image(wire.OBSERVATION, m),
                                     wire.STEP_QOS)

    def _on_places(self, msg) -> None:
        topic = self.params["subgoal_poses_topic"]
        places = self.decode(topic, lambda: nav.SubgoalTable.from_pose_array(msg, self.net.num_subgoals,
                                                                              self.node.resolve_topic(topic)))
        if places is not None:
            self.goals = places

    def _on_sub_state(self, msg) -> None:
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
        if self.spec.meta_input == "image":
            return self.inbox.has(wire.OBSERVATION, int(rows[0]["key"]))
        ended = [int(row["prev_key"]) for row, start in zip(rows, starts) if start and row["t"] > 0]
        return not ended or self.inbox.has(wire.SUB_STATE, ended[0])

    def process(self, rows: list[dict]) -> list:
        """A ``subgoal`` (and ``goal_pose``) where options start; nothing on other steps."""
        key = int(rows[0]["key"])
        starts = None if all_done(rows) else self.option_starts(rows)
        if starts is None or not starts.any():
            return []
        state_input = self.spec.meta_input == "state"
        fresh = starts & np.array([row["t"] == 0 for row in rows])
        ended = starts & ~fresh
        self.policy.start_episodes(fresh)
        if ended.any():  # the previous options ended: where they stand, and (hDRQNv2) the sub-controller's state
            prev = int(rows[int(np.flatnonzero(ended)[0])]["prev_key"])
            sub_end = self.inbox.get(wire.SUB_STATE, prev)[ended] if state_input else None
            self.policy.end_options(ended, np.array([int(row["at_subgoal"]) for row in rows]), sub_end)
        obs = None if state_input else self.inbox.get(wire.OBSERVATION, key)
        started = time.perf_counter()
        chosen, _ = self.policy.choose_subgoals(starts, obs, self.net.epsilon, self.net.rng)
        self.diagnostics.decision(time.perf_counter() - started)
        subgoals = np.full(self.num_envs, -1, np.int64)
        subgoals[starts] = chosen
        replies = [(self.pub_subgoal, wire.make_records(self.node, wire.INTS, wire.SUBGOAL_FIELDS,
                                                        [[key, g, int(s)] for g, s in zip(subgoals, starts)]))]
        if self.pub_goal is not None and self.goals is not None:
            stamp = wire.Stamp.of(key)
            replies.append((self.pub_goal, self.goals.pose_msg(self.node, int(subgoals[0]), stamp.sec, stamp.nanosec)))
        return replies


CONTROLLER_INPUT_ERRORS = (CheckpointError, nav.NavConfigError)
"""A controller's bad input besides :data:`~hdrqn_ros.nodes.common.STARTUP_ERRORS`: a
checkpoint it cannot load, a navigation table it cannot use."""


def main_sub(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: SubControllerNode(mw), argv, CONTROLLER_INPUT_ERRORS, managed_name="sub_controller")


def main_meta(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: MetaControllerNode(mw), argv, CONTROLLER_INPUT_ERRORS,
                    managed_name="meta_controller")
