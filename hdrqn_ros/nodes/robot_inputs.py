"""What the robot-side environment knows of the robot: its pose, costmaps and places, and the frames between them.

The pose comes from tf (``global_frame`` <- ``robot_base_frame``, REP 105's ``map <- base_link``)
or from a pose topic; each costmap is kept in its own frame, the last full grid with every
``<costmap>_updates`` (``map_msgs/OccupancyGridUpdate``) applied on top, as Nav2 sends them
with ``always_send_full_costmap: false``; the places in theirs. :class:`Frames` maps between
frames (identity within one, tf between two). Each input is checked as it arrives and
refused, with a throttled warning, when it cannot be used; :meth:`RobotInputs.missing` and
:meth:`RobotInputs.pose_at` say why no step can be built yet (a :class:`Waiting`), naming
what is missing and who would publish it. Times are ROS time in ns; the messages' fields
are read as they are (no ROS import).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from hdrqn_ros.nodes import nav
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.arrays import as_array
from hdrqn_ros.robot.transforms import ExtrapolationError, Transform, TransformError
from hdrqn_ros.throttle import Throttle

TF_PUBLISHERS = "on /tf and /tf_static: REP 105's map -> odom comes from AMCL (or another localiser), " \
                "odom -> base_link from the robot's odometry, sensor frames from robot_state_publisher"
"""Who publishes the transforms a wait for one names."""
AMCL_HINT = "AMCL publishes /amcl_pose only after the robot moved update_min_d (0.25 m) or turned update_min_a " \
            "(0.2 rad): read the pose from tf instead (pose_topic '')"
COSTMAP_PUBLISHER = "Nav2's costmap (controller_server's local_costmap) publishes it"


class Waiting(Exception):
    """Why a step cannot be built now (what is missing, who would publish it)."""


@dataclass
class Latest:
    """The latest accepted message of an input: its content, the ROS time it arrived and its
    header stamp (ns; -1: nothing yet)."""

    value: Any = None
    arrived_ns: int = -1
    stamp_ns: int = -1


@dataclass(frozen=True)
class Grid:
    """An OccupancyGrid as the node uses it: ``frame_id``, ``stamp_ns``, ``info``
    (``nav_msgs/MapMetaData``) and ``data`` ``(height * width,) int8`` (row-major from the origin)."""

    frame_id: str
    stamp_ns: int
    info: Any
    data: np.ndarray


@dataclass(frozen=True)
class RobotPose:
    """The robot at a step: ``x``, ``y`` (m), ``yaw`` (rad) in ``frame`` at ``stamp_ns``;
    ``latest``: the newest pose, taken after the wait for one at the step's time timed out."""

    x: float
    y: float
    yaw: float
    frame: str
    stamp_ns: int
    latest: bool = False


Lookup = Callable[[str, str, "int | None"], Transform]
"""``lookup(target, source, stamp_ns or None)``: the transform mapping points in ``source``
into ``target`` (``None``: the latest); raises :class:`~hdrqn_ros.robot.transforms.TransformError`."""


class Frames:
    """Transforms between the inputs' frames: the identity within one frame, tf's otherwise
    (``lookup`` ``None``: no tf here, ``unavailable`` says why)."""

    def __init__(self, lookup: Lookup | None, unavailable: str = ""):
        self.lookup, self.unavailable = lookup, unavailable
        self.fell_back = 0  # transforms taken at the latest time because the asked one was not (yet) there

    def transform(self, target: str, source: str, stamp_ns: int | None, what: str) -> Transform:
        """``target`` <- ``source`` at ``stamp_ns``, or at the latest time when tf has none at
        ``stamp_ns``; :class:`Waiting` naming the frames (and ``what`` needs them) otherwise."""
        if target == source:
            return Transform.identity()
        if self.lookup is None:
            raise Waiting(f"{what} needs the transform {target} <- {source}, and there is no tf here: "
                          f"{self.unavailable}")
        try:
            return self.lookup(target, source, stamp_ns)
        except ExtrapolationError:
            self.fell_back += 1
            try:
                return self.lookup(target, source, None)
            except TransformError as exc:
                raise Waiting(f"{what}: no transform {target} <- {source} ({exc}); {TF_PUBLISHERS}") from None
        except TransformError as exc:
            raise Waiting(f"{what}: no transform {target} <- {source} ({exc}); {TF_PUBLISHERS}") from None


