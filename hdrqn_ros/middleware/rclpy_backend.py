"""The rclpy backend of the middleware port: real ROS 2 Jazzy nodes.

rclpy comes from a sourced ROS 2 Jazzy (``source /opt/ros/jazzy/setup.bash``, which wins
when sourced) or from the PyPI wheels of Jazzy (``pip install hdrqn_ros[ros]``, RMW
``rmw_fastrtps_cpp``). Before ``rclpy.init`` the RMW gets our loopback-only network
defaults (:func:`hdrqn_ros.middleware.network.apply_rmw_network_defaults`) unless the user
configured an interface or a DDS profile of their own.

This module imports without rclpy so that :func:`rclpy_available` can be asked anywhere;
constructing :class:`RclpyMiddleware` without rclpy raises :class:`ImportError`.
"""
from __future__ import annotations

import array
import importlib
import logging
import sys
import time
import traceback
from functools import lru_cache
from typing import Any, Callable

try:
    import rclpy
    import rclpy.node
    from rclpy.clock import Clock, ClockType
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
    from rclpy.exceptions import InvalidParameterTypeException
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_c
    from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import deserialize_message, serialize_message
    from rclpy.signals import SignalHandlerOptions
except ImportError as exc:  # no sourced ROS 2 (or a broken one): the Cyclone backend is used
    _RCLPY_IMPORT_ERROR: ImportError | None = exc
else:
    _RCLPY_IMPORT_ERROR = None

import numpy as np

from hdrqn_ros.middleware.network import apply_rmw_network_defaults
from hdrqn_ros.middleware.port import (DEFAULT_QOS, Lifecycle, Middleware, Node, ParameterError, ParameterRule,
                                       Publisher, QoS, RosArgsError)
from hdrqn_ros.middleware.ros_args import ProcessSettings, check_overrides, process_settings, split_ros_args
from hdrqn_ros.throttle import Throttle

_SPIN_STEP_S = 0.05
_TYPECODES = {"u1": "B", "i1": "b", "u2": "H", "i2": "h", "u4": "I", "i4": "i", "u8": "Q", "i8": "q", "f4": "f",
              "f8": "d"}


RCLPY_INSTALL_HINT = ("pip install 'hdrqn_ros[ros]' (the PyPI wheels of ROS 2 Jazzy: Linux x86-64, CPython "
                      "3.10-3.13) or source /opt/ros/jazzy/setup.bash")


def rclpy_available() -> bool:
    """Whether ``import rclpy`` worked (the Jazzy wheels, or a sourced ROS 2)."""
    return _RCLPY_IMPORT_ERROR is None


def rclpy_version() -> str:
    """The installed rclpy's version ("7.1.6" for the Jazzy wheels), or "" when unknown."""
    from importlib.metadata import PackageNotFoundError, version

    for dist in ("ros-rclpy", "rclpy"):
        try:
            return version(dist)
        except PackageNotFoundError:
            continue
    return ""


def rclpy_import_error() -> str:
    """Why ``import rclpy`` failed ("" when it worked)."""
    return "" if _RCLPY_IMPORT_ERROR is None else str(_RCLPY_IMPORT_ERROR)


@lru_cache(maxsize=None)
def _interface_class(type_name: str, kind: str = "msg") -> type:
    """The rosidl Python class for ``"pkg/msg/Type"`` (``kind`` "srv": ``"pkg/srv/Type"``)."""
    what = "message" if kind == "msg" else "service"
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != kind or not all(parts):
        raise ValueError(f"{what} type {type_name!r} is not of the form 'pkg/{kind}/Type'")
    pkg, _, name = parts
    try:
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ImportError, AttributeError):
        raise ValueError(f"unknown {what} type {type_name!r}: no class {name} in the Python "
                         f"module {pkg}.{kind} (is the package built and sourced?)") from None


