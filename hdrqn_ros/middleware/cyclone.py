"""The Cyclone DDS backend: ROS 2 nodes without ROS, on ROS 2's wire conventions.

What makes a ROS 2 system (rmw_cyclonedds_cpp, same ``ROS_DOMAIN_ID``) see us as peers:

* topics ``rt/<fully qualified name>`` with DDS types ``pkg::msg::dds_::Type_``, keyless,
  serialized as XCDR1 (:mod:`hdrqn_ros.middleware.messages`);
* ROS 2 QoS (default: reliable, volatile, keep-last 10);
* participant USER_DATA ``enclave=/;`` and the ``ros_discovery_info`` topic
  (``rmw_dds_common/msg/ParticipantEntitiesInfo``, reliable, transient-local, keep-last 1)
  listing each node's reader and writer GUIDs, so ``ros2 node list`` shows our nodes.

Safe default network: unless an interface is configured (``dds_interface`` parameter,
``HDRQN_DDS_INTERFACE``, or the user's own ``CYCLONEDDS_URI``), the participant binds to
the loopback interface with unicast discovery to 127.0.0.1 and multicast off, so nothing
leaves the machine.
"""
from __future__ import annotations

import gc
import logging
import os
import sys
import threading
import time
from typing import Any, Callable

from cyclonedds._clayer import ddspy_take, ddspy_write
from cyclonedds.core import GuardCondition, InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from hdrqn_ros.middleware.messages import DecodeError, decode, message_class
from hdrqn_ros.middleware.network import LOOPBACK, cyclone_config, interface_address
from hdrqn_ros.middleware.port import DEFAULT_QOS, Middleware, Node, ParameterError, ParameterRule, QoS
from hdrqn_ros.middleware.ros_args import (check_overrides, check_parameter_type, process_settings,
                                           remap_and_resolve, split_ros_args)
from hdrqn_ros.throttle import Throttle

MAX_TAKE = 64
"""Samples taken from one reader per executor pass (the rest wait in the reader's history)."""


def _dds_qos(qos: QoS) -> Qos:
    return Qos(Policy.Reliability.Reliable(duration(seconds=1)) if qos.reliable else Policy.Reliability.BestEffort,
               Policy.Durability.TransientLocal if qos.transient_local else Policy.Durability.Volatile,
               Policy.History.KeepLast(qos.depth),
               Policy.DataRepresentation(use_cdrv0_representation=True))


_LOG_FORMAT = "[%(levelname)s] [%(created).6f] [%(name)s]: %(message)s"


def _setup_logging(level: str | None) -> None:
    root = logging.getLogger("hdrqn")
    if not root.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(_LOG_FORMAT))
        root.addHandler(handler)
        root.propagate = False
    root.setLevel(level or "INFO")


class _Publisher:
    def __init__(self, writer: DataWriter, cls: type, topic: str):
        self.writer, self.cls, self.topic = writer, cls, topic

    def publish(self, msg: Any) -> None:
        """``msg``: a message of the topic's type, or its CDR bytes (header first) as they are."""
        if isinstance(msg, (bytes, bytearray, memoryview)):
            ddspy_write(self.writer._ref, bytes(msg))
            return
        if not isinstance(msg, self.cls):
            raise TypeError(f"{self.topic} carries {self.cls.__ros_type__}, not {type(msg).__name__}")
        self.writer.write(msg)

    def get_subscription_count(self) -> int:
        return len(self.writer.get_matched_subscriptions())


class _Subscription:
    def __init__(self, node: "CycloneNode", reader: DataReader, cls: type, topic: str, callback, raw: bool):
        self.node, self.reader, self.cls, self.topic, self.callback = node, reader, cls, topic, callback
        self.raw = raw
        self.dropped = Throttle(node.logger, f"dropped a sample on {topic}")  # malformed or oversized

    def take(self) -> list[Any]:
        """Take up to :data:`MAX_TAKE` samples; malformed ones are logged and skipped."""
        raw = ddspy_take(self.reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, MAX_TAKE)
        if isinstance(raw, int):
            return []
        out = []
        limit = self.node.middleware.max_message_bytes
        for data, info in raw:
            if not info.valid_data:
                continue
            if len(data) > limit:
                self.dropped.warn(f"{len(data)} B exceeds the {limit} B message limit")
                continue
            if self.raw:
                out.append(bytes(data))
                continue
            try:
                out.append(decode(self.cls, data))
            except DecodeError as exc:  # a peer sent bytes that do not decode as this type
                self.dropped.warn(exc)
        return out


class _Timer:
    def __init__(self, period_s: float, callback):
        self.period, self.callback = period_s, callback
        self.next = time.monotonic() + period_s


