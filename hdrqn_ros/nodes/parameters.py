"""A node's ROS parameters, each declared once: default, description, range, live or not.

A node lists its parameters as ``{name: Param(...)}`` and calls :func:`declare_parameters`
once. Each becomes an rclpy parameter with a ``ParameterDescriptor`` (what ``ros2 param
describe`` shows: description, type, range, ``read_only`` unless ``live``), and one on-set
callback per node checks every value against its declaration: the values the node starts
with (``--ros-args -p``, ``--params-file``, ``parameter_overrides``) and every later
``ros2 param set``. rclpy itself enforces the type, the range and ``read_only``; the
callback adds what a descriptor cannot say (a set of choices, > 0, NaN or infinity) and
hands accepted live values to the node. No rule is checked a second time in node code.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter


class NodeConfigError(ValueError):
    """A parameter value the node cannot work with (the node exits 2, or a managed node's
    configure fails, with this message)."""


@dataclass(frozen=True)
class Param:
    """One parameter: its ``default`` (which fixes its type), a one-line ``description``,
    whether it is ``live`` (may change while the node runs; the node applies it at its next
    use), an inclusive ``low``..``high`` range for a number, ``positive`` (> 0),
    ``choices`` for a string, and ``check``: a rule of its own (value -> why not, or None)."""

    default: Any
    description: str
    live: bool = False
    low: float | None = None
    high: float | None = None
    positive: bool = False
    choices: tuple[str, ...] = ()
    check: Callable[[Any], str | None] | None = None

    def refusal(self, name: str, value: Any) -> str | None:
        """Why ``value`` is not allowed for parameter ``name`` (``None``: it is)."""
        if self.choices and value not in self.choices:
            return f"parameter {name} must be one of {list(self.choices)}, got {value!r}"
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            if isinstance(value, float) and not math.isfinite(value):
                return f"parameter {name} must be a finite number, got {value!r}"
            if self.positive and not value > 0:
                return f"parameter {name} must be > 0, got {value!r}"
            if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
                return f"parameter {name} must be in {self.low:g}..{self.high:g}, got {value!r}"
        if self.check is not None and (why := self.check(value)):
            return f"parameter {name}: {why}"
        return None

    def descriptor(self, managed: bool) -> ParameterDescriptor:
        """The rclpy descriptor: description, constraints in words, range; ``read_only``
        unless live (on a managed node every parameter is writable, and a not-live one is
        refused by :func:`declare_parameters`' callback outside the unconfigured state)."""
        words = [] if self.live else \
            ["changes only while the node is unconfigured" if managed else "read-only while the node runs"]
        if self.positive:
            words.append("> 0")
        if self.choices:
            words.append("one of " + ", ".join(self.choices))
        descriptor = ParameterDescriptor(description=self.description, read_only=not (self.live or managed),
                                         additional_constraints="; ".join(words))
        bounded = self.low is not None and self.high is not None and not isinstance(self.default, bool)
        if bounded and isinstance(self.default, int):
            descriptor.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=0)]
        elif bounded and isinstance(self.default, float):
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(self.low),
                                                                  to_value=float(self.high), step=0.0)]
        return descriptor


def declare_parameters(node: Node, table: dict[str, Param], apply: Callable[[str, Any], None] | None = None,
                       configurable: Callable[[], bool] | None = None) -> dict[str, Any]:
    """Declare ``table``'s parameters on ``node`` and return their values.

    One on-set callback checks each value with :meth:`Param.refusal`; an accepted change of
    a live parameter goes to ``apply(name, value)`` (after it is set). ``configurable``: a
    managed node's "am I unconfigured?": its not-live parameters change only then.
    A start value of the wrong type or refused raises :class:`NodeConfigError` naming the
    node, the parameter and the rule."""
    managed = configurable is not None
    declaring = True

    def check(parameters: list[Parameter]) -> SetParametersResult:
        for parameter in parameters:
            param = table.get(parameter.name)
            if param is None:
                continue
            if managed and not declaring and not param.live and not configurable():
                return SetParametersResult(successful=False, reason=(
                    f"parameter {parameter.name} is read-only once the node is configured: it changes only while "
                    f"the node is unconfigured (deactivate and cleanup first)"))
            if why := param.refusal(parameter.name, parameter.value):
                return SetParametersResult(successful=False, reason=why)
        return SetParametersResult(successful=True)

    def applied(parameters: list[Parameter]) -> None:
        for parameter in parameters:
            param = table.get(parameter.name)
            if param is not None and param.live and not declaring:
                node.get_logger().info(f"parameter {parameter.name} set to {parameter.value!r}")
                if apply is not None:
                    apply(parameter.name, parameter.value)

    node.add_on_set_parameters_callback(check)
    node.add_post_set_parameters_callback(applied)
    values = {}
    for name, param in table.items():
        values[name] = _declare(node, name, param, managed)
    declaring = False
    return values


def _declare(node: Node, name: str, param: Param, managed: bool) -> Any:
    """Declare one parameter, typed as its default."""
    where = f"node {node.get_fully_qualified_name()}: parameter {name!r}"
    default = param.default
    descriptor = param.descriptor(managed)
    descriptor.type = Parameter.Type.from_parameter_value(default).value
    try:
        value = node.declare_parameter(name, default, descriptor).value
    except InvalidParameterTypeException as exc:
        raise NodeConfigError(f"{where} must be {type(default).__name__} (default {default!r}): "
                              f"{_reason(exc, name)}") from None
    except InvalidParameterValueException as exc:
        raise NodeConfigError(f"{where}: {_reason(exc, name)}") from None
    return value


def _reason(exc: Exception, name: str) -> str:
    """The refusal in rclpy's exception text, without rclpy's preamble and trailing name."""
    text = str(exc).split("Reason: ", 1)[-1]
    return text.removesuffix(f": {name}").strip()


def value_of(node: Node, name: str) -> Any:
    """A declared parameter's current value."""
    return node.get_parameter(name).value