def _qos_profile(qos: QoS) -> QoSProfile:
    """Our :class:`QoS` as an rclpy profile (history is always keep-last)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth,
        reliability=ReliabilityPolicy.RELIABLE if qos.reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if qos.transient_local else DurabilityPolicy.VOLATILE,
    )


def _descriptor(rule: ParameterRule | None, default: Any, managed: bool) -> ParameterDescriptor:
    """The rclpy descriptor of a parameter's rule (none: an undescribed, read-write one). On a
    managed node a not-live parameter is writable (checked by the node's state instead)."""
    if rule is None:
        return ParameterDescriptor()
    descriptor = ParameterDescriptor(description=rule.description, read_only=not (rule.live or managed),
                                     additional_constraints=rule.constraints(managed))
    if rule.low is not None and rule.high is not None and not isinstance(default, bool):
        if isinstance(default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(rule.low), to_value=int(rule.high), step=0)]
        elif isinstance(default, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(rule.low),
                                                                  to_value=float(rule.high), step=0.0)]
    return descriptor


class _RcutilsHandler(logging.Handler):
    """Forwards formatted :mod:`logging` records to an rclpy (rcutils) logger."""

    def __init__(self, ros_logger: Any) -> None:
        super().__init__(logging.DEBUG)
        self._ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        """One call site per severity: rclpy refuses a severity change at one call site."""
        try:
            text, level, ros = self.format(record), record.levelno, self._ros_logger  # format: args, tracebacks
            if level >= logging.CRITICAL:
                ros.fatal(text)
            elif level >= logging.ERROR:
                ros.error(text)
            elif level >= logging.WARNING:
                ros.warning(text)
            elif level >= logging.INFO:
                ros.info(text)
            else:
                ros.debug(text)
        except Exception:
            self.handleError(record)


