"""A node's view of the tf tree (``/tf`` and ``/tf_static``, ``tf2_msgs/msg/TFMessage``).

``TfListener(node)`` listens on the node's behalf. Where ``tf2_ros`` imports (a sourced ROS 2)
it is ``tf2_ros.Buffer`` with ``tf2_ros.TransformListener``; on a pip-only machine it
subscribes itself, with tf2_ros's QoS (``/tf``: reliable, volatile, keep-last 100;
``/tf_static``: reliable, transient-local, keep-last 100, so a late joiner gets the static
transforms), and fills a :class:`~hdrqn_ros.robot.transforms.TransformBuffer`. Either way
``lookup(target, source, stamp)`` is a :class:`~hdrqn_ros.robot.transforms.Transform` mapping
points in ``source`` into ``target`` (``pose_in``: ``source``'s origin in ``target`` as
``(x, y, yaw)``, m and rad), or a :class:`~hdrqn_ros.robot.transforms.TransformError`
(``FrameMissing``, ``NotConnected``, ``ExtrapolationError``) whose message names the frames
and times. ``stamp``: an ``rclpy.time.Time``, a ``builtin_interfaces/msg/Time`` (a header's
stamp) or ``None``, the latest time the whole chain has (tf2's time 0). A lookup never waits:
a caller polls it from its own timer. A transform that cannot be used (a non-unit quaternion,
a second parent, a cycle) is dropped with a throttled warning and counted in ``rejections``.
When the node's clock jumps back by :data:`JUMP_BACK_S` or more, or switches between system
and ROS time (a simulation or a bag restarted), the buffer is cleared with a warning, as
tf2_ros does: its old history would refuse every new sample as too old.
"""
from __future__ import annotations

import importlib.util

from rclpy.clock import ClockChange, JumpThreshold
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.time import Time

from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.qos import keep_last
from hdrqn_ros.nodes.ros_messages import DEFAULT_MAX_MESSAGE_BYTES, bounded_subscription, interface_class
from hdrqn_ros.robot.transforms import (ExtrapolationError, FrameMissing, NotConnected, Transform, TransformBuffer,
                                        TransformError)
from hdrqn_ros.throttle import Throttle

TF_TOPIC, TF_STATIC_TOPIC = "/tf", "/tf_static"
TF_QOS = keep_last(100)
"""``/tf`` as tf2_ros's listener reads it: reliable, volatile, keep-last 100."""
TF_STATIC_QOS = keep_last(100, transient_local=True)
"""``/tf_static`` as tf2_ros's listener reads it: reliable, transient-local, keep-last 100."""
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
JUMP_BACK_S = 1.0
"""A jump back in time of the node's clock by this much or more clears the package's buffer."""


def tf2_ros_available() -> bool:
    """Whether ``tf2_ros`` (a sourced ROS 2's) can be imported here."""
    return importlib.util.find_spec("tf2_ros") is not None


def stamp_ns(stamp) -> int | None:
    """``stamp`` (``rclpy.time.Time``, ``builtin_interfaces/msg/Time`` or ``None``) in ns."""
    if stamp is None:
        return None
    if isinstance(stamp, Time):
        return stamp.nanoseconds
    if hasattr(stamp, "sec") and hasattr(stamp, "nanosec"):
        return int(stamp.sec) * 10**9 + int(stamp.nanosec)
    raise TypeError(f"a tf lookup's stamp must be an rclpy.time.Time, a builtin_interfaces/msg/Time or None, "
                    f"got {stamp!r}")


def from_msg(transform) -> Transform:
    """A ``geometry_msgs/msg/Transform`` as a :class:`Transform`."""
    t, r = transform.translation, transform.rotation
    return Transform((t.x, t.y, t.z), (r.x, r.y, r.z, r.w))