class CycloneNode(Node):
    """A node on the process's DDS participant (ROS 2 nodes share their context's participant)."""

    backend_name = "Cyclone DDS"

    def __init__(self, middleware: "CycloneMiddleware", name: str, namespace: str):
        self.middleware = middleware
        self.name, self.namespace = name, namespace or "/"
        self._logger = logging.getLogger(f"hdrqn.{self.fully_qualified_name.lstrip('/').replace('/', '.')}")
        self.publishers: list[_Publisher] = []
        self.subscriptions: list[_Subscription] = []
        self.timers: list[_Timer] = []
        self.parameters: dict[str, Any] = {}

    def msg(self, type_name: str) -> type:
        return message_class(type_name)

    def to_cdr(self, msg: Any) -> bytes:
        if getattr(type(msg), "__ros_type__", None) is None:
            raise TypeError(f"not a ROS message of this backend: {type(msg).__name__}")
        return msg.serialize(use_version_2=False)

    def from_cdr(self, type_name: str, data: bytes) -> Any:
        """:class:`~hdrqn_ros.middleware.messages.DecodeError` (a ValueError) for bytes that do not decode."""
        return decode(message_class(type_name), data)

    @property
    def logger(self) -> logging.Logger:
        return self._logger

    def resolve_topic(self, topic: str) -> str:
        return remap_and_resolve(self.middleware.ros_args, topic, self.namespace, self.name)

    def wait_for_delivery(self, publisher: _Publisher, timeout_s: float) -> bool:
        return publisher.writer.wait_for_acks(duration(seconds=timeout_s))

    def create_publisher(self, type_name: str, topic: str, qos: QoS = DEFAULT_QOS) -> _Publisher:
        cls = message_class(type_name)
        name = self.resolve_topic(topic)
        writer = DataWriter(self.middleware.participant, self.middleware.topic(name, cls), qos=_dds_qos(qos))
        pub = _Publisher(writer, cls, name)
        self.publishers.append(pub)
        self.middleware.announce()
        return pub

    def create_subscription(self, type_name: str, topic: str, callback: Callable[[Any], None],
                            qos: QoS = DEFAULT_QOS, raw: bool = False) -> _Subscription:
        cls = message_class(type_name)
        name = self.resolve_topic(topic)
        reader = DataReader(self.middleware.participant, self.middleware.topic(name, cls), qos=_dds_qos(qos))
        sub = _Subscription(self, reader, cls, name, callback, raw)
        self.subscriptions.append(sub)
        self.middleware.watch(reader)
        self.middleware.announce()
        return sub

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> _Timer:
        if period_s <= 0:
            raise ValueError(f"timer period must be > 0 s, got {period_s}")
        timer = _Timer(period_s, callback)
        self.timers.append(timer)
        self.middleware.wake()
        return timer

    def declare_parameters(self, defaults: dict[str, Any], overrides: dict[str, Any] | None = None,
                           rules: dict[str, ParameterRule] | None = None) -> dict[str, Any]:
        given = {**self.middleware.ros_args.parameters_for(self.name, self.namespace),
                 **check_overrides(self.fully_qualified_name, defaults, overrides)}
        for name, default in defaults.items():
            value = given.get(name, default)
            self.parameters[name] = check_parameter_type(self.fully_qualified_name, name, default, value)
            rule = (rules or {}).get(name)
            if rule is not None and (rule.low is not None or rule.high is not None) and \
                    (why := rule.refusal(name, self.parameters[name])):
                raise ParameterError(f"node {self.fully_qualified_name}: {why}")
        return {name: self.parameters[name] for name in defaults}

    def destroy(self) -> None:
        self.middleware.remove_node(self)


