"""The rclpy backend of the middleware port, for a ROS 2 Jazzy system (``import rclpy`` works).

This module imports without rclpy so that :func:`rclpy_available` can be asked anywhere;
constructing :class:`RclpyMiddleware` without rclpy raises :class:`ImportError`.
"""
from __future__ import annotations

import array
import importlib
import logging
import time
from functools import lru_cache
from typing import Any, Callable

try:
    import rclpy
    import rclpy.node
    from rclpy.clock import Clock, ClockType
    from rclpy.context import Context
    from rclpy.exceptions import InvalidParameterTypeException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message, serialize_message
except ImportError as exc:  # no sourced ROS 2 (or a broken one): the Cyclone backend is used
    _RCLPY_IMPORT_ERROR: ImportError | None = exc
else:
    _RCLPY_IMPORT_ERROR = None

import numpy as np

from hdrqn_ros.middleware.port import (DEFAULT_QOS, Middleware, Node, ParameterError, Publisher, QoS,
                                       RosArgsError)

_SPIN_STEP_S = 0.05
_TYPECODES = {"u1": "B", "i1": "b", "u2": "H", "i2": "h", "u4": "I", "i4": "i", "u8": "Q", "i8": "q", "f4": "f",
              "f8": "d"}
_RCUTILS_METHODS = ((logging.CRITICAL, "fatal"), (logging.ERROR, "error"), (logging.WARNING, "warning"),
                    (logging.INFO, "info"), (logging.NOTSET, "debug"))


def rclpy_available() -> bool:
    """Whether ``import rclpy`` worked (a sourced ROS 2 installation)."""
    return _RCLPY_IMPORT_ERROR is None


@lru_cache(maxsize=None)
def _message_class(type_name: str) -> type:
    """The rosidl Python class for ``"pkg/msg/Type"``."""
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        raise ValueError(f"message type {type_name!r} is not of the form 'pkg/msg/Type'")
    pkg, _, name = parts
    try:
        return getattr(importlib.import_module(f"{pkg}.msg"), name)
    except (ImportError, AttributeError):
        raise ValueError(f"unknown message type {type_name!r}: no class {name} in the Python "
                         f"module {pkg}.msg (is the package built and sourced?)") from None


