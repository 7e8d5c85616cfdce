"""Where ``robot_environment`` hears the robot: the pose (tf or ``pose_topic``), the costmaps
(full grids and Nav2's ``<costmap>_updates``) and the places (``subgoal_table`` or a latched
``subgoal_poses_topic``).

:func:`subscribe_robot_inputs` builds the node's
:class:`~hdrqn_ros.nodes.robot_inputs.RobotInputs` (tf joins the frames) and subscribes it
to its topics. The package builds ``tf2_msgs`` and ``map_msgs`` itself (``scripts/install``):
without them the pose needs a topic, and the costmaps full grids.
"""
from __future__ import annotations

import logging
from collections.abc import Callable

from geometry_msgs.msg import PoseArray
from nav_msgs.msg import OccupancyGrid
from rclpy.node import Node
from rclpy.time import Time

from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.parameters import NodeConfigError
from hdrqn_ros.nodes.qos import DEFAULT_QOS, LATCHED_QOS, keep_last
from hdrqn_ros.nodes.robot_inputs import Frames, RobotInputs
from hdrqn_ros.nodes.ros_messages import bounded_subscription, interface_class
from hdrqn_ros.nodes.tf_listener import TfListener

OCCUPANCY_GRID_UPDATE = "map_msgs/msg/OccupancyGridUpdate"
UPDATES_QOS = keep_last(10, transient_local=True)
"""``<costmap>_updates``: Nav2 offers reliable, transient local; a few deep, so none is lost in a burst."""


def subscribe_robot_inputs(node: Node, logger: logging.Logger, params: dict, num_subgoals: int, view: int,
                           on_pose: Callable, checked: tuple[str, ...] = ()) -> RobotInputs:
    """The robot's inputs for ``node`` (its ``robot_environment`` parameters ``params``),
    subscribed; ``on_pose(msg)`` takes a pose topic's message; ``checked``: the protocol
    topics the node reads itself (named when one of their messages is rejected)."""
    places = nav.SubgoalTable.load(params["subgoal_table"], num_subgoals) if params["subgoal_table"] else None
    from_tf = not params["pose_topic"]
    try:
        tf, no_tf = TfListener(node, max_message_bytes=params["max_message_bytes"]), ""
    except ImportError as exc:  # tf2_msgs is not on PyPI: scripts/install builds it
        tf, no_tf = None, str(exc)
    if from_tf and tf is None:
        raise NodeConfigError(f"the robot pose from tf ({params['global_frame']} <- {params['robot_base_frame']}) "
                              f"needs tf2_msgs: {no_tf}; or give a pose topic (pose_topic)")

    def lookup(target: str, source: str, stamp_ns: int | None):
        return tf.lookup(target, source, None if stamp_ns is None else Time(nanoseconds=stamp_ns))

    topics = {"pose": params["pose_topic"], "costmap": params["costmap_topic"],
              "costmap_updates": params["costmap_topic"] + "_updates", "global": params["global_costmap_topic"],
              "global_updates": params["global_costmap_topic"] and params["global_costmap_topic"] + "_updates",
              "places": params["subgoal_poses_topic"], **{topic: topic for topic in checked}}
    inputs = RobotInputs(logger, {kind: node.resolve_topic_name(topic) for kind, topic in topics.items() if topic},
                         places, num_subgoals, view, params["cell_size_m"],
                         Frames(lookup if tf is not None else None, no_tf),
                         (params["global_frame"], params["robot_base_frame"]) if from_tf else None,
                         amcl_like=params["pose_type"] == "pose_with_covariance")

    def subscribe(msg_type, topic: str, callback, qos) -> None:
        bounded_subscription(node, msg_type, topic, callback, qos, params["max_message_bytes"], logger)

    def now() -> int:
        return node.get_clock().now().nanoseconds

    if params["pose_topic"]:
        subscribe(interface_class(nav.POSE_TYPES[params["pose_type"]]), params["pose_topic"], on_pose, DEFAULT_QOS)
    for kind, topic in (("costmap", params["costmap_topic"]), ("global", params["global_costmap_topic"])):
        if not topic:
            continue
        subscribe(OccupancyGrid, topic, lambda msg, kind=kind: inputs.take_costmap(msg, now(), kind), LATCHED_QOS)
        try:
            update = interface_class(OCCUPANCY_GRID_UPDATE)
        except ImportError as exc:  # map_msgs is not on PyPI: scripts/install builds it
            node.get_logger().warning(f"not reading {topic}_updates: {exc}; Nav2's costmap must then send full "
                                      f"grids (always_send_full_costmap: true)")
            continue
        subscribe(update, topic + "_updates", lambda msg, kind=kind: inputs.take_update(msg, now(), kind), UPDATES_QOS)
    if params["subgoal_poses_topic"]:
        subscribe(PoseArray, params["subgoal_poses_topic"], inputs.take_places, LATCHED_QOS)
    return inputs
