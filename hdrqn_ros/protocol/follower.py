"""Following the environment's steps in key order: the join every graph node needs.

A node receives ``env_step`` records and other per-key messages from several writers, in
whatever order DDS delivers them. :class:`StepFollower` queues the steps in key order,
keeps the other inputs by key in a bounded :class:`KeyedInbox`, and hands a step to the
node's ``process`` only when the node says its inputs are all there. Repeated steps (the
environment re-publishes a step nobody answered) get the node's earlier reply again; an
environment restart (keys starting over) resets the follower.

A step is the list of its ``env_step`` records, one per environment of the batch the
environment node steps (``num_envs``; one by default); they share the step key.
"""
from __future__ import annotations

import time
from collections import OrderedDict, deque
from typing import Any, Callable

from hdrqn_ros.protocol import wire
from hdrqn_ros.throttle import Throttle

DEFAULT_CAPACITY = 512
"""Keys kept per input topic, steps queued, and replies remembered (each bounded)."""
STALL_REPORT_S = 5.0
"""A step waiting this long at the head of the queue is reported (and again each period)."""
LOST_AFTER_S = 10.0
"""A follower that keeps stale steps (the learner) gives up on a step whose inputs have not
come while a later step has been complete this long: they were lost. DDS repairs a reliable
sample within a few heartbeats (Fast DDS: 3 s each), so a repair is never taken for a loss."""


class KeyedInbox:
    """Latest value per (topic, key); at most ``capacity`` keys per topic (oldest dropped)."""

    def __init__(self, capacity: int = DEFAULT_CAPACITY):
        self.capacity = capacity
        self.slots: dict[str, OrderedDict[int, Any]] = {}

    def put(self, topic: str, key: int, value: Any) -> None:
        slot = self.slots.setdefault(topic, OrderedDict())
        slot[key] = value
        slot.move_to_end(key)
        while len(slot) > self.capacity:
            slot.popitem(last=False)

    def get(self, topic: str, key: int, default: Any = None) -> Any:
        return self.slots.get(topic, {}).get(key, default)

    def has(self, topic: str, key: int) -> bool:
        return key in self.slots.get(topic, {})

    def forget_before(self, key: int) -> None:
        """Drop every value of a key < ``key`` (steps already processed)."""
        for slot in self.slots.values():
            while slot and next(iter(slot)) < key:
                slot.popitem(last=False)

    def clear(self) -> None:
        self.slots.clear()


class Decoder:
    """Reads messages with :meth:`decode`: a malformed one is logged (throttled per topic)
    and counted in :attr:`rejected`. Subclasses set ``logger`` (a :class:`logging.Logger`);
    a node's ``resolve_topic_name`` names the topics in full."""

    logger = None

    def decode(self, topic: str, read: Callable[[], Any]) -> Any:
        """``read()``, or ``None`` with a logged warning if the message is malformed."""
        try:
            return read()
        except (wire.ProtocolError, ValueError, TypeError, AttributeError) as exc:
            rejections = self.__dict__.setdefault("_rejections", {})
            if topic not in rejections:
                rejections[topic] = Throttle(self.logger, f"rejected a message on {self._name(topic)}")
            rejections[topic].warn(exc)
            return None

    def _name(self, topic: str) -> str:
        """``topic``'s full name where the subclass resolves names (an rclpy node's ``resolve_topic_name``)."""
        resolve = getattr(self, "resolve_topic_name", None)
        return resolve(topic) if resolve is not None else topic

    @property
    def rejected(self) -> int:
        """Malformed messages rejected so far, over all topics."""
        return sum(t.count for t in self.__dict__.get("_rejections", {}).values())


