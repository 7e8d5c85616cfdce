"""One environment group as the learner node reads it: a :class:`TransitionAssembler` fed
by the learner's subscriptions to the group's topics, which also grants the group's credit
(``learner_credit``) and may record what it receives."""
from __future__ import annotations

import logging
import queue
from typing import Callable, Protocol

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray

from hdrqn_ros.nodes.qos import LATCHED_QOS, STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription, interface_class
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.assembly import TransitionAssembler
from hdrqn_ros.protocol.follower import DEFAULT_CAPACITY
from hdrqn_ros.training.episodes import FinishedEpisode
from hdrqn_ros.training.learner import Learner

MAX_LAG = DEFAULT_CAPACITY // 2
"""Steps of the environment node the env may run ahead of what the learner has assembled:
while DDS repairs a lost sample of one topic the others flow on, and the queue waiting for
it must not overflow (see :data:`~hdrqn_ros.protocol.follower.LOST_AFTER_S`)."""
STALL_CHECK_S = 1.0
"""Wall-clock seconds between :meth:`TransitionAssembler.check_stall` calls."""


class Recorder(Protocol):
    """Where the group's messages are also written, as received (e.g. the learner's bag)."""

    def add_group(self, namespace: str, topics: list[str]) -> dict[str, int]: ...

    def recording(self, connection: int, handler: Callable) -> Callable: ...

    def sync(self) -> bool: ...


class GroupAssembler(TransitionAssembler):
    """A :class:`TransitionAssembler` fed by ``node``'s subscriptions to one group (samples
    over ``max_message_bytes`` dropped), which also publishes the group's ``learner_credit``
    and may record what it receives. Finished episodes go to ``episodes`` (the training
    thread stores them in replay)."""

    def __init__(self, node: Node, namespace: str, learner: Learner, episodes: queue.Queue,
                 logger: logging.Logger, max_message_bytes: int, lost_after_s: float, log=None,
                 recorder: Recorder | None = None):
        """``logger``: %-style, for the protocol layer; ``log``: the transition log (a text file) or None."""
        super().__init__(namespace, learner.cfg, learner.agent.num_subgoals, self._acknowledge, logger=logger,
                         log=log, lost_after_s=lost_after_s)
        self.ros_node = node
        self.episodes, self.graph_recorder = episodes, recorder
        self.acked_episodes = self.acked_steps = 0
        self.first_step: list[dict] | None = None  # the first step heard from the group (its records)
        self.synced = False  # no credit before the learner holds a whole step's messages (see publish_credit)
        self.last_credit: tuple | None = None
        inputs = self.inputs()
        conns = recorder.add_group(namespace, list(inputs)) if recorder is not None else {}
        self.subscriptions = []
        for name, (type_name, handler) in inputs.items():
            if name in conns:
                handler = recorder.recording(conns[name], handler)
            self.subscriptions.append(bounded_subscription(node, interface_class(type_name), self.topic(name),
                                                           handler, STEP_QOS, max_message_bytes, logger))
        self.credit_pub = node.create_publisher(Float64MultiArray, self.topic(wire.CREDIT), LATCHED_QOS)
        node.create_timer(STALL_CHECK_S, self.check_stall, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def unmatched_topics(self) -> list[str]:
        """The group's topics that no publisher is matched to yet."""
        return [sub.topic_name for sub in self.subscriptions if sub.get_publisher_count() == 0]

    def resolve_topic_name(self, topic: str) -> str:
        """``topic``'s full name, as the learner node resolves it (for log lines)."""
        return self.ros_node.resolve_topic_name(topic)

    def _acknowledge(self, episode: FinishedEpisode) -> None:
        """A finished episode: make its messages durable in the recording (when recording),
        count it as acknowledged, and queue it for replay."""
        if self.graph_recorder is not None and self.graph_recorder.sync():
            self.acked_episodes += 1
            self.acked_steps += episode.stats.steps
        self.episodes.put(episode)

    def received(self, rows: list[dict]) -> None:
        super().received(rows)
        if self.first_step is None or len(self.first_step) != len(rows):
            self.first_step, self.synced = rows, False

    def stats(self) -> dict:
        """The assembler's counters, plus ``acked_episodes``/``acked_steps``: the episodes
        (and their transitions) already durable in the learner's bag when recording, and
        ``no_publisher_yet``: the topics no publisher is matched to (no credit ahead until
        there is none)."""
        return {**super().stats(), "acked_episodes": self.acked_episodes, "acked_steps": self.acked_steps,
                "no_publisher_yet": self.unmatched_topics()}

    def publish_credit(self, window: int, owed_ok: bool, eps: tuple[float, float], epoch: float,
                       force: bool = False) -> None:
        """Publish ``learner_credit`` when the credit or the epsilons changed (or ``force``).

        No credit ahead before every subscription of the group has a publisher matched and
        the learner holds the group's first heard step together with the other nodes' answers
        to it (critic, action, subgoal): a subscription matched late (discovery is per topic)
        would miss them, and the env would run on while every later step waits for them.
        Without credit the env re-publishes its step after ``action_timeout`` and the
        controllers their answers, which the late subscription then gets.

        Credit runs ``window`` steps of the environment node ahead of what the learner has
        received, and at most :data:`MAX_LAG` ahead of what it has assembled (a batch of N
        environments: N env steps per step)."""
        if not self.synced and self.first_step is not None:
            self.synced = not self.unmatched_topics() and self.holds_answers(self.first_step)
        n = max(1, len(self.envs))
        credit = self.env_steps_seen + window * n if owed_ok and self.synced else self.env_steps_seen
        assembled = self.assembled_env_steps
        if assembled is not None:
            credit = min(credit, max(assembled + MAX_LAG * n, self.env_steps_seen))
        values = (credit, round(eps[0], 4), round(eps[1], 4))
        if values == self.last_credit and not force:
            return
        self.last_credit = values
        self.credit_pub.publish(wire.make_record(ROS_MESSAGES, wire.FLOATS, wire.CREDIT_FIELDS,
                                                 [*values, self.last_key, epoch]))