class RobotInputs:
    """The robot's latest ``pose`` from a topic (``(x, y, yaw)``: m, rad, in ``pose_frame``),
    ``costmap`` and ``global_costmap`` (:class:`Grid` s) and ``places`` (a
    :class:`~hdrqn_ros.nodes.nav.SubgoalTable`, ``None`` until heard). ``topics``: each
    input's resolved topic name by kind (pose, costmap, global, places, their updates as
    ``costmap_updates``/``global_updates``, and the protocol inputs the node checks itself);
    ``frames``: the transforms between frames; ``pose_frames``: ``(global_frame,
    robot_base_frame)`` when the pose comes from tf, ``None`` for a pose topic."""

    def __init__(self, logger: logging.Logger, topics: dict[str, str], places: nav.SubgoalTable | None,
                 num_subgoals: int, view_cells: int, cell_size_m: float, frames: Frames,
                 pose_frames: tuple[str, str] | None = None, amcl_like: bool = False):
        self.topics, self.num_subgoals = topics, num_subgoals
        self.view_cells, self.cell_size_m = view_cells, cell_size_m
        self.frames, self.pose_frames, self.amcl_like = frames, pose_frames, amcl_like
        self.rejected = {kind: Throttle(logger, f"rejected a message on {topic}") for kind, topic in topics.items()}
        self.refused: dict[str, str] = {}  # kind -> why its latest message was refused
        self.places, self.places_stamp = places, 0  # the places' header stamp (a table's: 0)
        self.pose, self.pose_frame = Latest(), ""
        self.costmap, self.global_costmap = Latest(), Latest()

    def reject(self, kind: str, why: object) -> None:
        self.refused[kind] = str(why)
        self.rejected[kind].warn(why)

    @property
    def rejections(self) -> int:
        return sum(throttle.count for throttle in self.rejected.values())

    # -- messages ------------------------------------------------------------------------------------
    def take_pose(self, msg, now: int) -> bool:
        """A pose message (any of :data:`~hdrqn_ros.nodes.nav.POSE_TYPES`): whether it was taken."""
        try:
            pose = nav.robot_pose(msg)
            if not msg.header.frame_id:
                raise nav.NavConfigError("the pose's header.frame_id is empty")
        except nav.NavConfigError as exc:
            self.reject("pose", exc)
            return False
        self.pose, self.pose_frame = Latest(pose, now, wire.key_of(msg.header.stamp)), msg.header.frame_id
        self.refused.pop("pose", None)
        return True

    def take_costmap(self, msg, now: int, kind: str = "costmap") -> bool:
        """An OccupancyGrid for the observation (``kind`` costmap) or the places' images (global)."""
        what = "the costmap" if kind == "costmap" else "the global costmap"
        info, cells, cell_m = msg.info, self.view_cells, self.cell_size_m
        side, need = min(info.width, info.height) * info.resolution, cells * cell_m
        try:
            if not msg.header.frame_id:
                raise nav.NavConfigError(f"{what}'s header.frame_id is empty")
            if side < need:
                raise nav.NavConfigError(f"{what} covers {side:.2f} m, less than the view's {cells} cells of "
                                         f"{cell_m} m ({need:.2f} m)")
            nav.costmap_to_observation(msg, view_cells=cells, cell_size_m=cell_m)  # its size checks
        except ValueError as exc:  # NavConfigError among them
            self.reject(kind, exc)
            return False
        grid = Grid(msg.header.frame_id, wire.key_of(msg.header.stamp), info, as_array(msg.data, np.int8).copy())
        self._keep(kind, Latest(grid, now, grid.stamp_ns))
        return True

    def take_update(self, msg, now: int, kind: str = "costmap") -> bool:
        """A ``map_msgs/OccupancyGridUpdate`` on ``kind``'s ``_updates`` topic, applied on top of
        the last grid: its ``x``, ``y``, ``width``, ``height`` window (cells) gets the update's
        data; frame and stamp come from the update's header."""
        topic, latest = self.topics[kind], self._latest(kind)
        grid: Grid | None = latest.value
        x, y, w, h = int(msg.x), int(msg.y), int(msg.width), int(msg.height)
        data = as_array(msg.data, np.int8)
        stamp = wire.key_of(msg.header.stamp)
        why = ""
        if grid is None:
            why = f"no full grid on {topic} yet to apply it to (Nav2 sends one when the costmap starts and when " \
                  f"its size or origin changes)"
        elif msg.header.frame_id != grid.frame_id:
            why = f"the update is in frame {msg.header.frame_id!r}, the grid on {topic} in {grid.frame_id!r}"
        elif x < 0 or y < 0 or x + w > grid.info.width or y + h > grid.info.height:
            why = f"its window x {x}, y {y}, {w} x {h} cells is outside the {grid.info.width} x " \
                  f"{grid.info.height} grid on {topic}"
        elif data.size != w * h:
            why = f"its window is {w} x {h} cells but it has {data.size} data values"
        elif stamp < grid.stamp_ns:
            why = f"it is stamped {(grid.stamp_ns - stamp) / 1e9:.3f} s before the grid on {topic}"
        if why:
            self.reject(f"{kind}_updates", f"update refused: {why}")
            return False
        cells = grid.data.reshape(grid.info.height, grid.info.width).copy()
        cells[y:y + h, x:x + w] = data.reshape(h, w)
        self._keep(kind, Latest(Grid(grid.frame_id, stamp, grid.info, cells.reshape(-1)), now, stamp))
        return True

    def _latest(self, kind: str) -> Latest:
        return self.costmap if kind == "costmap" else self.global_costmap

    def _keep(self, kind: str, latest: Latest) -> None:
        if kind == "costmap":
            self.costmap = latest
        else:
            self.global_costmap = latest
        self.refused.pop(kind, None)

    def take_places(self, msg) -> bool:
        """A ``geometry_msgs/PoseArray`` of the places."""
        try:
            self.places = nav.SubgoalTable.from_pose_array(msg, self.num_subgoals, self.topics["places"])
        except nav.NavConfigError as exc:
            self.reject("places", exc)
            return False
        self.places_stamp = wire.key_of(msg.header.stamp)
        self.refused.pop("places", None)
        return True

    # -- what a step needs ---------------------------------------------------------------------------
    def missing(self, now: int, stale_ns: int, since_stamp: int = 0) -> str:
        """Why no step can be built at ``now`` from a costmap (and a topic's pose) that arrived
        within ``stale_ns`` and are stamped at or after ``since_stamp`` ('' if it can)."""
        kinds = ("costmap",) if self.pose_frames else ("pose", "costmap")
        return next((why for kind in kinds if (why := self._input_missing(kind, now, stale_ns, since_stamp))), "")

    def _input_missing(self, what: str, now: int, stale_ns: int, since_stamp: int = 0) -> str:
        latest, topic = (self.costmap if what == "costmap" else self.pose), self.topics[what]
        if latest.arrived_ns < 0:
            if what in self.refused:
                return f"every {what} on {topic} so far was refused, the last because: {self.refused[what]}"
            publisher = COSTMAP_PUBLISHER if what == "costmap" else \
                (AMCL_HINT if self.amcl_like else "is its publisher running?")
            return f"no {what} on {topic} yet ({publisher})"
        if now - latest.arrived_ns > stale_ns:
            age = f"the {what} on {topic} is {(now - latest.arrived_ns) / 1e9:.1f} s old (stale_after_s " \
                  f"{stale_ns / 1e9:g})"
            if what == "costmap":
                return f"{age}: no grid and no update on {self.topics['costmap_updates']} since (Nav2 with " \
                       f"always_send_full_costmap: false sends full grids only when the window moves, " \
                       f"otherwise updates there; is the costmap published?)"
            return f"{age}: {AMCL_HINT}" if self.amcl_like else f"{age}: is its publisher running?"
        if latest.stamp_ns < since_stamp:
            return f"a {what} on {topic} stamped after the places"
        return ""

    def pose_at(self, at_ns: int, now: int, stale_ns: int, waited_s: float, timeout_s: float) -> RobotPose:
        """The robot's pose at ``at_ns`` (a step's time): from tf, or the topic's latest pose
        stamped at or after it. After ``timeout_s`` (wall seconds ``waited_s`` so far) without
        one, the latest pose, unless older than ``stale_ns``. :class:`Waiting` while there is none."""
        if self.pose_frames is None:
            return self._topic_pose(at_ns, now, stale_ns, waited_s, timeout_s)
        target, source = self.pose_frames
        where = f"the robot pose: the transform {target} <- {source}"
        if self.frames.lookup is None:
            raise Waiting(f"{where} needs tf, and there is no tf here: {self.frames.unavailable}")
        try:
            pose = self.frames.lookup(target, source, at_ns)
            return RobotPose(*pose.translation[:2], pose.yaw, target, at_ns)
        except ExtrapolationError as exc:
            newest = getattr(exc, "latest_ns", at_ns)
            if newest < at_ns and at_ns - newest > stale_ns:
                raise Waiting(f"{where} is {(at_ns - newest) / 1e9:.1f} s old at the step's time (stale_after_s "
                              f"{stale_ns / 1e9:g}): {exc}; {TF_PUBLISHERS}") from None
            if waited_s < timeout_s:
                raise Waiting(f"{where} at the step's time ({exc})") from None
        except TransformError as exc:
            raise Waiting(f"{where} is not in the tree: {exc}; {TF_PUBLISHERS}") from None
        try:
            pose = self.frames.lookup(target, source, None)
        except TransformError as exc:
            raise Waiting(f"{where}: {exc}; {TF_PUBLISHERS}") from None
        return RobotPose(*pose.translation[:2], pose.yaw, target, at_ns, latest=True)

    def _topic_pose(self, at_ns: int, now: int, stale_ns: int, waited_s: float, timeout_s: float) -> RobotPose:
        if why := self._input_missing("pose", now, stale_ns):
            raise Waiting(why)
        pose = self.pose
        if pose.stamp_ns < at_ns and waited_s < timeout_s:
            raise Waiting(f"a pose on {self.topics['pose']} stamped at or after the step's time (the latest is "
                          f"{(at_ns - pose.stamp_ns) / 1e9:.2f} s older)" + (f"; {AMCL_HINT}" if self.amcl_like else ""))
        return RobotPose(*pose.value, self.pose_frame, pose.stamp_ns, latest=pose.stamp_ns < at_ns)

    @property
    def places_costmap(self) -> Grid:
        """The grid the places' images are drawn from: the global costmap if there is one."""
        return self.costmap.value if self.global_costmap.value is None else self.global_costmap.value

    def on_lethal(self, grid: Grid, xy, lethal: int) -> bool:
        """The costmap cell at ``xy`` (m, the grid's frame) has a cost of at least ``lethal``."""
        info = grid.info
        col = math.floor((xy[0] - info.origin.position.x) / info.resolution)
        row = math.floor((xy[1] - info.origin.position.y) / info.resolution)
        return 0 <= col < info.width and 0 <= row < info.height and grid.data[row * info.width + col] >= lethal