class RclpyNode(Node):
    """A :class:`Node` backed by an ``rclpy.node.Node`` (or, managed, a ``LifecycleNode``).

    It keeps what it creates, so that a managed node's cleanup can :meth:`release` it. A
    managed node's not-live parameters may change while it is unconfigured: they are read at
    the next configure; in any other state they are refused."""

    backend_name = "rclpy"

    def __init__(self, node: rclpy.node.Node, max_message_bytes: int, managed: bool = False) -> None:
        self._node = node
        self.managed = managed
        self._owned: list[tuple[Callable[[Any], Any], Any]] = []  # (destroy, entity), in creation order
        self._rules: dict[str, ParameterRule | None] = {}  # every parameter this node declared, and its rule
        self._max_message_bytes = max_message_bytes
        self.name = node.get_name()  # after any __node / __ns remapping
        self.namespace = node.get_namespace()
        # A Logger outside logging's registry: nodes of equal names do not share handlers, and
        # records reach rcutils (console, /rosout) once, not also through the root logger.
        self._logger = logging.Logger(f"hdrqn.{node.get_logger().name}", logging.DEBUG)
        self._logger.propagate = False
        self._logger.addHandler(_RcutilsHandler(node.get_logger()))
        self._destroyed = False
        if managed:
            node.add_on_set_parameters_callback(self._check_managed_change)

    def _own(self, destroy: Callable[[Any], Any], entity: Any) -> Any:
        self._owned.append((destroy, entity))
        return entity

    def release(self) -> None:
        for destroy, entity in reversed(self._owned):
            destroy(entity)
        self._owned.clear()

    def _check_managed_change(self, parameters: list[Parameter]) -> SetParametersResult:
        """A managed node's not-live parameters: refused while configured, else checked by their rules."""
        for parameter in parameters:
            rule = self._rules.get(parameter.name)
            if rule is None or rule.live:
                continue
            if not self._node.unconfigured:
                return SetParametersResult(successful=False, reason=(
                    f"parameter {parameter.name} is read when the node configures: it changes only while the node is "
                    f"unconfigured (deactivate and cleanup first)"))
            if why := rule.refusal(parameter.name, parameter.value):
                return SetParametersResult(successful=False, reason=why)
        return SetParametersResult(successful=True)

    def msg(self, type_name: str) -> type:
        """The rosidl class for ``"pkg/msg/Type"``; :class:`ValueError` for an unknown type."""
        return _interface_class(type_name)

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
        return self._own(self._node.destroy_publisher,
                         self._node.create_publisher(self.msg(type_name), topic, _qos_profile(qos)))

    def wait_for_delivery(self, publisher: Publisher, timeout_s: float) -> bool:
        return publisher.wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9)))

    def create_subscription(self, type_name: str, topic: str, callback: Callable[[Any], None],
                            qos: QoS = DEFAULT_QOS, raw: bool = False) -> Any:
        """Takes the serialized sample, so that an oversized one (over ``max_message_bytes``) is
        dropped before decoding and one that does not decode is dropped too, each with a
        throttled warning, as on the Cyclone backend."""
        cls, limit = self.msg(type_name), self._max_message_bytes
        name = self.resolve_topic(topic)
        dropped = Throttle(self._logger, f"dropped a sample on {name}")

        def on_sample(data: bytes) -> None:
            if len(data) > limit:
                dropped.warn(f"{len(data)} B exceeds the {limit} B message limit")
                return
            if raw:
                callback(data)
                return
            try:
                msg = deserialize_message(data, cls)
            except Exception as exc:  # rmw's deserializer: bytes that are not this type
                dropped.warn(f"does not decode as {type_name}: {exc}")
                return
            callback(msg)

        return self._own(self._node.destroy_subscription,
                         self._node.create_subscription(cls, topic, on_sample, _qos_profile(qos), raw=True))

    def create_service(self, type_name: str, name: str, callback: Callable[[Any, Any], Any]) -> Any:
        return self._own(self._node.destroy_service,
                         self._node.create_service(_interface_class(type_name, "srv"), name, callback))

    def create_timer(self, period_s: float, callback: Callable[[], None]) -> Any:
        """A timer on the steady clock: wall time as the port says, even with ``use_sim_time``."""
        if period_s <= 0:
            raise ValueError(f"timer period must be > 0 s, got {period_s}")
        return self._own(self._node.destroy_timer,
                         self._node.create_timer(period_s, callback, clock=Clock(clock_type=ClockType.STEADY_TIME)))

    def declare_parameters(self, defaults: dict[str, Any], overrides: dict[str, Any] | None = None,
                           rules: dict[str, ParameterRule] | None = None) -> dict[str, Any]:
        """Declare each parameter with the descriptor of its rule (description, read-only
        unless live, range; already declared ones such as ``use_sim_time`` are read, not
        redeclared), with the values of ``overrides``; a type mismatch with the default or a
        value out of range raises :class:`ParameterError`."""
        given = check_overrides(self.fully_qualified_name, defaults, overrides)
        values: dict[str, Any] = {}
        for name, default in defaults.items():
            if name in self._rules:  # declared at an earlier configure of this managed node: its value now
                pass
            elif not self._node.has_parameter(name):
                rule = (rules or {}).get(name)
                try:  # writable and unbounded while its start value is set, then its rule's descriptor
                    self._node.declare_parameter(name, default)
                except InvalidParameterTypeException as exc:
                    raise ParameterError(f"node {self.fully_qualified_name}: parameter {name!r} must be "
                                         f"{type(default).__name__} (default {default!r}): {exc}") from None
                self._set_typed(name, given)
                value = self._node.get_parameter(name).value
                if rule is not None and (why := rule.refusal(name, value)) and \
                        (rule.low is not None or rule.high is not None):
                    raise ParameterError(f"node {self.fully_qualified_name}: {why}")
                descriptor = _descriptor(rule, default, self.managed)
                descriptor.type = self._node.get_parameter(name).type_.value
                self._node.set_descriptor(name, descriptor)
                self._rules[name] = rule
            else:  # rclpy's own (use_sim_time)
                self._set_typed(name, given)
            values[name] = self._node.get_parameter(name).value
        return values

    def _set_typed(self, name: str, given: dict[str, Any]) -> None:
        """Set ``given[name]`` (if given) typed as declared (an empty list would otherwise be a byte array)."""
        if name not in given:
            return
        declared = self._node.get_parameter(name).type_
        result = self._node.set_parameters([Parameter(name, declared, given[name])])[0]
        if not result.successful:
            raise ParameterError(f"node {self.fully_qualified_name}: parameter {name!r} cannot be set to "
                                 f"{given[name]!r}: {result.reason}")

    def on_parameters_set(self, rules: dict[str, ParameterRule], apply: Callable[[str, Any], None]) -> None:
        def check_then_apply(parameters: list[Parameter]) -> SetParametersResult:
            for parameter in parameters:
                rule = rules.get(parameter.name)
                if rule is not None and (why := rule.refusal(parameter.name, parameter.value)):
                    return SetParametersResult(successful=False, reason=why)
            for parameter in parameters:
                if parameter.name in rules:
                    apply(parameter.name, parameter.value)
                    self._logger.info("parameter %s set to %r", parameter.name, parameter.value)
            return SetParametersResult(successful=True)

        self._node.add_on_set_parameters_callback(check_then_apply)
        self._own(self._node.remove_on_set_parameters_callback, check_then_apply)

    @property
    def logger(self) -> logging.Logger:
        """A :class:`logging.Logger` whose records go to the node's rclpy logger."""
        return self._logger

    def resolve_topic(self, topic: str) -> str:
        return self._node.resolve_topic_name(topic)

    def destroy(self, leave_executor: bool = True) -> None:
        """Leave the executor (unless it is already shut down) and destroy the rclpy node;
        safe to call twice."""
        if self._destroyed:
            return
        self._destroyed = True
        executor = self._node.executor
        if leave_executor and executor is not None:
            executor.remove_node(self._node)
        self._node.destroy_node()