class TfListener:
    """The tf tree as ``node`` hears it. ``buffer``: a :class:`TransformBuffer` to fill (then
    ``tf2_ros`` is not used); ``None``: ``tf2_ros.Buffer`` where it imports and
    ``prefer_tf2_ros``, else a new ``TransformBuffer(cache_s)``. ``backend`` names which one."""

    def __init__(self, node: Node, buffer: TransformBuffer | None = None, cache_s: float = 10.0,
                 prefer_tf2_ros: bool = True, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES):
        self.node = node
        logger = python_logger(node)
        self.rejected = Throttle(logger, f"rejected a transform on {TF_TOPIC} or {TF_STATIC_TOPIC}")
        self._tf2 = None
        if buffer is None and prefer_tf2_ros and tf2_ros_available():
            import tf2_ros

            self.buffer = None
            self._tf2 = tf2_ros.Buffer(cache_time=Duration(nanoseconds=int(cache_s * 1e9)), node=node)
            self._tf2_listener = tf2_ros.TransformListener(self._tf2, node)
            self.backend = "tf2_ros.Buffer"
        else:
            message = interface_class(TF_MESSAGE)  # MissingRosPackage naming how to get tf2_msgs
            self.buffer = TransformBuffer(cache_s) if buffer is None else buffer
            self._subscriptions = [
                bounded_subscription(node, message, TF_TOPIC, lambda msg: self._take(msg, False), TF_QOS,
                                     max_message_bytes, logger),
                bounded_subscription(node, message, TF_STATIC_TOPIC, lambda msg: self._take(msg, True), TF_STATIC_QOS,
                                     max_message_bytes, logger)]
            self.backend = "hdrqn_ros TransformBuffer" + ("" if tf2_ros_available() else " (tf2_ros is not installed)")
            self._jump = node.get_clock().create_jump_callback(
                JumpThreshold(min_forward=None, min_backward=Duration(seconds=-JUMP_BACK_S), on_clock_change=True),
                post_callback=self._on_jump)
        node.get_logger().info(f"tf: {self.backend}, listening on {TF_TOPIC} and {TF_STATIC_TOPIC}")

    @property
    def rejections(self) -> int:
        """Transforms dropped so far (never counted by the tf2_ros backend, which logs its own)."""
        return self.rejected.count

    def _on_jump(self, jump) -> None:
        self.buffer.clear()
        switched = jump.clock_change in (ClockChange.ROS_TIME_ACTIVATED, ClockChange.ROS_TIME_DEACTIVATED)
        what = "switched between system and ROS time" if switched else f"jumped back {-jump.delta.nanoseconds / 1e9} s"
        self.node.get_logger().warning(f"the clock {what}: the tf buffer was cleared")

    def _take(self, msg, static: bool) -> None:
        for stamped in msg.transforms:
            header = stamped.header
            try:
                self.buffer.set_transform(header.frame_id, stamped.child_frame_id,
                                          header.stamp.sec * 10**9 + header.stamp.nanosec,
                                          from_msg(stamped.transform), static=static)
            except (TransformError, ValueError) as exc:
                self.rejected.warn(f"{header.frame_id!r} -> {stamped.child_frame_id!r} "
                                   f"({TF_STATIC_TOPIC if static else TF_TOPIC}): {exc}")

    def lookup(self, target: str, source: str, stamp=None) -> Transform:
        """The transform mapping points in ``source`` into ``target`` at ``stamp``."""
        when = stamp_ns(stamp)
        if self._tf2 is None:
            return self.buffer.lookup(target, source, when)
        return self._tf2_lookup(target, source, when)

    def pose_in(self, target: str, source: str, stamp=None) -> tuple[float, float, float]:
        """``source``'s origin in ``target`` at ``stamp``: ``(x, y, yaw)`` (m, m, rad)."""
        pose = self.lookup(target, source, stamp)
        return float(pose.translation[0]), float(pose.translation[1]), pose.yaw

    def _tf2_lookup(self, target: str, source: str, when: int | None) -> Transform:
        import tf2_ros

        try:
            stamped = self._tf2.lookup_transform(target, source, Time(nanoseconds=when or 0))
        except tf2_ros.LookupException as exc:
            raise FrameMissing(f"no transform from {source!r} to {target!r}: {exc}", None) from exc
        except tf2_ros.ConnectivityException as exc:
            raise NotConnected(f"frames {target!r} and {source!r} are not connected: {exc}", None) from exc
        except tf2_ros.ExtrapolationException as exc:
            raise ExtrapolationError(f"no transform from {source!r} to {target!r} at that time: {exc}", target,
                                     source, when or 0) from exc
        except tf2_ros.TransformException as exc:
            raise TransformError(f"no transform from {source!r} to {target!r}: {exc}") from exc
        return from_msg(stamped.transform)

    def destroy(self) -> None:
        """Stop listening (the subscriptions go; the buffer stays readable)."""
        if self._tf2 is not None:
            self._tf2_listener.unregister()
        else:
            self._jump.unregister()
            for subscription in self._subscriptions:
                self.node.destroy_subscription(subscription)
            self._subscriptions = []
