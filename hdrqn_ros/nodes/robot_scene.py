"""A robot step's scene and the images drawn from it (``robot_environment``).

:func:`scene_at` puts the robot's pose at a step's time, the places and both costmaps in
one frame, the pose's (tf joins the frames, each costmap at its own stamp);
:func:`step_images` draws the step's ``observation`` (the local costmap around the robot)
and ``subgoal_images`` (the places' costmap around each place) from that scene, as the
simulator draws its view: the places still to visit in their colours.
"""
from __future__ import annotations

import math

import numpy as np

from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.robot_inputs import Grid, RobotInputs, RobotPose
from hdrqn_ros.robot.transforms import Transform


class Scene:
    """What a step is built from: the robot's ``pose``, the places ``goal_xy`` ``(n, 2)`` in
    its frame, and the transforms from that frame into the costmap's (``to_costmap``) and the
    places' images' costmap's (``to_images``) frames."""

    def __init__(self, pose: RobotPose, goal_xy: np.ndarray, to_costmap: Transform, to_images: Transform):
        self.pose, self.goal_xy, self.to_costmap, self.to_images = pose, goal_xy, to_costmap, to_images

    def robot_in(self, to: Transform) -> tuple[float, float, float]:
        """The robot's ``(x, y, yaw)`` in the frame ``to`` maps into."""
        x, y = to.apply((self.pose.x, self.pose.y))
        return float(x), float(y), self.pose.yaw + to.yaw


def scene_at(inputs: RobotInputs, at_ns: int, now: int, stale_ns: int, pose_waited_s: float,
             pose_timeout_s: float) -> Scene:
    """The robot at ``at_ns`` (ROS time, ns; the latest pose once it waited ``pose_timeout_s``
    wall seconds) and the places and costmaps in its frame; raises
    :class:`~hdrqn_ros.nodes.robot_inputs.Waiting` naming what is missing."""
    pose = inputs.pose_at(at_ns, now, stale_ns, pose_waited_s, pose_timeout_s)
    places, frames = inputs.places, inputs.frames
    to_pose = frames.transform(pose.frame, places.frame_id, pose.stamp_ns,
                               f"the places ({places.source}, frame {places.frame_id!r})")
    goal_xy = to_pose.apply(np.array([p[:2] for p in places.poses]))
    into = {}
    for kind, grid in (("costmap", inputs.costmap.value), ("global", inputs.places_costmap)):
        topic = inputs.topics.get(kind if inputs.global_costmap.value is not None else "costmap")
        into[kind] = frames.transform(grid.frame_id, pose.frame, grid.stamp_ns,
                                      f"the costmap on {topic} (frame {grid.frame_id!r})")
    return Scene(pose, goal_xy, into["costmap"], into["global"])


def step_images(scene: Scene, goal_xy: np.ndarray, uncollected_xy: list, costmap: Grid, images_costmap: Grid,
                view: int, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """The step's ``observation`` ``(44, 44, 3) uint8`` and ``subgoal_images``
    ``(44 n, 44, 3) uint8``, each drawn from its costmap in the costmap's frame: ``view`` x
    ``view`` cells of ``params['cell_size_m']`` (m); ``goal_xy`` ``(n, 2)`` the places and
    ``uncollected_xy`` each place's (x, y) or ``None`` once visited, in the pose's frame;
    ``params``: the node's ``heading_up``, ``lethal``, ``unknown_cells``."""

    def drawn(to: Transform) -> tuple[tuple[float, float], dict]:
        """The robot's (x, y) and the drawing's settings in the frame ``to`` maps into;
        image up: the robot's heading, or (north-up) the pose frame's +y."""
        x, y, yaw = scene.robot_in(to)
        goals = [None if xy is None else tuple(to.apply(xy)) for xy in uncollected_xy]
        up = yaw if params["heading_up"] else (None if to.yaw == 0.0 else math.pi / 2 + to.yaw)
        return (x, y), {"view_cells": view, "cell_size_m": params["cell_size_m"], "lethal": params["lethal"],
                        "robot_yaw": up, "unknown": params["unknown_cells"], "goals_xy": goals}

    robot_xy, style = drawn(scene.to_costmap)
    obs = nav.costmap_to_observation(costmap, robot_xy=robot_xy, **style)
    robot_xy, style = drawn(scene.to_images)
    images = np.concatenate([nav.costmap_to_observation(images_costmap, robot_xy=scene.to_images.apply(xy),
                                                        agent_xy=robot_xy, **style) for xy in goal_xy])
    return obs, images
