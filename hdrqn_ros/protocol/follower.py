"""Following the environment's steps in key order: the join every graph node needs.

A node receives ``env_step`` records and other per-key messages from several writers, in
whatever order DDS delivers them. :class:`StepFollower` queues the steps in key order,
keeps the other inputs by key in a bounded :class:`KeyedInbox`, and hands a step to the
node's ``process`` only when the node says its inputs are all there. Repeated steps (the
environment re-publishes a step nobody answered) get the node's earlier reply again; an
environment restart (keys starting over) resets the follower.
"""
from __future__ import annotations

from collections import OrderedDict, deque
from typing import Any, Callable

from hdrqn_ros.protocol import wire
from hdrqn_ros.throttle import Throttle

DEFAULT_CAPACITY = 512
"""Keys kept per input topic, steps queued, and replies remembered (each bounded)."""


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


class StepFollower:
    """Base of the critic, meta- and sub-controller nodes and the learner's group assembler.

    Subclasses implement ``ready(step) -> bool`` and ``process(step) -> list of
    (publisher, message)`` (the replies, remembered for repeats) and may override
    ``reset()``. ``step`` is the ``env_step`` record as a dict of :data:`wire.STEP_FIELDS`."""

    skip_stale = True
    """Drop queued steps older than a step that is ready (the loop went on without them:
    their inputs were lost). The learner keeps them (an episode needs every step)."""

    def __init__(self, node=None, capacity: int = DEFAULT_CAPACITY, logger=None):
        """``node``: the middleware node (logger, topic names, a stall-report timer); without
        one (reading a bag) give a ``logger``."""
        self.node = node
        self.logger = logger if logger is not None else node.logger
        self.capacity = capacity
        self.inbox = KeyedInbox(capacity)
        self.queue: deque[dict] = deque()
        self.replies: OrderedDict[int, list] = OrderedDict()
        self.last_key = 0
        self._rejections: dict[str, Throttle] = {}
        self._head_seen: int | None = None
        if node is not None:
            node.create_timer(5.0, self._report_stall)

    # -- inputs ----------------------------------------------------------------------------------
    def on_env_step(self, msg) -> None:
        step = self.decode(wire.ENV_STEP, lambda: wire.read_step(msg))
        if step is None:
            return
        self.received(step)
        key = int(step["key"])
        if key in self.replies:
            for pub, reply in self.replies[key]:
                pub.publish(reply)
            return
        if step["t"] == 0 and key <= self.last_key:
            self.logger.info("the environment restarted (step keys start over): resynchronising")
            self.reset()
        elif key <= self.last_key or (self.queue and key <= self.queue[-1]["key"]):
            return  # stale or repeated before we answered
        self.queue.append(step)
        if len(self.queue) > self.capacity:
            dropped = self.queue.popleft()
            self.logger.warning("inputs for step key %d never arrived; skipping it", int(dropped["key"]))
        self.pump()

    def put(self, topic: str, key: int, value: Any) -> None:
        if key >= self.last_key:  # inputs of the last processed step may still be needed (prev_key)
            self.inbox.put(topic, key, value)
        self.pump()

    def decode(self, topic: str, read: Callable[[], Any]) -> Any:
        """``read()``, or ``None`` with a logged warning if the message is malformed."""
        try:
            return read()
        except (wire.ProtocolError, ValueError, TypeError, AttributeError) as exc:
            if topic not in self._rejections:
                name = self.node.resolve_topic(topic) if self.node is not None else topic
                self._rejections[topic] = Throttle(self.logger, f"rejected a message on {name}")
            self._rejections[topic].warn(exc)
            return None

    @property
    def rejected(self) -> int:
        """Malformed messages rejected so far, over all topics."""
        return sum(t.count for t in self._rejections.values())

    # -- processing ------------------------------------------------------------------------------
    def pump(self) -> None:
        if self.skip_stale and self.queue and not self.ready(self.queue[0]):
            ready_at = next((i for i, step in enumerate(self.queue) if i and self.ready(step)), 0)
            for _ in range(ready_at):
                stale = self.queue.popleft()
                self.logger.warning("skipping step key %d: a later step is complete, its inputs are not",
                                         int(stale["key"]))
        while self.queue and self.ready(self.queue[0]):
            step = self.queue.popleft()
            key = int(step["key"])
            replies = self.process(step)
            for pub, reply in replies:
                pub.publish(reply)
            self.replies[key] = replies
            while len(self.replies) > 8:
                self.replies.popitem(last=False)
            self.last_key = key
            self.inbox.forget_before(int(step["prev_key"]) or key)

    def received(self, step: dict) -> None:
        """Called for every well-formed ``env_step`` on arrival (before ordering)."""

    def _report_stall(self) -> None:
        """Log once per 5 s while the same step waits at the head of the queue."""
        head = int(self.queue[0]["key"]) if self.queue else None
        if head is not None and head == self._head_seen:
            step = self.queue[0]
            have = sorted(t for t, slot in self.inbox.slots.items() if head in slot or int(step["prev_key"]) in slot)
            self.logger.warning("step key %d (t=%d, episode %d) still waits for its inputs; have %s for it or "
                                     "its previous step %d; %d steps queued", head, step["t"], step["episode"],
                                     have, int(step["prev_key"]), len(self.queue))
        self._head_seen = head

    def ready(self, step: dict) -> bool:
        raise NotImplementedError

    def process(self, step: dict) -> list:
        raise NotImplementedError

    def reset(self) -> None:
        self.queue.clear()
        self.inbox.clear()
        self.replies.clear()
        self.last_key = 0


def done(step: dict) -> bool:
    """The step ended its episode."""
    return bool(step["terminated"] or step["truncated"])