def _managed_ros_node(name: str, context: Context, lifecycle: Lifecycle) -> "rclpy.node.Node":
    """An rclpy ``LifecycleNode`` whose transitions call ``lifecycle``. A failed configure
    (the reason logged) leaves it unconfigured; an exception in a transition is logged and
    the node cleaned up (rclpy's error processing, back to unconfigured). A transition that
    is not allowed from the current state is refused (``success: false``, logged), where
    rclpy would raise out of the executor for a transition given by id."""

    class ManagedRosNode(LifecycleNode):
        unconfigured = True  # in the unconfigured state (where its not-live parameters may change)

        def _run(self, what: str, call: Callable[[], Any], unconfigured_after: bool) -> TransitionCallbackReturn:
            try:
                why = call()
            except Exception:
                self.get_logger().error(f"{what} failed:\n{traceback.format_exc()}")
                return TransitionCallbackReturn.ERROR
            if why:
                self.get_logger().error(f"{what} failed, the node stays unconfigured: {why}")
                return TransitionCallbackReturn.FAILURE
            self.unconfigured = unconfigured_after
            self.get_logger().info(f"{what}: done")
            return TransitionCallbackReturn.SUCCESS

        def on_configure(self, state):
            return self._run("configure", lifecycle.on_configure, False)

        def on_activate(self, state):
            return self._run("activate", lifecycle.on_activate, False)

        def on_deactivate(self, state):
            return self._run("deactivate", lifecycle.on_deactivate, False)

        def on_cleanup(self, state):
            return self._run("cleanup", lifecycle.on_cleanup, True)

        def on_shutdown(self, state):
            return self._run("shutdown", lifecycle.on_shutdown, False)

        def on_error(self, state):
            return self._run("error processing (cleanup)", lifecycle.on_cleanup, True)

    node = ManagedRosNode(name, context=context)
    service = node._service_change_state
    change_state = service.callback

    def refuse_what_is_not_allowed(request, response):
        try:
            return change_state(request, response)
        except _rclpy_c.RCLError as exc:
            label = node._state_machine.current_state[1]
            node.get_logger().warning(f"transition {request.transition.label or request.transition.id} refused "
                                      f"in state {label}: {exc}")
            response.success = False
            return response

    service.callback = refuse_what_is_not_allowed
    return node


