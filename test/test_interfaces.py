"""The ROS 2 Jazzy interfaces PyPI has no wheels for, as ``scripts/build_interfaces`` builds them
from ros_interfaces/ (or as a sourced ROS 2 has them): Jazzy's RIHS01 type hashes, rclpy
serialization, a TFMessage topic and a NavigateToPose action over DDS (one process)."""
from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ros_probe
from hdrqn_ros.nodes.ros_packages import BUILT_PACKAGES, install_hint

JAZZY_HASHES = {
    # `ros2 topic info -v /tf` on Jazzy systems (several published outputs); shared/DESIGN.md section 5
    "tf2_msgs/msg/TFMessage": "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    # a published `ros2 topic info -v` of rviz's costmap updates subscription
    "map_msgs/msg/OccupancyGridUpdate": "RIHS01_c4095b0be2e4363f8978a1570e0293ee093436f1e1c61d99b48502ac317025e8",
    # a Nav2 node's /bond publication as Fast DDS announces it (a captured discovery packet)
    "bond/msg/Status": "RIHS01_87eaccffa254ffffadc0b61600452e8251740f06c25659a2dbda4927fdb1f70a",
    # nav2_msgs 1.3 (Jazzy): shared/DESIGN.md section 5 has RIHS01_a56dba8a...7eab from a Jazzy Nav2
    "nav2_msgs/action/NavigateToPose": "RIHS01_a56dba8a3234a1215e610180dc703ae25bbf406dded8b54887891c9732857eab",
    # the feedback topic's type in a published table of a Jazzy robot stack's hashes
    "nav2_msgs/action/NavigateToPose_FeedbackMessage":
        "RIHS01_9d1f6fa2eb975ce733b419ac2e97b134d8ff92b6478b6559feed9a50bdfd82b3",
    # a Jazzy bt_navigator's send_goal reply as Fast DDS announces it (a captured discovery packet)
    "nav2_msgs/action/NavigateToPose_SendGoal_Response":
        "RIHS01_99f97fcbb07daf024df4b8c3f02f19ce7fa3183fcedfb76b8772a61a371a55fa",
}
"""Jazzy's type hashes (what discovery compares: a type with another hash does not match)."""

ROOT = Path(__file__).resolve().parents[1]
DEADLINE_S = 60.0




def interface(type_name: str):
    """The rosidl class of ``"pkg/kind/Type"``; a failure naming how to build it when missing."""
    package, kind, name = type_name.split("/")
    try:
        return getattr(importlib.import_module(f"{package}.{kind}"), name)
    except ModuleNotFoundError as error:
        pytest.fail(f"{type_name} cannot be imported ({error}): {install_hint(package)}")


def described_hash(type_name: str) -> str:
    """The RIHS01 hash of ``type_name`` in the type description (``share/<pkg>/<kind>/<Type>.json``)
    installed beside the Python package that imports (``<prefix>/lib/pythonX.Y/site-packages/<pkg>``)."""
    package, kind, name = type_name.split("/")
    top = name.split("_")[0]
    prefix = Path(importlib.import_module(package).__file__).parents[4]
    described = json.loads((prefix / "share" / package / kind / f"{top}.json").read_text())
    return {entry["type_name"]: entry["hash_string"] for entry in described["type_hashes"]}[type_name]


def announced_hash(node, topic: str) -> str:
    """The type hash the one publisher of ``topic`` announces, as ``RIHS01_<hex>``."""
    (info,) = node.get_publishers_info_by_topic(topic)
    return f"RIHS{info.topic_type_hash.version:02d}_{info.topic_type_hash.value.hex()}"


def test_ros_interfaces_holds_the_built_packages():
    folders = {path.parent.name for path in (ROOT / "ros_interfaces").glob("*/package.xml")}
    assert folders == set(BUILT_PACKAGES) == {name.split("/")[0] for name in JAZZY_HASHES}


