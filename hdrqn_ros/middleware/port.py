"""The middleware port: the little that nodes need from ROS 2.

Two backends implement it with the same behaviour, so one node code base runs on both:
:mod:`hdrqn_ros.middleware.rclpy_backend` (real ROS 2 Jazzy nodes: the default wherever
``import rclpy`` works, from the PyPI wheels or a sourced ROS 2) and
:mod:`hdrqn_ros.middleware.cyclone` (PyPI ``cyclonedds``, speaking ROS 2's wire
conventions, for platforms without rclpy and for mixed graphs). Nodes never import either backend;
they get a :class:`Node` from :func:`hdrqn_ros.middleware.open_middleware`.

Message types are named as in ROS 2 (``"sensor_msgs/msg/Image"``); :meth:`Node.msg`
returns the backend's class for a name. Both backends' classes take keyword arguments
named like the ROS fields. Array fields accept numpy arrays; read them back through
:func:`hdrqn_ros.middleware.messages.as_array` (rclpy gives ``array.array``, the Cyclone
backend numpy arrays).
"""
from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Callable, Protocol


@dataclass(frozen=True)
class QoS:
    """The QoS settings we use; ``depth`` is the keep-last history depth (samples)."""

    depth: int = 10
    reliable: bool = True
    transient_local: bool = False


DEFAULT_QOS = QoS()
"""ROS 2's default (``rclpy.qos.qos_profile_default``): reliable, volatile, keep-last 10."""
LATCHED_QOS = QoS(depth=1, transient_local=True)
"""Reliable, transient-local, keep-last 1: late joiners get the last sample (weights, status)."""


@dataclass(frozen=True)
class ParameterRule:
    """What ``ros2 param describe`` shows of a parameter and what ``ros2 param set`` may do
    to it: a one-line ``description``; ``live`` parameters may change while the node runs
    (the node applies the new value at its next use), the others are read-only; ``low`` /
    ``high`` bound a number (inclusive, shown as the descriptor's range); ``positive``
    asks for > 0; ``choices`` lists the allowed strings."""

    description: str
    live: bool = False
    low: float | None = None
    high: float | None = None
    positive: bool = False
    choices: tuple[str, ...] = ()

    def refusal(self, name: str, value: Any) -> str | None:
        """Why ``value`` is not allowed for parameter ``name`` (``None``: it is)."""
        if self.choices and value not in self.choices:
            return f"parameter {name} must be one of {list(self.choices)}, got {value!r}"
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if value != value:  # NaN
                return f"parameter {name} must be a number, got nan"
            if self.positive and not value > 0:
                return f"parameter {name} must be > 0, got {value!r}"
            if self.low is not None and value < self.low or self.high is not None and value > self.high:
                return f"parameter {name} must be in {self.low:g}..{self.high:g}, got {value!r}"
        return None

    def constraints(self, managed: bool = False) -> str:
        """The rules in words (the descriptor's ``additional_constraints``); ``managed``: the
        parameter belongs to a managed node, where a not-live one changes while unconfigured."""
        words = [] if self.live else \
            ["changes only while the node is unconfigured" if managed else "read-only while the node runs"]
        if self.positive:
            words.append("> 0")
        if self.choices:
            words.append("one of " + ", ".join(self.choices))
        return "; ".join(words)


class Lifecycle(Protocol):
    """What a managed (lifecycle) node does on each transition of ROS 2's node state machine
    (``unconfigured -> inactive -> active``), called on the spinning thread."""

    def on_configure(self) -> str:
        """Build the node from its parameters: "" when configured, else why not (the node stays unconfigured)."""

    def on_activate(self) -> None: ...

    def on_deactivate(self) -> None: ...

    def on_cleanup(self) -> None:
        """Release everything configure made (back to unconfigured)."""

    def on_shutdown(self) -> None: ...


class Publisher(Protocol):
    def publish(self, msg: Any) -> None:
        """Publish a message of the topic's type, or its CDR bytes (header first) as they are."""

    def get_subscription_count(self) -> int:
        """Subscriptions matched to this publisher (as rclpy's ``Publisher`` answers)."""


