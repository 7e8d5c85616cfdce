"""``player`` node: plays rosbag2 (MCAP) bags back onto the graph, like ``ros2 bag play``.

Every recorded message goes out on its recorded topic (an absolute name; ``--ros-args -r
/from:=/to`` remaps it), with a QoS that suits the publishers' offers stored in the bag
(reliable / transient-local only if every recorded offer was, the deepest keep-last depth;
ROS 2's default profile where the bag recorded none), paced by its bag timestamp divided
by ``rate``. With ``clock`` the node publishes ``/clock`` (``rosgraph_msgs/msg/Clock``) in
bag time, at most ``clock_hz`` times a wall-clock second and never ahead of the next
message; a bag that recorded its own ``/clock`` has that played instead.

Reading and publishing run on a background thread; the executor spins on the main thread.
The node sets ``finished`` when the bags have been played (``loop``: never, until stopped),
so :func:`~hdrqn_ros.nodes.process.run_node` exits with ``exit_code`` 0, or 2 for a bag
that cannot be read.
"""
from __future__ import annotations

import heapq
import math
import sys
import threading
import time
import traceback
from typing import Any, Callable, Iterator

from builtin_interfaces.msg import Time
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg

from hdrqn_ros.nodes.parameters import NodeConfigError, Param, declare_parameters
from hdrqn_ros.nodes.process import run_node
from hdrqn_ros.nodes.qos import DEFAULT_QOS, keep_last
from hdrqn_ros.nodes.ros_messages import MissingRosPackage, from_cdr, interface_class
from hdrqn_ros.recording.bag import BagError, TopicInfo, bag_summary, bag_topics, read_messages, select_topics


PARAMETERS = {
    "bag": Param([""], "bag directories, played together in timestamp order (empty items are ignored)",
                 check=lambda bags: None if any(bags) else "no bag to play: give a list of bag directories"),
    "rate": Param(1.0, "bag seconds per wall-clock second", positive=True),
    "loop": Param(False, "start over at the end, until stopped"),
    "topics": Param([""], "recorded topic names to play ([''] : all)"),
    "clock": Param(True, "publish /clock in bag time"),
    "clock_hz": Param(100.0, "at most this many generated /clock messages per wall-clock second", positive=True),
    "delay": Param(1.0, "seconds to wait for discovery before the first message", low=0.0, high=3600.0),
    "wait_for_subscribers": Param(0, "first wait until every topic has this many subscribers (0: do not wait)",
                                  low=0, high=1000),
}
"""All read-only (set when the playback starts). ``delay``: seconds to wait after creating
the publishers, so that DDS discovery matches the subscribers before the first message;
``wait_for_subscribers``: first wait (without limit, until stopped) until every topic's
publisher has at least this many matched subscriptions, for a consumer that must get every
message."""

CLOCK_TOPIC = "/clock"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"


def parameter_overrides(values: dict[str, Any]) -> list[Parameter]:
    """Values of :data:`PARAMETERS` given in Python (``hdrqn bag play``) as the node's
    ``parameter_overrides``, which win over ``--ros-args``: typed as declared (an int for a
    double is a double, ``[]`` is ``[""]``: rclpy takes an empty list for bytes, and the
    lists' empty names are ignored); :class:`NodeConfigError` for an unknown name or a value
    of another type."""
    overrides = []
    for name, value in values.items():
        if name not in PARAMETERS:
            raise NodeConfigError(f"node player has no parameter {name!r} (it declares {sorted(PARAMETERS)})")
        default = PARAMETERS[name].default
        if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        elif isinstance(default, list) and isinstance(value, (list, tuple)) and not value:
            value = [""]
        try:
            overrides.append(Parameter(name, Parameter.Type.from_parameter_value(default), value))
        except ValueError:  # rclpy: the type and the value do not agree
            raise NodeConfigError(f"node player: parameter {name!r} must be {type(default).__name__} "
                                  f"(default {default!r}), got {value!r}") from None
    return overrides


def _merge(a: TopicInfo | None, b: TopicInfo) -> TopicInfo:
    """One topic seen in several bags: counts add up, QoS suits every recorded offer."""
    if a is None:
        return b

    def both(x, y, combine):
        return y if x is None else x if y is None else combine(x, y)
    return TopicInfo(a.type_name, a.message_count + b.message_count,
                     both(a.reliable, b.reliable, lambda x, y: x and y),
                     both(a.transient_local, b.transient_local, lambda x, y: x and y),
                     both(a.depth, b.depth, max))


