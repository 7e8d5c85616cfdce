"""What the robot-side environment knows of the robot: its latest pose, costmaps and places.

Each input is checked as it arrives and refused, with a throttled warning, when it cannot be
used: a frame other than the places' (there is no tf2 here), a non-finite pose, a costmap
smaller than the view, places that do not fit the agent. :meth:`RobotInputs.missing` says
why no step can be built yet. Times are ROS time in ns; the messages' fields are read as
they are (no ROS import).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from hdrqn_ros.nodes import nav
from hdrqn_ros.protocol import wire
from hdrqn_ros.throttle import Throttle


@dataclass
class Latest:
    """The latest accepted message of an input: its content, the ROS time it arrived and its
    header stamp (ns; -1: nothing yet)."""

    value: Any = None
    arrived_ns: int = -1
    stamp_ns: int = -1


class RobotInputs:
    """The robot's latest ``pose`` (``(x, y, yaw)``: m, rad), ``costmap`` and ``global_costmap``
    (OccupancyGrids) and ``places`` (a :class:`~hdrqn_ros.nodes.nav.SubgoalTable`, ``None``
    until heard). ``topics``: each input's resolved topic name by kind (pose, costmap, and
    global, places and the protocol inputs the node checks itself where used)."""

    def __init__(self, logger: logging.Logger, topics: dict[str, str], places: nav.SubgoalTable | None,
                 num_subgoals: int, view_cells: int, cell_size_m: float):
        self.topics, self.num_subgoals = topics, num_subgoals
        self.view_cells, self.cell_size_m = view_cells, cell_size_m
        self.rejected = {kind: Throttle(logger, f"rejected a message on {topic}") for kind, topic in topics.items()}
        self.places, self.places_stamp = places, 0  # the places' header stamp (a table's: 0)
        self.pose, self.costmap, self.global_costmap = Latest(), Latest(), Latest()

    def reject(self, kind: str, why: object) -> None:
        self.rejected[kind].warn(why)

    @property
    def rejections(self) -> int:
        return sum(throttle.count for throttle in self.rejected.values())

    def _check_frame(self, frame_id: str, what: str) -> None:
        if self.places is not None and frame_id != self.places.frame_id:
            raise nav.NavConfigError(f"{what} is in frame {frame_id!r} but the places are in {self.places.frame_id!r} "
                                     f"({self.places.source}); publish both in one frame (no tf2 here)")

    def take_pose(self, msg, now: int) -> bool:
        """A pose message (any of :data:`~hdrqn_ros.nodes.nav.POSE_TYPES`): whether it was taken."""
        try:
            pose = nav.robot_pose(msg)
            self._check_frame(msg.header.frame_id, "the robot pose")
        except nav.NavConfigError as exc:
            self.reject("pose", exc)
            return False
        self.pose = Latest(pose, now, wire.key_of(msg.header.stamp))
        return True

    def take_costmap(self, msg, now: int, kind: str = "costmap") -> bool:
        """An OccupancyGrid for the observation (``kind`` costmap) or the places' images (global)."""
        what = "the costmap" if kind == "costmap" else "the global costmap"
        info, cells, cell_m = msg.info, self.view_cells, self.cell_size_m
        side, need = min(info.width, info.height) * info.resolution, cells * cell_m
        try:
            self._check_frame(msg.header.frame_id, what)
            if side < need:
                raise nav.NavConfigError(f"{what} covers {side:.2f} m, less than the view's {cells} cells of "
                                         f"{cell_m} m ({need:.2f} m)")
            nav.costmap_to_observation(msg, view_cells=cells, cell_size_m=cell_m)  # its size checks
        except ValueError as exc:  # NavConfigError among them
            self.reject(kind, exc)
            return False
        latest = Latest(msg, now, wire.key_of(msg.header.stamp))
        if kind == "costmap":
            self.costmap = latest
        else:
            self.global_costmap = latest
        return True

    def take_places(self, msg) -> bool:
        """A ``geometry_msgs/PoseArray`` of the places."""
        try:
            self.places = nav.SubgoalTable.from_pose_array(msg, self.num_subgoals, self.topics["places"])
        except nav.NavConfigError as exc:
            self.reject("places", exc)
            return False
        self.places_stamp = wire.key_of(msg.header.stamp)
        return True

    def missing(self, now: int, stale_ns: int, since_stamp: int = 0) -> str:
        """Why no step can be built at ``now`` from a pose and a costmap that arrived within
        ``stale_ns`` and are stamped at or after ``since_stamp`` ('' if it can)."""
        for what, latest in (("pose", self.pose), ("costmap", self.costmap)):
            topic = self.topics[what]
            if latest.arrived_ns < 0:
                return f"no {what} on {topic} yet"
            if now - latest.arrived_ns > stale_ns:
                return f"the {what} on {topic} is {(now - latest.arrived_ns) / 1e9:.1f} s old (stale_after_s " \
                       f"{stale_ns / 1e9:g})"
            if latest.stamp_ns < since_stamp:
                return f"a {what} on {topic} stamped after the places"
        return ""

    @property
    def places_costmap(self):
        """The OccupancyGrid the places' images are drawn from: the global costmap if there is one."""
        return self.costmap.value if self.global_costmap.value is None else self.global_costmap.value

    def on_lethal(self, lethal: int) -> bool:
        """The robot's costmap cell has a cost of at least ``lethal``."""
        info, (x, y, _) = self.costmap.value.info, self.pose.value
        col = math.floor((x - info.origin.position.x) / info.resolution)
        row = math.floor((y - info.origin.position.y) / info.resolution)
        return 0 <= col < info.width and 0 <= row < info.height and \
            self.costmap.value.data[row * info.width + col] >= lethal