class Node(ABC):
    """One ROS 2 node: publishers, subscriptions, timers, parameters and a logger.

    Topic names are resolved like ROS 2 does (relative names get the node's namespace,
    ``~`` the node's name, remappings from ``--ros-args -r`` apply)."""

    name: str
    namespace: str

    @property
    def fully_qualified_name(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"

    @abstractmethod
    def msg(self, type_name: str) -> type:
        """The message class for ``type_name`` (``"pkg/msg/Type"``)."""

    def to_cdr(self, msg: Any) -> bytes:
        """``msg`` serialized as ROS 2 does (XCDR1), with the 4-byte encapsulation header
        (``00 01 00 00``, little-endian): the bytes a rosbag2 bag stores for it."""
        raise NotImplementedError(f"{type(self).__name__} cannot serialize messages")

    def from_cdr(self, type_name: str, data: bytes) -> Any:
        """The message of type ``type_name`` that the CDR bytes ``data`` (encapsulation header
        first, as in a rosbag2 bag) hold; :class:`ValueError` for an unknown type."""
        raise NotImplementedError(f"{type(self).__name__} cannot deserialize messages")

    def pack(self, values) -> Any:
        """A numeric numpy array as the value of a message's array field (numpy here;
        ``array.array`` for rclpy, whose message classes accept no numpy arrays)."""
        return values

    @abstractmethod
    def create_publisher(self, type_name: str, topic: str, qos: QoS = DEFAULT_QOS) -> Publisher: ...

    @abstractmethod
    def create_subscription(self, type_name: str, topic: str, callback: Callable[[Any], None],
                            qos: QoS = DEFAULT_QOS, raw: bool = False) -> Any:
        """``callback(msg)`` runs on the thread that spins the middleware; with ``raw`` it gets
        the sample's CDR bytes as received (header first, what a bag stores), undecoded.
        Samples over ``max_message_bytes`` are dropped either way."""

    @abstractmethod
    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """``callback()`` every ``period_s`` seconds (wall time) on the spinning thread."""

    def create_service(self, type_name: str, name: str, callback: Callable[[Any, Any], Any]) -> Any:
        """A service server of ``type_name`` (``"std_srvs/srv/Trigger"``): ``callback(request,
        response)`` fills and returns the response, on the spinning thread. Only rclpy has
        services: elsewhere :class:`BackendError` names the backend and the service."""
        raise BackendError(f"the {self.backend_name} backend offers no ROS 2 services: {self.resolve_topic(name)} "
                           f"({type_name}) needs the rclpy backend")

    backend_name = "this"

    @abstractmethod
    def declare_parameters(self, defaults: dict[str, Any], overrides: dict[str, Any] | None = None,
                           rules: dict[str, ParameterRule] | None = None) -> dict[str, Any]:
        """Declare parameters with their defaults; returns their values after overrides
        from ``--ros-args -p name:=value`` and ``--params-file``, then from ``overrides``
        (values given in Python by code that builds the node in-process; they win, like
        rclpy's ``Node(parameter_overrides=...)``). A value whose type differs from the
        default's, or an override without a default, raises :class:`ParameterError`.
        ``rules`` describe them (rclpy: their descriptors; a value outside a rule's range
        raises :class:`ParameterError`)."""

    def on_parameters_set(self, rules: dict[str, ParameterRule], apply: Callable[[str, Any], None]) -> None:
        """Accept changes to the ``live`` parameters of ``rules`` at run time (``ros2 param
        set``): each is checked against its rule (a refusal names the parameter and the
        rule), then ``apply(name, value)`` is called. The Cyclone backend has no parameter
        services: nothing to do there."""

    @abstractmethod
    def wait_for_delivery(self, publisher: Publisher, timeout_s: float) -> bool:
        """Block until every matched subscription has acknowledged what ``publisher`` sent
        (reliable QoS), at most ``timeout_s``: whether they all did. For a last message
        before the process exits (the zero velocity command)."""

    def release(self) -> None:
        """Destroy every publisher, subscription, timer, service and parameter callback made
        so far (a managed node's cleanup); declared parameters stay, with their values."""
        raise NotImplementedError(f"{type(self).__name__} has no managed mode")

    @property
    @abstractmethod
    def logger(self) -> logging.Logger: ...

    @abstractmethod
    def resolve_topic(self, topic: str) -> str:
        """The fully qualified name ``topic`` resolves to (after remapping)."""

    @abstractmethod
    def destroy(self) -> None: ...


class Middleware(ABC):
    """One process's connection to the ROS 2 graph (an rclpy context or a DDS participant)."""

    backend: str

    @abstractmethod
    def create_node(self, name: str, namespace: str = "") -> Node:
        """A node; ``--ros-args -r __node:=`` / ``__ns:=`` given to the process override
        ``name`` / ``namespace``."""

    def create_managed_node(self, name: str, lifecycle: Lifecycle) -> Node:
        """A managed (lifecycle) node, born unconfigured: ROS 2's ``~/change_state`` and
        ``~/get_state`` services drive ``lifecycle``'s transitions. Only rclpy has them:
        elsewhere :class:`BackendError`."""
        raise BackendError(f"the {self.backend} backend has no managed (lifecycle) nodes: {name} needs the "
                           f"rclpy backend to run managed")

    @abstractmethod
    def spin(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> None:
        """Run callbacks and timers on this thread until :meth:`shutdown`, ``until()`` is
        true or ``timeout_s`` passed."""

    @abstractmethod
    def shutdown(self) -> None:
        """Destroy all nodes and leave the graph; safe to call twice and from signal handlers' aftermath."""

    def __enter__(self) -> "Middleware":
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown()


class BackendError(ValueError):
    """A middleware backend that was asked for but cannot be used here (names what to install)."""


class ParameterError(ValueError):
    """A parameter override of the wrong type, or a parameters file that cannot be used."""


class RosArgsError(ValueError):
    """Malformed ``--ros-args`` (unknown flag, ``-p`` without ``name:=value``, ...)."""