def build_interfaces(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    """``scripts/build_interfaces *args`` on this test's venv, in environment ``env``."""
    return subprocess.run([str(ROOT / "scripts/build_interfaces"), *args], capture_output=True, text=True,
                          timeout=DEADLINE_S, env={**env, "VENV": sys.prefix})


def test_a_sourced_ros_2s_packages_are_left_to_it(tmp_path):
    for package in BUILT_PACKAGES:
        index = tmp_path / "opt_ros/share/ament_index/resource_index/packages"
        index.mkdir(parents=True, exist_ok=True)
        (index / package).touch()
    done = build_interfaces(env={**os.environ, "AMENT_PREFIX_PATH": str(tmp_path / "opt_ros")})
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [f"{package}: provided by {tmp_path / 'opt_ros'} (a sourced ROS 2), not built"
                                        for package in ("tf2_msgs", "map_msgs", "bond", "nav2_msgs")]


def test_a_missing_compiler_names_the_debian_package(tmp_path):
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin/dirname").symlink_to(shutil.which("dirname"))
    done = build_interfaces("--force", env={"PATH": str(tmp_path / "bin"), "HOME": str(tmp_path)})
    assert done.returncode == 1
    assert "no C/C++ compiler" in done.stderr and "sudo apt install g++" in done.stderr, done.stderr


@pytest.mark.parametrize("type_name", sorted(JAZZY_HASHES))
def test_type_descriptions_hash_as_jazzys(type_name):
    package, kind, name = type_name.split("/")
    interface(f"{package}/{kind}/{name.split('_')[0]}")
    assert described_hash(type_name) == JAZZY_HASHES[type_name]


def sample_messages() -> list:
    """One message of each type with every field set away from its default."""
    from builtin_interfaces.msg import Duration, Time
    from geometry_msgs.msg import PoseStamped, TransformStamped

    tf = interface("tf2_msgs/msg/TFMessage")
    update = interface("map_msgs/msg/OccupancyGridUpdate")
    status = interface("bond/msg/Status")
    action = interface("nav2_msgs/action/NavigateToPose")
    edge = TransformStamped(child_frame_id="base_link")
    edge.header.frame_id, edge.header.stamp = "odom", Time(sec=12, nanosec=5)
    edge.transform.translation.x, edge.transform.rotation.z, edge.transform.rotation.w = 0.8, 0.0998, 0.995
    pose = PoseStamped()
    pose.header.frame_id, pose.pose.position.x, pose.pose.position.y = "map", 1.25, -0.5
    grid = update(x=3, y=4, width=2, height=3, data=[0, 1, 98, 99, 100, -1])
    grid.header.frame_id = "odom"
    beat = status(id="sub_controller", instance_id="f00d", active=True, heartbeat_timeout=4.0, heartbeat_period=0.25)
    return [tf(transforms=[edge, TransformStamped(child_frame_id="odom")]), grid, beat,
            action.Goal(pose=pose, behavior_tree="navigate.xml"),
            action.Result(error_code=action.Result.NONE + 7, error_msg="no path"),
            action.Feedback(current_pose=pose, navigation_time=Duration(sec=3), estimated_time_remaining=Duration(sec=9),
                            number_of_recoveries=2, distance_remaining=1.5)]


def test_messages_round_trip_through_rclpy_serialization():
    from rclpy.serialization import deserialize_message, serialize_message

    for msg in sample_messages():
        data = serialize_message(msg)
        back = deserialize_message(data, type(msg))
        assert back == msg, type(msg).__name__
        assert back != type(msg)(), f"{type(msg).__name__}: the sample must differ from the defaults"


def test_tf_message_over_dds_with_jazzys_hashes(domain):
    from rclpy.qos import DurabilityPolicy, QoSProfile

    tf_type = interface("tf2_msgs/msg/TFMessage")
    sample = sample_messages()[0]
    received = []
    with ros_probe() as probe:
        talker, listener = probe.create_node("tf_talker"), probe.create_node("tf_listener")
        static = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        talker.create_publisher(tf_type, "/tf_static", static).publish(sample)
        listener.create_subscription(tf_type, "/tf_static", received.append, static)
        for type_name, topic in (("bond/msg/Status", "/bond"), ("map_msgs/msg/OccupancyGridUpdate", "/costmap_updates")):
            talker.create_publisher(interface(type_name), topic, 10)
        probe.spin(until=lambda: received, timeout_s=DEADLINE_S)
        assert received == [sample], f"no TFMessage on /tf_static within {DEADLINE_S} s"
        for type_name, topic in (("tf2_msgs/msg/TFMessage", "/tf_static"), ("bond/msg/Status", "/bond"),
                                 ("map_msgs/msg/OccupancyGridUpdate", "/costmap_updates")):
            assert announced_hash(listener, topic) == JAZZY_HASHES[type_name], topic


def test_navigate_to_pose_action_over_dds(domain):
    from action_msgs.msg import GoalStatus
    from rclpy.action import ActionClient, ActionServer

    action = interface("nav2_msgs/action/NavigateToPose")
    goal_sample, failed, feedback_sample = sample_messages()[3:]

    def navigate(handle):
        handle.publish_feedback(feedback_sample)
        if handle.request.behavior_tree == "unreachable":
            handle.abort()
            return failed
        handle.succeed()
        return action.Result(error_code=action.Result.NONE)

    with ros_probe() as probe:
        server_node, client_node = probe.create_node("navigator"), probe.create_node("agent")
        ActionServer(server_node, action, "navigate_to_pose", navigate)
        client = ActionClient(client_node, action, "navigate_to_pose")
        probe.spin(until=client.server_is_ready, timeout_s=DEADLINE_S)
        assert client.server_is_ready(), f"no navigate_to_pose server within {DEADLINE_S} s"
        outcomes = []
        for behavior_tree in ("", "unreachable"):
            feedback = []
            goal = action.Goal(pose=goal_sample.pose, behavior_tree=behavior_tree)
            sent = client.send_goal_async(goal, feedback_callback=lambda msg: feedback.append(msg.feedback))
            probe.spin(until=sent.done, timeout_s=DEADLINE_S)
            assert sent.done() and sent.result().accepted, "the goal was not accepted"
            result = sent.result().get_result_async()
            probe.spin(until=lambda: result.done() and feedback, timeout_s=DEADLINE_S)
            assert result.done(), f"no result within {DEADLINE_S} s"
            assert feedback == [feedback_sample]
            outcomes.append((result.result().status, result.result().result))
        assert outcomes == [(GoalStatus.STATUS_SUCCEEDED, action.Result(error_code=action.Result.NONE)),
                            (GoalStatus.STATUS_ABORTED, failed)]
        assert announced_hash(client_node, "/navigate_to_pose/_action/feedback") == \
            JAZZY_HASHES["nav2_msgs/action/NavigateToPose_FeedbackMessage"]