def on_wire(cdr: bytes) -> bytes:
    """A bag's CDR bytes as published: zero-padded to a multiple of 4 bytes, as DDS sends a
    serialized payload (else the DDS implementation pads with whatever its buffer held)."""
    return bytes(cdr) + b"\0" * (-len(cdr) % 4)


def playback_qos(info: TopicInfo) -> QoSProfile:
    """The QoS to publish a recorded topic with (:data:`DEFAULT_QOS` for what the bag did not record)."""
    reliable = DEFAULT_QOS.reliability == ReliabilityPolicy.RELIABLE if info.reliable is None else info.reliable
    return keep_last(info.depth or DEFAULT_QOS.depth, reliable=reliable, transient_local=bool(info.transient_local))


class PlayerNode(Node):
    """Plays ``bag`` onto the graph. ``progress(player)`` (optional) is called every
    ``progress_period`` seconds (wall time) on the spinning thread (the CLI's progress line);
    ``kwargs`` go to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``)."""

    def __init__(self, progress: Callable[["PlayerNode"], None] | None = None, progress_period: float = 2.0,
                 **kwargs):
        super().__init__("player", **kwargs)
        params = self.params = declare_parameters(self, PARAMETERS)
        self.bags = [b for b in params["bag"] if b]
        self.rate, self.loop, self.delay = params["rate"], params["loop"], params["delay"]

        infos: dict[str, TopicInfo] = {}
        first_bag: dict[str, str] = {}
        spans: list[tuple[int, int]] = []
        for bag in self.bags:
            for topic, info in bag_topics(bag).items():
                if topic in infos and infos[topic].type_name != info.type_name:
                    raise BagError(f"{bag}: topic {topic} is {info.type_name}, but {infos[topic].type_name} "
                                   f"in {first_bag[topic]}: bags played together must agree on types")
                infos[topic] = _merge(infos.get(topic), info)
                first_bag.setdefault(topic, bag)
            summary = bag_summary(bag)
            if summary["message_count"]:
                spans.append((summary["start_ns"], summary["end_ns"]))

        # the bags' time span (all topics), for progress reports
        self.start_ns = min((s for s, _ in spans), default=None)
        self.end_ns = max((e for _, e in spans), default=None)
        wanted = [t for t in params["topics"] if t]
        bag_clock = infos.get(CLOCK_TOPIC)
        selected = select_topics(wanted, set(infos), ", ".join(self.bags)) if wanted else set(infos)
        if params["clock"] and bag_clock is not None:
            if bag_clock.type_name != CLOCK_TYPE:
                raise BagError(f"{first_bag[CLOCK_TOPIC]}: topic {CLOCK_TOPIC} is {bag_clock.type_name}, not "
                               f"{CLOCK_TYPE}; play it with clock:=false")
            selected.add(CLOCK_TOPIC)  # the recorded clock is the clock
        self.generate_clock = params["clock"] and bag_clock is None
        self.clock_period = 1.0 / params["clock_hz"] if self.generate_clock else math.inf

        self.topics = {t: infos[t] for t in sorted(selected)}
        self.topic_publishers: dict[str, Any] = {}  # recorded topic -> its publisher
        for topic, info in self.topics.items():
            try:
                msg_type = interface_class(info.type_name)
            except (ValueError, MissingRosPackage) as exc:
                raise BagError(f"{first_bag[topic]}: topic {topic}: {exc}") from None
            self.topic_publishers[topic] = self.create_publisher(msg_type, topic, playback_qos(info))
        self.clock_pub = self.create_publisher(ClockMsg, CLOCK_TOPIC, DEFAULT_QOS) if self.generate_clock else None

        self.total = sum(info.message_count for info in self.topics.values())  # per pass
        self.published = 0  # messages published, all passes
        self.passes = 0
        self.bag_time_ns: int | None = None  # stamp of the last message published
        self.finished = False
        self.exit_code = 0
        self._stop = threading.Event()
        self.get_logger().info(f"playing {self.total} messages on {len(self.topics)} topics from "
                               f"{', '.join(self.bags)} at rate {self.rate:g}{', looping' if self.loop else ''}"
                               f"{', publishing /clock' if self.generate_clock else ''}")
        if progress is not None:
            self.create_timer(progress_period, lambda: progress(self), clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._thread = threading.Thread(target=self._run, name="player", daemon=True)
        self._thread.start()

    # -- the playing thread ----------------------------------------------------------------
    def _wait_for_subscribers(self) -> bool:
        """Wait until each publisher has ``wait_for_subscribers`` matched subscriptions; False if stopped."""
        wanted = self.params["wait_for_subscribers"]
        publishers = {**self.topic_publishers, **({CLOCK_TOPIC: self.clock_pub} if self.clock_pub is not None else {})}
        next_report = time.monotonic() + 5.0
        while wanted > 0 and not self._stop.is_set():
            missing = sorted(t for t, pub in publishers.items() if pub.get_subscription_count() < wanted)
            if not missing:
                return True
            if time.monotonic() >= next_report:
                self.get_logger().info(f"waiting for {wanted} subscriber(s) on {', '.join(missing)}")
                next_report += 5.0
            self._stop.wait(0.05)
        return not self._stop.is_set()

    def _messages(self) -> Iterator[tuple[int, int, str, str, str, bytes]]:
        """(stamp, bag index, bag, topic, type, cdr) of all bags in stamp order."""
        topics = list(self.topics)
        streams = [((t, i, bag, topic, type_name, data) for topic, type_name, t, data in read_messages(bag, topics))
                   for i, bag in enumerate(self.bags)]
        return heapq.merge(*streams, key=lambda m: (m[0], m[1]))

    def _run(self) -> None:
        log = self.get_logger()
        try:
            if not self._wait_for_subscribers():
                return
            wall0 = time.monotonic()
            if self._stop.wait(self.delay):
                return
            while not self._stop.is_set():
                self.passes += 1
                if self.loop:
                    log.info(f"playing pass {self.passes}")
                if not self._play_once() or not self.loop:
                    break
            log.info(f"played {self.published} messages on {len(self.topics)} topics in {self.passes} pass(es) over "
                     f"{time.monotonic() - wall0 - self.delay:.1f} s (rate {self.rate:g})"
                     f"{', stopped early' if self._stop.is_set() else ''}")
        except BagError as exc:
            log.error(f"error: {exc}")
            self.exit_code = 2
        except Exception:  # a bug: say so, with the traceback, and exit non-zero
            log.error(f"playing the bags failed:\n{traceback.format_exc()}")
            self.exit_code = 1
        finally:
            self.finished = True

    def _play_once(self) -> int:
        """One pass through the bags; the number of messages published (0 when stopped early)."""
        start_ns = start_wall = None
        self._next_clock = time.monotonic() if self.clock_pub is not None else math.inf
        count = 0
        for t, _i, bag, topic, type_name, data in self._messages():
            if start_wall is None:
                start_ns, start_wall = t, time.monotonic()
            try:
                from_cdr(type_name, data)  # it must decode; the recorded bytes go out as they are
            except Exception as exc:
                raise BagError(f"{bag}: the message on {topic} at {t} ns does not decode as {type_name} "
                               f"({type(exc).__name__}: {exc})") from None
            if not self._wait_until(t, start_ns, start_wall):
                return 0
            self.topic_publishers[topic].publish(on_wire(data))
            self.published += 1
            self.bag_time_ns = t
            count += 1
        return count

    def _wait_until(self, t_ns: int, start_ns: int, start_wall: float) -> bool:
        """Sleep until bag time ``t_ns`` is due, publishing the generated clock on the way;
        False if stopped."""
        due = start_wall + (t_ns - start_ns) / 1e9 / self.rate
        while True:
            now = time.monotonic()
            if self.clock_pub is not None and now >= self._next_clock:
                bag_now = start_ns + int((now - start_wall) * self.rate * 1e9)
                self._publish_clock(min(bag_now, t_ns))
                self._next_clock = max(self._next_clock + self.clock_period, now)
            if now >= due:
                return not self._stop.is_set()
            if self._stop.wait(min(due, self._next_clock) - now):
                return False

    def _publish_clock(self, t_ns: int) -> None:
        self.clock_pub.publish(ClockMsg(clock=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)))

    def close(self) -> None:
        """Stop playing (Ctrl-C, SIGTERM) and wait for the playing thread."""
        self._stop.set()
        self._thread.join(timeout=10)


def main(argv: list[str] | None = None) -> int:
    return run_node(PlayerNode, argv, (BagError,))


if __name__ == "__main__":
    sys.exit(main())