class CycloneMiddleware(Middleware):
    """One DDS participant per process, a single-threaded executor, ROS 2 graph discovery."""

    backend = "cyclone"

    def __init__(self, argv: list[str] | None = None, domain_id: int | None = None, interface: str | None = None):
        self.user_args, self.ros_args = split_ros_args(list(argv or []))
        _setup_logging(self.ros_args.log_level)
        settings = process_settings(self.ros_args)
        if domain_id is None:
            domain_id = settings.domain_id
        if not 0 <= domain_id <= 232:
            raise ValueError(f"ROS_DOMAIN_ID must be in 0..232, got {domain_id}")
        interface = interface or settings.interface
        self.domain_id = domain_id
        self.max_message_bytes = settings.max_message_bytes
        if interface is None and os.environ.get("CYCLONEDDS_URI"):
            self.interface = "CYCLONEDDS_URI"
            self._domain = Domain(domain_id, os.environ["CYCLONEDDS_URI"])
        else:
            self.interface = interface or LOOPBACK
            if self.interface != LOOPBACK:
                interface_address(self.interface)  # a ParameterError naming it, not Cyclone's bare DDSException
            self._domain = Domain(domain_id, cyclone_config(self.interface))
        self.participant = DomainParticipant(domain_id, qos=Qos(Policy.Userdata(b"enclave=/;")))
        self._topics: dict[str, Topic] = {}
        self._nodes: list[CycloneNode] = []
        self._waitset = WaitSet(self.participant)
        self._guard = GuardCondition(self.participant)
        self._waitset.attach(self._guard)
        self._lock = threading.RLock()
        self._shutdown = False
        self._gid_cls = message_class("rmw_dds_common/msg/Gid")
        self._node_info_cls = message_class("rmw_dds_common/msg/NodeEntitiesInfo")
        self._info_cls = message_class("rmw_dds_common/msg/ParticipantEntitiesInfo")
        self._info_writer = DataWriter(self.participant,
                                       Topic(self.participant, "ros_discovery_info", self._info_cls),
                                       qos=_dds_qos(QoS(depth=1, transient_local=True)))

    # -- graph ---------------------------------------------------------------------------
    def topic(self, name: str, cls: type) -> Topic:
        """The DDS topic ``rt<name>`` (one per name and participant)."""
        with self._lock:
            topic = self._topics.get(name)
            if topic is None:
                topic = self._topics[name] = Topic(self.participant, "rt" + name, cls)
            elif topic.data_type is not cls:
                raise TypeError(f"topic {name} already carries {topic.data_type.__ros_type__}, "
                                f"not {cls.__ros_type__}")
            return topic

    def _gid(self, entity) -> Any:
        return self._gid_cls(data=list(entity.guid.bytes))

    def announce(self) -> None:
        """Publish ``ros_discovery_info``: this participant's nodes and their endpoints."""
        with self._lock:
            if self._shutdown:
                return
            nodes = [self._node_info_cls(node_namespace=n.namespace, node_name=n.name,
                                         reader_gid_seq=[self._gid(s.reader) for s in n.subscriptions],
                                         writer_gid_seq=[self._gid(p.writer) for p in n.publishers])
                     for n in self._nodes]
            self._info_writer.write(self._info_cls(gid=self._gid(self.participant), node_entities_info_seq=nodes))

    def create_node(self, name: str, namespace: str = "") -> CycloneNode:
        name = self.ros_args.node_name or name
        namespace = self.ros_args.namespace or namespace or "/"
        if not namespace.startswith("/"):
            namespace = "/" + namespace
        node = CycloneNode(self, name, namespace.rstrip("/") or "/")
        with self._lock:
            self._nodes.append(node)
            first = len(self._nodes) == 1
        self.announce()
        if first:
            node.logger.info("middleware cyclone: Cyclone DDS on %s, domain %d", self.interface, self.domain_id)
        return node

    def remove_node(self, node: CycloneNode) -> None:
        with self._lock:
            if node in self._nodes:
                self._nodes.remove(node)
                for sub in node.subscriptions:
                    self._waitset.detach(sub.reader)
        self.announce()

    # -- executor -------------------------------------------------------------------------
    def watch(self, reader: DataReader) -> None:
        with self._lock:
            self._waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Alive))

    def wake(self) -> None:
        self._guard.set(True)

    def spin_once(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for data or a due timer, then run the callbacks."""
        with self._lock:
            nodes = list(self._nodes)
        now = time.monotonic()
        due = min((t.next for n in nodes for t in n.timers), default=now + timeout_s)
        wait_s = max(0.0, min(timeout_s, due - now))
        if wait_s > 0:
            self._waitset.wait(int(wait_s * 1e9))
        self._guard.set(False)
        for node in nodes:
            for sub in list(node.subscriptions):
                for msg in sub.take():
                    sub.callback(msg)
            now = time.monotonic()
            for timer in list(node.timers):
                if timer.next <= now:
                    timer.next = max(timer.next + timer.period, now)
                    timer.callback()

    def spin(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> None:
        end = None if timeout_s is None else time.monotonic() + timeout_s
        while not self._shutdown and not (until is not None and until()):
            left = 0.1 if end is None else min(0.1, end - time.monotonic())
            if left <= 0:
                return
            self.spin_once(left)

    def shutdown(self) -> None:
        with self._lock:
            if self._shutdown:
                return
            self._shutdown = True
            self._nodes.clear()
        self.wake()
        # dropping the references deletes the DDS entities (their lifetime follows the Python objects)
        self._info_writer = self._waitset = self._guard = None
        self._topics.clear()
        self.participant = self._domain = None
        gc.collect()