def _executor(context: Context) -> Any:
    """rclpy's C++ ``EventsExecutor`` (about 10 us per callback here, against about 90 us for
    ``SingleThreadedExecutor``, which rebuilds its Python wait set on every spin). The events
    executor enables :mod:`faulthandler` on ``sys.stderr``; where stderr has no file descriptor
    (a node inside a process whose stderr is captured in memory) or rclpy has no events
    executor, the single-threaded one is used. Both run one callback at a time; both let a
    callback's exception leave :meth:`RclpyMiddleware.spin`."""
    try:
        from rclpy.experimental import EventsExecutor
        sys.stderr.fileno()
    except (ImportError, AttributeError, ValueError, OSError):
        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


class RclpyMiddleware(Middleware):
    """A private rclpy context initialised from ``argv`` plus one executor for its nodes."""

    backend = "rclpy"

    def __init__(self, argv: list[str] | None) -> None:
        """``argv`` is the whole process argv (program name first, ``--ros-args ...`` included);
        ``None`` lets rclpy read ``sys.argv``. rclpy installs no signal handlers: the
        process's owner (:func:`hdrqn_ros.nodes.common.run_node`) stops the spin, so nodes
        can still publish on the way out (a zero ``cmd_vel``)."""
        if _RCLPY_IMPORT_ERROR is not None:
            raise ImportError(f"the rclpy middleware backend needs ROS 2 Jazzy's rclpy: {RCLPY_INSTALL_HINT} "
                              f"({_RCLPY_IMPORT_ERROR})") from _RCLPY_IMPORT_ERROR
        self.settings: ProcessSettings = process_settings(split_ros_args(list(argv or sys.argv))[1])
        self.network = apply_rmw_network_defaults(self.settings.interface)
        self._context = Context()
        try:
            rclpy.init(args=argv, context=self._context, domain_id=self.settings.domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
        except RuntimeError as exc:  # rcl's RCLError / UnknownROSArgsError
            raise RosArgsError(f"rclpy.init rejected the ROS arguments: {exc}") from None
        self._executor = _executor(self._context)
        self._nodes: list[RclpyNode] = []
        self._closed = False

    def create_node(self, name: str, namespace: str = "") -> RclpyNode:
        return self._add(RclpyNode(rclpy.node.Node(name, namespace=namespace, context=self._context),
                                   self.settings.max_message_bytes))

    def create_managed_node(self, name: str, lifecycle: Lifecycle) -> RclpyNode:
        return self._add(RclpyNode(_managed_ros_node(name, self._context, lifecycle), self.settings.max_message_bytes,
                                   managed=True))

    def _add(self, node: RclpyNode) -> RclpyNode:
        self._executor.add_node(node._node)
        self._nodes.append(node)
        if len(self._nodes) == 1:
            node.logger.info("middleware rclpy %s: %s, domain %d", rclpy_version(), self.network,
                             self.settings.domain_id)
        return node

    def spin(self, until: Callable[[], bool] | None = None, timeout_s: float | None = None) -> None:
        """Spin the executor in steps of at most 50 ms; returns early if the context is shut down."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        try:
            while not self._closed and self._context.ok() and not (until is not None and until()):
                step = _SPIN_STEP_S if deadline is None else min(_SPIN_STEP_S, deadline - time.monotonic())
                if step <= 0:
                    return
                self._executor.spin_once(timeout_sec=step)
        except ExternalShutdownException:  # the context was shut down elsewhere (SIGINT)
            return

    def shutdown(self) -> None:
        """Stop the executor, destroy the nodes and shut the context down, in rclpy's own order
        (no callback runs while the nodes go), then free the executor and the context, whose
        native threads (the events executor's, the DDS participant's) stop here, while Python
        runs, not in the interpreter's exit; safe to call twice."""
        if self._closed:
            return
        self._closed = True
        self._executor.shutdown()
        for node in self._nodes:
            node.destroy(leave_executor=False)
        self._nodes.clear()
        rclpy.try_shutdown(context=self._context)
        self._executor = None
        self._context.destroy()
