"""What ``robot_environment`` publishes for a step: ``env_step``, ``observation``,
``subgoal_images`` and ``pose`` (``docs/topics.md``), stamped with the step's key, and the
places as ``subgoal_markers`` for RViz (:mod:`~hdrqn_ros.nodes.place_markers`).
"""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from sensor_msgs.msg import Image
from std_msgs.msg import Float64MultiArray
from visualization_msgs.msg import MarkerArray

from hdrqn_ros.nodes.place_markers import MARKERS, place_markers
from hdrqn_ros.nodes.qos import DEFAULT_QOS, STEP_QOS
from hdrqn_ros.nodes.robot_scene import Scene
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES
from hdrqn_ros.protocol import wire
from hdrqn_ros.robot.ordered_visits import OrderedVisits


class StepPublishers:
    """``node``'s publishers of a robot step."""

    def __init__(self, node: Node):
        self.obs = node.create_publisher(Image, wire.OBSERVATION, STEP_QOS)
        self.images = node.create_publisher(Image, wire.SUBGOAL_IMAGES, STEP_QOS)
        self.step = node.create_publisher(Float64MultiArray, wire.ENV_STEP, STEP_QOS)
        self.pose = node.create_publisher(PoseStamped, wire.POSE, DEFAULT_QOS)
        self.markers = node.create_publisher(MarkerArray, MARKERS, DEFAULT_QOS)

    def publish(self, key: int, record: dict, scene: Scene, obs: np.ndarray, images: np.ndarray) -> None:
        """The step ``key``: its ``env_step`` ``record`` (``wire.STEP_FIELDS``), ``obs`` and
        ``images`` (``uint8`` RGB, :func:`~hdrqn_ros.nodes.robot_scene.step_images`) and the
        robot's pose (m), all in the pose's frame: the one whose axes a north-up view keeps
        (a motion primitive's moves are in it)."""
        frame = scene.pose.frame
        self.step.publish(wire.make_record(ROS_MESSAGES, wire.FLOATS, wire.STEP_FIELDS,
                                           [record[f] for f in wire.STEP_FIELDS]))
        self.obs.publish(wire.make_image(ROS_MESSAGES, key, obs, frame))
        self.images.publish(wire.make_image(ROS_MESSAGES, key, images, frame))
        self.pose.publish(wire.make_pose(ROS_MESSAGES, key, frame, scene.pose.x, scene.pose.y))

    def publish_markers(self, key: int, scene: Scene, task: OrderedVisits, aimed: int) -> None:
        """The places of ``task`` (visited or not) and the robot, ``aimed``: the current option's place."""
        header = wire.make_header(ROS_MESSAGES, key, scene.pose.frame)
        self.markers.publish(place_markers(header, task.goal_xy, task.collected, aimed, (scene.pose.x, scene.pose.y)))
