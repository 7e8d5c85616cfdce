"""A node's parameters (:mod:`hdrqn_ros.nodes.parameters`) on real rclpy nodes, in this process.

Each test's nodes live in a private rclpy ``Context`` on a DDS domain of their own. Declared
once from a table of ``Param``: a descriptor (description, range, ``read_only`` unless live);
a start value (``--ros-args -p``) of the wrong type or against a rule is a
``NodeConfigError`` naming the node, the parameter and the rule; a later ``set_parameters``
(what ``ros2 param set`` calls) against a rule is refused and the value kept; an accepted
live value reaches the node. A managed node's not-live parameters change only while it is
unconfigured.
"""
from __future__ import annotations

import math
import os
from unittest import mock

import pytest

pytest.importorskip("rclpy", reason="rclpy (ROS 2 Jazzy) cannot be imported here")

import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.lifecycle import TransitionCallbackReturn  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402

from hdrqn_ros.dds import INTERFACE_ENV, apply_rmw_network_defaults  # noqa: E402
from hdrqn_ros.nodes.lifecycle import ManagedNode  # noqa: E402
from hdrqn_ros.nodes.parameters import NodeConfigError, Param, declare_parameters  # noqa: E402

PRIVATE_DOMAIN = 229
"""A DDS domain no process test takes (they use 20..219)."""

TABLE = {
    "count": Param(3, "how many", low=1, high=10),
    "rate": Param(1.0, "updates per second", live=True, low=0.0, high=100.0),
    "gain": Param(2.0, "a gain", live=True, positive=True),
    "offset": Param(0.5, "any finite number", live=True),
    "mode": Param("a", "which mode", live=True, choices=("a", "b")),
    "label": Param("x", "a label", check=lambda v: None if v.isidentifier() else f"must be an identifier, got {v!r}"),
    "flag": Param(False, "a switch"),
    "names": Param(["/"], "namespaces"),
}


@pytest.fixture
def start():
    """``start(*ros_args)``: a private rclpy context initialised with those ROS arguments (the
    package's network defaults applied); every one is shut down after the test."""
    contexts: list[Context] = []
    with mock.patch.dict(os.environ):
        apply_rmw_network_defaults(os.environ.get(INTERFACE_ENV) or None)

        def start(*ros_args: str) -> Context:
            context = Context()
            rclpy.init(args=["test_parameters", "--ros-args", *ros_args], context=context, domain_id=PRIVATE_DOMAIN,
                       signal_handler_options=SignalHandlerOptions.NO)
            contexts.append(context)
            return context

        yield start
        for context in contexts:
            rclpy.try_shutdown(context=context)
            context.destroy()


def plain_node(context: Context, applied: list | None = None) -> tuple[Node, dict]:
    node = Node("params", namespace="/ns", context=context)
    values = declare_parameters(node, TABLE, apply=None if applied is None else lambda *nv: applied.append(nv))
    return node, values


def test_each_parameter_is_declared_once_with_its_descriptor(start):
    node, values = plain_node(start("-p", "count:=5", "-p", "flag:=true", "-p", "names:=[/a, /b]"))
    assert values == {"count": 5, "rate": 1.0, "gain": 2.0, "offset": 0.5, "mode": "a", "label": "x", "flag": True,
                      "names": ["/a", "/b"]}
    count, rate, gain, mode = node.describe_parameters(["count", "rate", "gain", "mode"])
    assert (count.description, count.read_only, count.type) == ("how many", True, Parameter.Type.INTEGER.value)
    assert [(r.from_value, r.to_value) for r in count.integer_range] == [(1, 10)]
    assert "read-only" in count.additional_constraints
    assert not rate.read_only and [(r.from_value, r.to_value) for r in rate.floating_point_range] == [(0.0, 100.0)]
    assert not gain.read_only and gain.additional_constraints == "> 0" and not gain.floating_point_range
    assert mode.additional_constraints == "one of a, b"
    with pytest.raises(rclpy.exceptions.ParameterAlreadyDeclaredException):
        declare_parameters(node, {"count": TABLE["count"]})
    node.destroy_node()


