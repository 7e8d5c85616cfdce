"""The inputs a node waits for, and a warning when one stays quiet naming the node that would publish it."""
from __future__ import annotations

import time

from rclpy.clock import Clock, ClockType

from hdrqn_ros.nodes.lifecycle import ManagedNode


class QuietInputs:
    """Each expected input topic, when it was last heard (wall time) and who publishes it.
    Once a second, while the node is active, a topic quiet for the node's ``quiet_input_s``
    parameter is reported, once per quiet spell."""

    def __init__(self, node: ManagedNode):
        self.node = node
        self.heard: dict[str, tuple[float, str]] = {}  # topic -> (last heard, monotonic s; who publishes it)
        self.reported: set[str] = set()
        node.create_timer(1.0, self._report, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def expect(self, topic: str, publisher: str) -> None:
        """``topic`` is an input published by ``publisher`` (in words): report when none comes."""
        self.heard[topic] = (time.monotonic(), publisher)

    def hear(self, topic: str) -> None:
        """A message came on ``topic``."""
        self.heard[topic] = (time.monotonic(), self.heard[topic][1])
        self.reported.discard(topic)

    def restart(self) -> None:
        """The node starts acting: every input counts as heard now."""
        now = time.monotonic()
        self.heard = {topic: (now, publisher) for topic, (_, publisher) in self.heard.items()}
        self.reported.clear()

    def quiet(self) -> list[str]:
        """The inputs reported quiet, in words."""
        now = time.monotonic()
        return [f"nothing on {self.node.resolve_topic_name(topic)} for {now - last:.0f} s: waiting for {publisher}"
                for topic, (last, publisher) in self.heard.items() if topic in self.reported]

    def _report(self) -> None:
        if not self.node.active:
            return
        now = time.monotonic()
        for topic, (last, publisher) in self.heard.items():
            if now - last >= self.node.params["quiet_input_s"] and topic not in self.reported:
                self.reported.add(topic)
                self.node.get_logger().warning(f"nothing on {self.node.resolve_topic_name(topic)} for "
                                               f"{now - last:.0f} s: waiting for {publisher}")
