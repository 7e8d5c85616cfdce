"""The sub-controller free-running on a robot's local costmap (``observation_source: costmap``):
no environment node and no lock-step; one action per costmap update."""
from __future__ import annotations

import time

import numpy as np
from nav_msgs.msg import OccupancyGrid
from std_msgs.msg import Int64MultiArray

from hdrqn_ros.agents.specs import stack_subgoal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.nodes.controller_node import ControllerNode
from hdrqn_ros.nodes.nav import SubgoalTable, costmap_to_observation
from hdrqn_ros.nodes.nav_adapters import VelocityDriver
from hdrqn_ros.nodes.parameters import Param
from hdrqn_ros.nodes.qos import LATCHED_QOS, STEP_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, bounded_subscription
from hdrqn_ros.protocol import wire

OBSERVATION_PARAMETERS = {
    "observation_source": Param("topic", "topic: the environment's observation; costmap: free-running on "
                                         "costmap_topic", choices=("topic", "costmap")),
    "costmap_topic": Param("/local_costmap/costmap", "the nav_msgs/OccupancyGrid observed with observation_source "
                                                     "costmap"),
}
"""Where the sub-controller's observation comes from."""
_ONE = np.ones(1, bool)  # the rows mask of the one robot


class CostmapSubController:
    """Acts for one robot on each ``costmap_topic`` update: the observation is the costmap's
    ``view`` x ``view`` window around the robot (:func:`~hdrqn_ros.nodes.nav.costmap_to_observation`);
    a hierarchical agent acts toward the latest ``subgoal`` heard (none before the first), with
    the window centred on that subgoal's place in ``places`` as its subgoal image (blank
    without places). Each action goes out on ``action`` stamped with the costmap's stamp, and
    to ``driver``."""

    def __init__(self, node: ControllerNode, driver: VelocityDriver | None, places: SubgoalTable | None):
        self.node, self.driver, self.places = node, driver, places
        params = node.params
        self.view, self.topic = int(params["view"]), params["costmap_topic"]
        self.hierarchical = node.spec.hierarchical
        self.subgoal = -1  # the latest subgoal heard
        self.subgoal_image = np.zeros((OBS_SIZE, OBS_SIZE, 3), np.uint8)
        self.costmaps = 0
        self.pub_action = node.create_publisher(Int64MultiArray, wire.ACTION, STEP_QOS)
        limit = params["max_message_bytes"]
        node.watch.expect(self.topic, "the robot's local costmap (Nav2's local_costmap, costmap_topic)")
        bounded_subscription(node, OccupancyGrid, self.topic, self._on_costmap, LATCHED_QOS, limit, node.logger)
        if self.hierarchical:
            node.watch.expect(wire.SUBGOAL, "the meta_controller")
            bounded_subscription(node, Int64MultiArray, wire.SUBGOAL, self._on_subgoal, STEP_QOS, limit, node.logger)

    def reset(self) -> None:
        """A fresh episode from the next costmap on."""
        self.node.policy.start_episodes(_ONE)

    def problems(self) -> list[str]:
        if self.hierarchical and self.subgoal < 0:
            return [f"no subgoal yet on {self.node.resolve_topic_name(wire.SUBGOAL)} (is the meta_controller running?)"]
        return []

    def _on_subgoal(self, msg: Int64MultiArray) -> None:
        self.node.watch.hear(wire.SUBGOAL)
        chosen = self.node.decode(wire.SUBGOAL, lambda: wire.read_subgoals(msg, self.node.net.num_subgoals, 1))
        if chosen is not None:
            self.subgoal = int(chosen[1][0])

    def _on_costmap(self, msg: OccupancyGrid) -> None:
        node = self.node
        if not node.active:
            return
        node.watch.hear(self.topic)
        obs = node.decode(self.topic, lambda: costmap_to_observation(msg, view_cells=self.view))
        if obs is None:
            return
        if self.driver is not None:
            self.driver.observed()
        self.costmaps += 1
        key = wire.key_of(msg.header.stamp) or self.costmaps
        x = obs
        if self.hierarchical:
            if self.subgoal < 0:
                return
            if self.subgoal != node.policy.subgoal[0]:  # a new option
                node.policy.start_options(_ONE, np.array([self.subgoal]))
            if self.places is not None:
                self.subgoal_image = costmap_to_observation(msg, robot_xy=self.places.poses[self.subgoal][:2],
                                                            view_cells=self.view)
            x = stack_subgoal(obs, self.subgoal_image)
        started = time.perf_counter()
        action = int(node.policy.act(x[None], node.net.epsilon, node.net.rng)[0])
        node.diagnostics.decision(time.perf_counter() - started)
        self.pub_action.publish(wire.make_record(ROS_MESSAGES, wire.INTS, wire.ACTION_FIELDS, [key, action]))
        if self.driver is not None:
            pub, command = self.driver.command(action, key)
            pub.publish(command)