@pytest.mark.parametrize("override, rule", [
    ("count:=0", "out of range. Min: 1, Max: 10"),
    ("count:=abc", "must be int"),
    ("rate:=.nan", "out of range"),
    ("offset:=.inf", "must be a finite number"),
    ("gain:=0.0", "must be > 0"),
    ("gain:=1", "must be float"),
    ("mode:=c", "must be one of ['a', 'b']"),
    ("label:=two words", "must be an identifier"),
    ("names:=[1, 2]", "must be list"),
])
def test_a_bad_start_value_is_a_node_config_error_naming_the_parameter_and_rule(start, override, rule):
    context = start("-p", override)
    node = Node("params", namespace="/ns", context=context)
    name = override.partition(":=")[0]
    with pytest.raises(NodeConfigError) as info:
        declare_parameters(node, TABLE)
    assert "/ns/params" in str(info.value) and name in str(info.value) and rule in str(info.value), info.value
    node.destroy_node()


@pytest.mark.parametrize("name, value, reason", [
    ("rate", 200.0, "out of range"),
    ("rate", math.nan, "out of range"),
    ("offset", math.nan, "must be a finite number"),
    ("offset", -math.inf, "must be a finite number"),
    ("gain", -1.0, "must be > 0"),
    ("gain", math.inf, "must be a finite number"),
    ("mode", "c", "must be one of ['a', 'b']"),
    ("rate", 2, "Wrong parameter type"),
    ("count", 5, "read-only"),
    ("names", ["/a"], "read-only"),
])
def test_a_refused_set_parameters_keeps_the_value(start, name, value, reason):
    """What ``ros2 param set`` gets: ``successful: false`` and why; the node keeps its value
    and is told nothing."""
    applied = []
    node, values = plain_node(start(), applied)
    result, = node.set_parameters([Parameter(name, value=value)])
    assert not result.successful and reason in result.reason, result.reason
    assert node.get_parameter(name).value == values[name] and applied == []
    node.destroy_node()


def test_a_live_parameter_is_applied(start):
    applied = []
    node, _ = plain_node(start(), applied)
    results = node.set_parameters([Parameter("gain", value=0.5), Parameter("mode", value="b"),
                                   Parameter("offset", value=-3.0)])
    assert all(r.successful for r in results), results
    assert applied == [("gain", 0.5), ("mode", "b"), ("offset", -3.0)]
    assert node.get_parameter("gain").value == 0.5
    node.destroy_node()


class Managed(ManagedNode):
    """A managed node that notes what each configure read and each live change."""

    def __init__(self, **kwargs):
        self.built: list[dict] = []
        self.live: list[tuple] = []
        super().__init__("managed", {"size": Param(3, "size", low=1, high=9), "rate": Param(1.0, "rate", live=True)},
                         **kwargs)

    def build(self) -> None:
        self.built.append(dict(self.params))

    def on_live_parameter(self, name, value) -> None:
        self.live.append((name, value))


def test_a_managed_nodes_not_live_parameters_change_only_while_unconfigured(start):
    node = Managed(context=start("-p", "size:=4"))
    size, = node.describe_parameters(["size"])
    assert not size.read_only and "only while the node is unconfigured" in size.additional_constraints

    def set_(name, value):
        return node.set_parameters([Parameter(name, value=value)])[0]

    assert set_("size", 5).successful, "unconfigured: it may change"
    assert not set_("size", 10).successful, "the range holds while unconfigured too"
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.built == [{"size": 5, "rate": 1.0}]
    refused = set_("size", 6)
    assert not refused.successful and "unconfigured" in refused.reason, refused.reason
    assert node.get_parameter("size").value == 5
    assert set_("rate", 2.5).successful and node.live == [("rate", 2.5)] and node.params["rate"] == 2.5
    assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
    assert not set_("size", 6).successful
    assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert node.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert set_("size", 6).successful
    assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
    assert node.built[-1] == {"size": 6, "rate": 2.5}
    node.close()
    node.destroy_node()