def _qos_profile(qos: QoS) -> QoSProfile:
    """Our :class:`QoS` as an rclpy profile (history is always keep-last)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth,
        reliability=ReliabilityPolicy.RELIABLE if qos.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos.transient_local else DurabilityPolicy.VOLATILE,
    )


class _RcutilsHandler(logging.Handler):
    """Forwards formatted :mod:`logging` records to an rclpy (rcutils) logger."""

    def __init__(self, ros_logger: Any) -> None:
        super().__init__(logging.DEBUG)
        self._ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            method = next(m for level, m in _RCUTILS_METHODS if record.levelno >= level)
            getattr(self._ros_logger, method)(self.format(record))  # format: printf args, tracebacks
        except Exception:
            self.handleError(record)


class RclpyNode(Node):
    """A :class:`Node` backed by an ``rclpy.node.Node``."""

    def __init__(self, node: rclpy.node.Node) -> None:
        self._node = node
        self.name = node.get_name()  # after any __node / __ns remapping
        self.namespace = node.get_namespace()
        # A Logger outside logging's registry: nodes of equal names do not share handlers, and
        # records reach rcutils (console, /rosout) once, not also through the root logger.
        self._logger = logging.Logger(f"hdrqn.{node.get_logger().name}", logging.DEBUG)
        self._logger.propagate = False
        self._logger.addHandler(_RcutilsHandler(node.get_logger()))
        self._destroyed = False

    def msg(self, type_name: str) -> type:
        """The rosidl class for ``"pkg/msg/Type"``; :class:`ValueError` for an unknown type."""
        return _message_class(type_name)

    def to_cdr(self, msg: Any) -> bytes:
        """CDR through the RMW's serializer (``rclpy.serialization``), header included."""
        return bytes(serialize_message(msg))

    def from_cdr(self, type_name: str, data: bytes) -> Any:
        return deserialize_message(bytes(data), self.msg(type_name))

    def pack(self, values) -> Any:
        """numpy -> ``array.array`` (rosidl array fields check for it; numpy is refused)."""
        values = np.ascontiguousarray(values)
        return array.array(_TYPECODES[values.dtype.str[1:]], values.tobytes())

    def create_publisher(self, type_name: str, topic: str, qos: QoS = DEFAULT_QOS) -> Publisher:
        return self._node.create_publisher(self.msg(type_name), topic, _qos_profile(qos))

    def create_subscription(self, type_name: str, topic: str, callback: Callable[[Any], None],
                            qos: QoS = DEFAULT_QOS) -> Any:
        return self._node.create_subscription(self.msg(type_name), topic, callback, _qos_profile(qos))

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """A timer on the steady clock: wall time as the port says, even with ``use_sim_time``."""
        if period_s <= 0:
            raise ValueError(f"timer period must be > 0 s, got {period_s}")
        return self._node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))

    def declare_parameters(self, defaults: dict[str, Any]) -> dict[str, Any]:
        """Declare each parameter (already declared ones such as ``use_sim_time`` are read, not
        redeclared); a type mismatch with the default raises :class:`ParameterError`."""
        values: dict[str, Any] = {}
        for name, default in defaults.items():
            if self._node.has_parameter(name):
                values[name] = self._node.get_parameter(name).value
                continue
            try:
                values[name] = self._node.declare_parameter(name, default).value
            except InvalidParameterTypeException as exc:
                raise ParameterError(f"node {self.fully_qualified_name}: parameter {name!r} must be "
                                     f"{type(default).__name__} (default {default!r}): {exc}") from None
        return values

    @property
    def logger(self) -> logging.Logger:
        """A :class:`logging.Logger` whose records go to the node's rclpy logger."""
        return self._logger

    def resolve_topic(self, topic: str) -> str:
        return self._node.resolve_topic_name(topic)

    def destroy(self) -> None:
        """Leave the executor and destroy the rclpy node; safe to call twice."""
        if self._destroyed:
            return
        self._destroyed = True
        executor = self._node.executor
        if executor is not None:
            executor.remove_node(self._node)
        self._node.destroy_node()


class RclpyMiddleware(Middleware):
    """A private rclpy context initialised from ``argv`` plus a single-threaded executor."""

    backend = "rclpy"

    def __init__(self, argv: list[str] | None) -> None:
        """``argv`` is the whole process argv (program name first, ``--ros-args ...`` included);
        ``None`` lets rclpy read ``sys.argv``."""
        if _RCLPY_IMPORT_ERROR is not None:
            raise ImportError("the rclpy middleware backend needs ROS 2 Jazzy's rclpy (source "
                              f"/opt/ros/jazzy/setup.bash): {_RCLPY_IMPORT_ERROR}") from _RCLPY_IMPORT_ERROR
        self._context = Context()
        try:
            rclpy.init(args=argv, context=self._context)
        except RuntimeError as exc:  # rcl's RCLError / UnknownROSArgsError
            raise RosArgsError(f"rclpy.init rejected the ROS arguments: {exc}") from None
        self._executor = SingleThreadedExecutor(context=self._context)
        self._nodes: list[RclpyNode] = []
        self._closed = False

    def create_node(self, name: str, namespace: str = "") -> RclpyNode:
        node = RclpyNode(rclpy.node.Node(name, namespace=namespace, context=self._context))
        self._executor.add_node(node._node)
        self._nodes.append(node)
        return node

    def spin(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> None:
        """Spin the executor in steps of at most 50 ms; returns early if the context is shut down."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        try:
            while self._context.ok() and not (until is not None and until()):
                step = _SPIN_STEP_S if deadline is None else min(_SPIN_STEP_S, deadline - time.monotonic())
                if step <= 0:
                    return
                self._executor.spin_once(timeout_sec=step)
        except ExternalShutdownException:  # the context was shut down elsewhere (SIGINT)
            return

    def shutdown(self) -> None:
        """Destroy the nodes, stop the executor and shut the context down; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        for node in self._nodes:
            node.destroy()
        self._nodes.clear()
        self._executor.shutdown()
        rclpy.try_shutdown(context=self._context)
