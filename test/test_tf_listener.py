"""TfListener over real DDS (loopback): this process's probe node publishes a static
``map -> odom`` before the listener exists (transient-local: the late joiner must get it) and
then timed ``odom -> base_link``; a listener in a process of its own looks ``base_link`` up in
``map`` and reports the composed pose and the errors' text."""
from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.nodes.qos import keep_last  # noqa: E402
from hdrqn_ros.nodes.tf_listener import TfListener, stamp_ns, tf2_ros_available  # noqa: E402

from conftest import ros_probe  # noqa: E402

S = 10**9
DEADLINE_S = 60.0
MAP_ODOM = (0.8, 0.4, 0.2)
"""A localised robot's ``map -> odom`` (m, m, rad)."""
EXIT_S = 30.0
"""How long the listener may take to report and exit after its own deadline."""
QUERY_NS = 100_250_000_000
"""Between the 100.2 s and 100.3 s samples of ``odom -> base_link``."""

LISTENER = """
import json, sys
sys.path.insert(0, {test_dir!r})
from rclpy.time import Time
from ros_probe import RosProbe
from hdrqn_ros.nodes.tf_listener import TfListener
from hdrqn_ros.robot.transforms import TransformError

probe = RosProbe(["tf_listener"])
node = probe.create_node("tf_listener")
tf = TfListener(node, prefer_tf2_ros={prefer_tf2_ros})
result = {{"backend": tf.backend}}

def composed():
    try:
        result["pose"] = tf.pose_in("map", "base_link", Time(nanoseconds={query_ns}))
        tf.lookup("map", "base_link", Time(nanoseconds=101 * 10**9))  # the last sample: every message is in
    except TransformError as exc:
        result.pop("pose", None)
        result["waited_on"] = str(exc)
        return False
    return True

probe.spin(until=composed, timeout_s={deadline_s})
if "pose" in result:
    result["latest"] = tf.pose_in("map", "base_link")
    for name, target, source, stamp in [("missing", "map", "gripper", None),
                                        ("too_late", "map", "base_link", Time(nanoseconds=200 * 10**9))]:
        try:
            tf.lookup(target, source, stamp)
        except TransformError as exc:
            result[name] = [type(exc).__name__, str(exc)]
    result["rejections"] = tf.rejections
print("RESULT " + json.dumps(result), flush=True)
probe.shutdown()
"""




