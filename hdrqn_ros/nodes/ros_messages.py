"""rclpy's message classes for the wire layouts, and subscriptions that bound what they take.

:mod:`hdrqn_ros.protocol.wire` builds messages through a message factory (``msg(type_name)``
for a class, ``pack(array)`` for an array field) so that it imports no ROS; here that factory
is rclpy's (:data:`ROS_MESSAGES`); bags use the ``rosbags`` type store's. A message package
that is not installed is a :class:`MissingRosPackage` naming how to get it (a node exits 2).
"""
from __future__ import annotations

import array
import importlib
import importlib.util
import logging
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message, serialize_message

from hdrqn_ros.nodes.ros_packages import install_hint
from hdrqn_ros.throttle import Throttle

DEFAULT_MAX_MESSAGE_BYTES = 64 * 2**20
"""Received samples larger than this are dropped with a warning (weights are ~2.5 MB)."""
_TYPECODES = {"u1": "B", "i1": "b", "u2": "H", "i2": "h", "u4": "I", "i4": "i", "u8": "Q", "i8": "q", "f4": "f",
              "f8": "d"}


class MissingRosPackage(ImportError):
    """A ROS interface package the node needs is not installed."""


@lru_cache(maxsize=None)
def interface_class(type_name: str) -> type:
    """The rosidl class for ``"pkg/msg/Type"`` or ``"pkg/srv/Type"``; :class:`MissingRosPackage`
    when ``pkg`` is not installed, :class:`ValueError` for a malformed or unknown name."""
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] not in ("msg", "srv", "action") or not all(parts):
        raise ValueError(f"interface type {type_name!r} is not of the form 'pkg/msg/Type'")
    package, kind, name = parts
    spec = importlib.util.find_spec(package) if package.isidentifier() else None
    if spec is None:
        raise MissingRosPackage(f"ROS package {package} is not installed ({type_name}): {install_hint(package)}")
    if not any((Path(where) / kind / "__init__.py").exists() for where in spec.submodule_search_locations or ()):
        raise ValueError(f"unknown interface type {type_name!r}: {package} is not a ROS interface package")
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ModuleNotFoundError as exc:
        if exc.name not in (package, f"{package}.{kind}"):
            raise
        raise MissingRosPackage(f"ROS package {package} is not installed ({type_name}): {install_hint(package)}") \
            from None
    try:
        return getattr(module, name)
    except AttributeError:
        raise ValueError(f"unknown interface type {type_name!r}: no class {name} in {package}.{kind}") from None


def pack(values) -> array.array:
    """A numeric numpy array as the value of an rclpy message's array field (rosidl accepts
    ``array.array``, not numpy)."""
    values = np.ascontiguousarray(values)
    return array.array(_TYPECODES[values.dtype.str[1:]], values.tobytes())


class RosMessages:
    """The message factory :mod:`hdrqn_ros.protocol.wire`'s builders take, for rclpy."""

    msg = staticmethod(interface_class)
    pack = staticmethod(pack)


ROS_MESSAGES = RosMessages()


def to_cdr(msg: Any) -> bytes:
    """``msg`` serialized as the RMW does (CDR, encapsulation header first): what a bag stores."""
    return bytes(serialize_message(msg))


def from_cdr(type_name: str, data: bytes) -> Any:
    """The message of ``type_name`` that CDR bytes ``data`` hold."""
    return deserialize_message(bytes(data), interface_class(type_name))


def bounded_subscription(node: Node, msg_type: type, topic: str, callback: Callable[[Any], None],
                         qos: QoSProfile, max_bytes: int, logger: logging.Logger, raw: bool = False):
    """``node.create_subscription`` that takes each sample serialized, so that one over
    ``max_bytes`` is dropped before it is decoded, and one that does not decode is dropped
    too, each with a throttled warning on ``logger``; ``raw``: ``callback`` gets the CDR
    bytes (what a bag stores)."""
    name = node.resolve_topic_name(topic)
    dropped = Throttle(logger, f"dropped a sample on {name}")

    def on_sample(data: bytes) -> None:
        if len(data) > max_bytes:
            dropped.warn(f"{len(data)} B exceeds the {max_bytes} B message limit (max_message_bytes)")
            return
        if raw:
            callback(data)
            return
        try:
            msg = deserialize_message(data, msg_type)
        except Exception as exc:  # the RMW's deserializer: bytes that are not this type
            dropped.warn(f"does not decode as {msg_type.__module__.split('.')[0]}/{msg_type.__name__}: {exc}")
            return
        callback(msg)

    return node.create_subscription(msg_type, topic, on_sample, qos, raw=True)
