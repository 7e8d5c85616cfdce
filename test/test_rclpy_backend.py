"""The rclpy backend against a real ROS 2 Jazzy installation (skipped where rclpy is missing)."""
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.middleware.port import LATCHED_QOS, ParameterError  # noqa: E402
from hdrqn_ros.middleware.rclpy_backend import RclpyMiddleware, rclpy_available  # noqa: E402


@pytest.fixture
def middleware():
    mw = RclpyMiddleware(["prog", "--ros-args", "-p", "rate:=5.0", "-p", "label:=7"])
    yield mw
    mw.shutdown()


def test_available():
    assert rclpy_available()


def test_publish_and_receive_int32(middleware):
    talker = middleware.create_node("talker")
    listener = middleware.create_node("listener")
    got = []
    listener.create_subscription("std_msgs/msg/Int32", "chatter", lambda m: got.append(m.data))
    pub = talker.create_publisher("std_msgs/msg/Int32", "chatter")
    Int32 = talker.msg("std_msgs/msg/Int32")
    talker.create_timer(0.05, lambda: pub.publish(Int32(data=42)))  # repeats until discovery matched
    middleware.spin(until=lambda: bool(got), timeout_s=60.0)
    assert got and got[0] == 42


def test_latched_sample_reaches_late_subscriber(middleware):
    node = middleware.create_node("latch")
    Int32 = node.msg("std_msgs/msg/Int32")
    node.create_publisher("std_msgs/msg/Int32", "status", LATCHED_QOS).publish(Int32(data=7))
    got = []
    node.create_subscription("std_msgs/msg/Int32", "status", lambda m: got.append(m.data), LATCHED_QOS)
    middleware.spin(until=lambda: bool(got), timeout_s=60.0)
    assert got == [7]


def test_parameters_override_and_type_mismatch(middleware):
    node = middleware.create_node("params")
    assert node.declare_parameters({"rate": 1.0, "steps": 3}) == {"rate": 5.0, "steps": 3}
    assert node.declare_parameters({"use_sim_time": False}) == {"use_sim_time": False}
    with pytest.raises(ParameterError, match="label") as info:
        node.declare_parameters({"label": "text"})
    assert "/params" in str(info.value)


def test_names_logger_and_unknown_type(middleware):
    node = middleware.create_node("named", "/ns")
    assert node.fully_qualified_name == "/ns/named"
    assert node.resolve_topic("chatter") == "/ns/chatter"
    assert node.resolve_topic("~/state") == "/ns/named/state"
    node.logger.info("printf-style %s %d", "args", 3)
    with pytest.raises(ValueError, match="no_such_pkg"):
        node.msg("no_such_pkg/msg/Nothing")
    with pytest.raises(ValueError):
        node.msg("std_msgs/Int32")


def test_spin_timeout_and_shutdown_twice():
    mw = RclpyMiddleware(["prog"])
    mw.create_node("idle")
    mw.spin(timeout_s=0.1)
    mw.shutdown()
    mw.shutdown()
    mw.spin(timeout_s=0.1)  # returns at once on a shut-down context