def stamped(node, parent: str, child: str, stamp_ns: int, x: float, y: float, yaw: float, rotation=None):
    t = node.msg("geometry_msgs/msg/TransformStamped")()
    t.header.frame_id, t.child_frame_id = parent, child
    t.header.stamp.sec, t.header.stamp.nanosec = divmod(stamp_ns, S)
    t.transform.translation.x, t.transform.translation.y = x, y
    r = t.transform.rotation
    r.x, r.y, r.z, r.w = rotation or (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
    return t


def tf_message(node, *transforms):
    msg = node.msg("tf2_msgs/msg/TFMessage")()
    msg.transforms = list(transforms)
    return msg


def odom_base(s: float) -> tuple[float, float, float]:
    """The robot in ``odom`` at ``s`` seconds after 100 s: 0.5 m/s along x, 0.2 m/s along y, 0.4 rad/s."""
    return 1.0 + 0.5 * s, 0.2 * s, 0.4 * s


def in_map(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    mx, my, myaw = MAP_ODOM
    return (mx + math.cos(myaw) * x - math.sin(myaw) * y, my + math.sin(myaw) * x + math.cos(myaw) * y, myaw + yaw)


@pytest.mark.parametrize("backend", ["hdrqn_ros", pytest.param("tf2_ros", marks=pytest.mark.skipif(
    not tf2_ros_available(), reason="tf2_ros needs a sourced ROS 2"))])
def test_a_late_listener_composes_static_map_odom_with_timed_odom_base_link(domain, backend):
    probe = ros_probe()
    listener = None
    try:
        node = probe.create_node("tf_publisher")
        # as tf2_ros's broadcasters offer them: static reliable, transient-local, depth 1; dynamic reliable, depth 100
        static_pub = node.create_publisher("tf2_msgs/msg/TFMessage", "/tf_static", keep_last(1, transient_local=True))
        tf_pub = node.create_publisher("tf2_msgs/msg/TFMessage", "/tf", keep_last(100))
        static_pub.publish(tf_message(node, stamped(node, "map", "odom", 0, *MAP_ODOM)))
        script = LISTENER.format(test_dir=str(Path(__file__).parent), prefer_tf2_ros=backend == "tf2_ros",
                                 query_ns=QUERY_NS, deadline_s=DEADLINE_S)
        listener = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True)
        deadline = time.monotonic() + DEADLINE_S
        probe.spin(until=lambda: tf_pub.get_subscription_count() > 0 or listener.poll() is not None,
                   timeout_s=DEADLINE_S)
        assert tf_pub.get_subscription_count() > 0, f"the listener never subscribed to /tf: {listener.poll()=}"
        tf_pub.publish(tf_message(node, stamped(node, "odom", "broken", 100 * S, 0, 0, 0, rotation=(0, 0, 0, 0)),
                                  stamped(node, "lidar_mount", "lidar", 100 * S, 0, 0, 0),
                                  stamped(node, "lidar", "lidar_mount", 100 * S, 0, 0, 0)))  # 1st and 3rd refused
        for k in range(11):  # 100.0 s to 101.0 s at 10 Hz; /tf is reliable and in order: 101 s comes last
            tf_pub.publish(tf_message(node, stamped(node, "odom", "base_link", 100 * S + k * S // 10,
                                                    *odom_base(k / 10))))
        out, err = listener.communicate(timeout=max(1.0, deadline - time.monotonic()) + EXIT_S)
    finally:
        if listener is not None and listener.poll() is None:
            listener.kill()
            listener.communicate()
        probe.shutdown()
    lines = [line for line in out.splitlines() if line.startswith("RESULT ")]
    assert listener.returncode == 0 and lines, f"listener exited {listener.returncode}:\n{out}\n{err}"
    result = json.loads(lines[-1][len("RESULT "):])
    assert "pose" in result, f"no pose within {DEADLINE_S} s, last error: {result.get('waited_on')}\n{err}"
    assert tuple(result["pose"]) == pytest.approx(in_map(*odom_base(0.25)), abs=1e-9)
    assert tuple(result["latest"]) == pytest.approx(in_map(*odom_base(1.0)), abs=1e-9)
    assert result["missing"][0] == "FrameMissing" and "'gripper'" in result["missing"][1]
    assert result["too_late"][0] == "ExtrapolationError" and "'map'" in result["too_late"][1]
    if backend == "hdrqn_ros":
        assert result["backend"].startswith("hdrqn_ros TransformBuffer")
        assert ("known frames: base_link, lidar, lidar_mount, map, odom; connected: {lidar, lidar_mount} and "
                "{base_link, map, odom}" in result["missing"][1])  # trees in the order of their roots
        assert ("at 200.0 s: edge 'odom' -> 'base_link' has data from 100.0 s to 101.0 s only"
                in result["too_late"][1])
        assert result["rejections"] == 2
        assert "not a unit quaternion" in err and "'lidar_mount' is already an ancestor of 'lidar'" in err
    else:
        assert result["backend"] == "tf2_ros.Buffer"


def test_lookup_stamps_are_rclpy_times_header_stamps_or_none():
    from builtin_interfaces.msg import Time as TimeMsg
    from rclpy.time import Time

    assert stamp_ns(Time(seconds=100, nanoseconds=250_000_000)) == QUERY_NS
    assert stamp_ns(TimeMsg(sec=100, nanosec=250_000_000)) == QUERY_NS
    assert stamp_ns(None) is None
    with pytest.raises(TypeError, match="rclpy.time.Time, a builtin_interfaces/msg/Time or None"):
        stamp_ns(100.25)


def test_a_jump_back_of_the_clock_clears_the_buffer(domain):
    """A simulation restarted: /clock goes from 100 s back to 50 s; samples before the jump
    would otherwise make every new one look too old."""
    from rclpy.parameter import Parameter

    from hdrqn_ros.robot.transforms import Transform, TransformBuffer

    probe = ros_probe()
    try:
        node = probe.create_node("tf_user", parameter_overrides=[Parameter("use_sim_time", value=True)])
        buffer = TransformBuffer()
        listener = TfListener(node, buffer=buffer)
        clock_node = probe.create_node("sim_clock")
        clock_pub = clock_node.create_publisher("rosgraph_msgs/msg/Clock", "/clock", keep_last(1))

        def clock_at(seconds: int):
            def reached() -> bool:
                msg = clock_node.msg("rosgraph_msgs/msg/Clock")()
                msg.clock.sec = seconds
                clock_pub.publish(msg)
                return node.get_clock().now().nanoseconds == seconds * S
            probe.spin(until=reached, timeout_s=DEADLINE_S)
            assert node.get_clock().now().nanoseconds == seconds * S, f"the node's clock never reached {seconds} s"

        clock_at(100)
        buffer.set_transform("odom", "base_link", 100 * S, Transform.from_xy_yaw(1, 0, 0))
        clock_at(101)
        assert buffer.frames() == ("base_link", "odom")  # forward: kept
        clock_at(50)
        assert buffer.frames() == ()
        buffer.set_transform("odom", "base_link", 50 * S, Transform.from_xy_yaw(2, 0, 0))
        assert listener.pose_in("odom", "base_link") == pytest.approx((2.0, 0.0, 0.0))
        listener.destroy()
    finally:
        probe.shutdown()