class StepFollower(Decoder):
    """Base of the critic, meta- and sub-controller nodes and the learner's per-environment
    assemblers.

    Subclasses implement ``ready(rows) -> bool`` and ``process(rows) -> list of
    (publisher, message)`` (the replies, remembered for repeats) and may override
    ``reset()``. ``rows`` are a step's ``env_step`` records, one dict of
    :data:`wire.STEP_FIELDS` per environment. A follower with ``num_envs`` set stops (exit
    code 2) at a step of another number of environments: the nodes of a group disagree."""

    skip_stale = True
    """Drop queued steps older than a step that is ready (the loop went on without them:
    their inputs were lost). The learner keeps them (an episode needs every step)."""
    lost_after_s = LOST_AFTER_S
    """A follower that keeps stale steps gives one up once a later step was complete this long."""

    def __init__(self, logger, capacity: int = DEFAULT_CAPACITY, num_envs: int | None = None):
        """``logger``: a :class:`logging.Logger` (a node's, :func:`~hdrqn_ros.nodes.node_logger.python_logger`);
        ``num_envs``: the environments per step this follower works with (``None``: any). A
        node calls :meth:`check_stall` every second."""
        self.logger = logger
        self.num_envs = num_envs
        self.finished = False
        self.exit_code = 0
        self.capacity = capacity
        self.inbox = KeyedInbox(capacity)
        self.queue: deque[list[dict]] = deque()
        self.replies: OrderedDict[int, list] = OrderedDict()
        self.last_key = 0
        self.processed_env_steps: int | None = None  # the env node's step count at the last step processed
        self._head: tuple[int | None, float] = (None, 0.0)  # the waiting head's key, and when it was reported
        self._complete_since: float | None = None  # since when a later step is complete and the head is not

    # -- inputs ----------------------------------------------------------------------------------
    def on_env_step(self, msg) -> None:
        rows = self.decode(wire.ENV_STEP, lambda: wire.read_steps(msg))
        if rows is None or self.finished:
            return
        if self.num_envs is not None and len(rows) != self.num_envs:
            self.logger.error("the environment publishes steps of %d environment(s) on %s, but this node has "
                              "num_envs %d: give every node of the group the same num_envs; stopping",
                              len(rows), self._name(wire.ENV_STEP), self.num_envs)
            self.finished, self.exit_code = True, 2
            return
        self.take(rows)

    def take(self, rows: list[dict]) -> None:
        """Queue a well-formed step (its records, one per environment) and process what is ready."""
        self.received(rows)
        key = int(rows[0]["key"])
        if key in self.replies:
            for pub, reply in self.replies[key]:
                pub.publish(reply)
            return
        if all(row["t"] == 0 for row in rows) and key <= self.last_key:
            self.logger.info("the environment restarted (step keys start over): resynchronising")
            self.reset()
        elif key <= self.last_key or (self.queue and key <= self.queue[-1][0]["key"]):
            return  # stale or repeated before we answered
        self.queue.append(rows)
        if len(self.queue) > self.capacity:
            dropped = self.queue.popleft()
            self.logger.warning("inputs for step key %d never arrived (%s); skipping it", int(dropped[0]["key"]),
                                self._holding(dropped[0]))
        self.pump()

    def put(self, topic: str, key: int, value: Any) -> None:
        if key >= self.last_key:  # inputs of the last processed step may still be needed (prev_key)
            self.inbox.put(topic, key, value)
        self.pump()

    # -- processing ------------------------------------------------------------------------------
    def pump(self) -> None:
        if self.skip_stale and self.queue and not self.ready(self.queue[0]):
            for _ in range(self._first_complete_behind_head()):
                stale = self.queue.popleft()
                self.logger.warning("skipping step key %d: a later step is complete, its inputs are not",
                                    int(stale[0]["key"]))
        while self.queue and self.ready(self.queue[0]):
            rows = self.queue.popleft()
            key = int(rows[0]["key"])
            replies = self.process(rows)
            for pub, reply in replies:
                pub.publish(reply)
            self.replies[key] = replies
            while len(self.replies) > 8:
                self.replies.popitem(last=False)
            self.last_key = key
            self.processed_env_steps = int(rows[0]["env_steps"])
            self.inbox.forget_before(min((int(row["prev_key"]) for row in rows if row["prev_key"]), default=key))

    def received(self, rows: list[dict]) -> None:
        """Called for every well-formed step (its ``env_step`` records) on arrival (before ordering)."""

    def check_stall(self, now: float | None = None, report: bool = True) -> None:
        """Called every second: report a step waiting at the head (every
        :data:`STALL_REPORT_S`, unless not ``report``), and in a follower that keeps stale
        steps, give up on it once a later step has been complete for ``lost_after_s``
        (``now``: monotonic s, or a recording's clock)."""
        now = time.monotonic() if now is None else now
        if not self.queue or self.ready(self.queue[0]):
            self._head, self._complete_since = (None, now), None
            return
        step = self.queue[0][0]
        head = int(step["key"])
        if head != self._head[0]:
            self._head, self._complete_since = (head, now), None
        elif report and now - self._head[1] >= STALL_REPORT_S:
            self._head = (head, now)
            self.logger.warning("step key %d (t=%d, episode %d) still waits for its inputs (%s); %d steps queued",
                                head, step["t"], step["episode"], self._holding(step), len(self.queue))
        if self.skip_stale:
            return
        complete = self._first_complete_behind_head()
        if not complete:
            self._complete_since = None
        elif self._complete_since is None:
            self._complete_since = now
        elif now - self._complete_since >= self.lost_after_s:
            self._give_up(complete, f"while a later step was complete for {self.lost_after_s:.0f} s")

    def give_up_waiting(self) -> None:
        """The end of a recording: give up every step that keeps a later complete one
        waiting (no input can come any more; a running learner would have after
        ``lost_after_s``)."""
        while complete := self._first_complete_behind_head():
            self._give_up(complete, "before the recording ends")

    def _give_up(self, count: int, why: str) -> None:
        """Drop the ``count`` steps at the head of the queue as lost, then process what is ready."""
        for _ in range(count):
            lost = self.queue.popleft()[0]
            self.logger.warning("inputs for step key %d never arrived (%s) %s; skipping it", int(lost["key"]),
                                self._holding(lost), why)
        self._complete_since = None
        self.pump()

    @property
    def waiting(self) -> bool:
        """A step is queued whose inputs have not all come (the stall timer has work)."""
        return bool(self.queue) and not self.ready(self.queue[0])

    def _first_complete_behind_head(self) -> int:
        """The queue index of the first step after the head that is ready (0: none is)."""
        return next((i for i, rows in enumerate(self.queue) if i and self.ready(rows)), 0)

    def _holding(self, step: dict) -> str:
        """What the inbox holds for ``step`` and for its previous step, by topic."""
        key, prev = int(step["key"]), int(step["prev_key"])
        return (f"have {sorted(t for t, slot in self.inbox.slots.items() if key in slot)} for it, "
                f"{sorted(t for t, slot in self.inbox.slots.items() if prev in slot)} for its previous step {prev}")

    def ready(self, rows: list[dict]) -> bool:
        raise NotImplementedError

    def process(self, rows: list[dict]) -> list:
        raise NotImplementedError

    def reset(self) -> None:
        self.queue.clear()
        self.inbox.clear()
        self.replies.clear()
        self.last_key = 0
        self.processed_env_steps = None


def done(step: dict) -> bool:
    """The step (one environment's record) ended its episode."""
    return bool(step["terminated"] or step["truncated"])


def all_done(rows: list[dict]) -> bool:
    """Every environment's episode ended at this step (nobody acts on it: the environment
    node starts new episodes without waiting for an action)."""
    return all(done(row) for row in rows)
