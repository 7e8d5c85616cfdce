"""Nav2 tables and conversions: subgoal index -> goal pose, action index -> velocity, local
costmap -> observation, a robot's pose from its messages.

Messages are rclpy's (``geometry_msgs``, ``nav_msgs``). Units: metres, radians, m/s, rad/s.
Observations are ``(44, 44, 3) uint8`` RGB images in the gridworld's colours (see
``docs/nav2.md``). Stamps are ``(sec, nanosec)`` or integer nanoseconds (a step key).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Twist, TwistStamped, Vector3
from std_msgs.msg import Header

from hdrqn_ros.envs.gridworld import AGENT, FREE, GOAL0, GOAL_NAMES, OUTSIDE, PALETTE, WALL
from hdrqn_ros.protocol.arrays import as_array
from hdrqn_ros.robot.motion_primitives import Motion, motion_of
from hdrqn_ros.robot.transforms import quaternion_yaw
from hdrqn_ros.yaml_files import read_mapping

POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TWIST = "geometry_msgs/msg/Twist"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
POSE_TYPES = {"odometry": "nav_msgs/msg/Odometry", "pose": POSE_STAMPED,
              "pose_with_covariance": "geometry_msgs/msg/PoseWithCovarianceStamped"}
"""The robot pose messages a robot-side node reads (``pose_type``): ``/odom``, a
``PoseStamped``, ``/amcl_pose``."""
LETHAL = 100
"""Default threshold: OccupancyGrid cost (0..100) at or above it is drawn as a wall: Nav2's
lethal obstacles only (its inflation, 1-98, and inscribed cells, 99, lie around walls in cells
the robot's centre may reach, as the simulator's free cells beside a wall)."""
OBSERVATION_UP = ("north_up", "heading_up")
"""An action table's ``observation``: how the agent's image is turned (what a move's direction means)."""
_POSE_KEYS = {"x", "y", "yaw"}
_TWIST_KEYS = {f"{kind}_{axis}" for kind in ("linear", "angular") for axis in "xyz"}


class NavConfigError(ValueError):
    """A table (the message names its file) or a costmap message that cannot be used."""


def _read(path, allowed: set[str], required: set[str]) -> dict:
    path = Path(path)
    data = read_mapping(path, NavConfigError)
    if unknown := set(data) - allowed:
        raise NavConfigError(f"{path}: unknown key(s) {sorted(map(str, unknown))}; allowed: {sorted(allowed)}")
    if missing := required - set(data):
        raise NavConfigError(f"{path}: missing key(s) {sorted(missing)}")
    if "frame_id" in data and (not isinstance(data["frame_id"], str) or not data["frame_id"]):
        raise NavConfigError(f"{path}: frame_id must be a non-empty string, got {data['frame_id']!r}")
    return data


def _entries(path, data: dict, key: str, allowed: set[str], required: set[str], count: int | None) -> list[dict]:
    """The list ``data[key]`` checked entry by entry: float values, name optional."""
    items = data[key]
    if not isinstance(items, list) or not items:
        raise NavConfigError(f"{path}: {key} must be a non-empty list, got {items!r}")
    if count is not None and len(items) != count:
        raise NavConfigError(f"{path}: {key} has {len(items)} entries but the agent has {count} (one per index)")
    out = []
    for i, item in enumerate(items):
        where = f"{path}: {key}[{i}]"
        if not isinstance(item, dict):
            raise NavConfigError(f"{where} must be a mapping like {{{', '.join(sorted(required or allowed))}: ...}}")
        if unknown := set(item) - allowed - {"name"}:
            raise NavConfigError(f"{where}: unknown key(s) {sorted(map(str, unknown))}; allowed: {sorted(allowed)}")
        if missing := required - set(item):
            raise NavConfigError(f"{where}: missing key(s) {sorted(missing)}")
        entry = {}
        for field in allowed & set(item):
            value = item[field]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise NavConfigError(f"{where}: {field} must be a finite number, got {value!r}")
            entry[field] = float(value)
        out.append(entry)
    return out


def _index(i, n: int, what: str) -> int:
    if isinstance(i, (bool, np.bool_)) or not isinstance(i, (int, np.integer)) or not 0 <= i < n:
        raise IndexError(f"{what} must be an integer in [0, {n}), got {i!r}")
    return int(i)


def _time(stamp) -> Time:
    """``builtin_interfaces/Time`` from ``(sec, nanosec)`` or integer nanoseconds."""
    sec, nsec = divmod(int(stamp), 10**9) if isinstance(stamp, (int, np.integer)) else stamp
    return Time(sec=int(sec), nanosec=int(nsec))


def yaw_of(q) -> float:
    """Rotation about z (rad) of a ``geometry_msgs/Quaternion``."""
    return quaternion_yaw(q.x, q.y, q.z, q.w)


def robot_pose(msg) -> tuple[float, float, float]:
    """``(x, y, yaw)`` (m, rad) of any :data:`POSE_TYPES` message; :class:`NavConfigError`
    for a non-finite pose."""
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    values = (float(pose.position.x), float(pose.position.y), yaw_of(pose.orientation))
    if not all(math.isfinite(v) for v in values):
        raise NavConfigError(f"pose is not finite: x, y, yaw = {values}")
    return values


class SubgoalTable:
    """One goal pose ``(x, y, yaw)`` in ``frame_id`` per subgoal index (for Nav2's ``goal_pose``)."""

    def __init__(self, poses: list[tuple[float, float, float]], frame_id: str = "map", source: str = "<table>"):
        self.poses, self.frame_id, self.source = [tuple(map(float, p)) for p in poses], frame_id, source

    @classmethod
    def load(cls, path, num_subgoals: int | None = None) -> "SubgoalTable":
        data = _read(path, {"frame_id", "subgoals"}, {"subgoals"})
        entries = _entries(path, data, "subgoals", _POSE_KEYS, {"x", "y"}, num_subgoals)
        return cls([(e["x"], e["y"], e.get("yaw", 0.0)) for e in entries], data.get("frame_id", "map"), str(path))

    @classmethod
    def from_pose_array(cls, msg, num_subgoals: int, source: str) -> "SubgoalTable":
        """The table a ``geometry_msgs/PoseArray`` holds (one pose per subgoal, in its
        header's frame), e.g. a robot's places published on a latched topic."""
        if len(msg.poses) != num_subgoals:
            raise NavConfigError(f"{source}: {len(msg.poses)} poses but the agent has {num_subgoals} subgoals")
        poses = [(float(p.position.x), float(p.position.y), yaw_of(p.orientation)) for p in msg.poses]
        if not all(math.isfinite(v) for pose in poses for v in pose):
            raise NavConfigError(f"{source}: a pose is not finite: {poses}")
        if not msg.header.frame_id:
            raise NavConfigError(f"{source}: header.frame_id is empty")
        return cls(poses, msg.header.frame_id, source)

    def __len__(self) -> int:
        return len(self.poses)

    def pose_msg(self, subgoal, stamp=(0, 0)) -> PoseStamped:
        """``geometry_msgs/PoseStamped`` of subgoal ``subgoal`` (yaw about z -> quaternion z, w)."""
        x, y, yaw = self.poses[_index(subgoal, len(self), "subgoal")]
        return PoseStamped(header=Header(stamp=_time(stamp), frame_id=self.frame_id),
                           pose=Pose(position=Point(x=x, y=y, z=0.0),
                                     orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))))


class ActionTable:
    """One velocity command per action index; ``stamped`` selects TwistStamped over Twist.
    ``observation``: whether the agent's image is ``north_up`` (a move's direction is the
    frame's, whatever the robot's yaw) or ``heading_up`` (the robot's heading); by default
    heading-up when an action turns, else north-up. ``holonomic``: an action moves sideways."""

    def __init__(self, commands: list[dict[str, float]], stamped: bool = False, frame_id: str = "base_link",
                 source: str = "<table>", observation: str | None = None):
        self.commands, self.stamped, self.frame_id, self.source = commands, bool(stamped), frame_id, source
        if observation is None:
            observation = "heading_up" if any(c.get("angular_z", 0.0) for c in commands) else "north_up"
        if observation not in OBSERVATION_UP:
            raise NavConfigError(f"{source}: observation must be one of {list(OBSERVATION_UP)}, got {observation!r}")
        self.heading_up = observation == "heading_up"
        self.holonomic = any(c.get("linear_y", 0.0) for c in commands)

    @classmethod
    def load(cls, path, num_actions: int) -> "ActionTable":
        data = _read(path, {"stamped", "frame_id", "observation", "actions"}, {"actions"})
        stamped = data.get("stamped", False)
        if not isinstance(stamped, bool):
            raise NavConfigError(f"{path}: stamped must be true or false, got {stamped!r}")
        entries = _entries(path, data, "actions", _TWIST_KEYS, set(), num_actions)
        return cls(entries, stamped, data.get("frame_id", "base_link"), str(path), data.get("observation"))

    def __len__(self) -> int:
        return len(self.commands)

    @property
    def type_name(self) -> str:
        return TWIST_STAMPED if self.stamped else TWIST

    @property
    def msg_type(self) -> type:
        """The message class of the commands: ``Twist`` or ``TwistStamped``."""
        return TwistStamped if self.stamped else Twist

    def moves(self, action: int) -> bool:
        """Whether action ``action``'s command is not the zero one."""
        return any(self.commands[_index(action, len(self), "action")].values())

    def motion(self, action: int) -> Motion:
        """Action ``action``'s motion primitive (a move of one cell, a 90 degree turn, or stay);
        NavConfigError for a command that both moves and turns."""
        cmd = self.commands[_index(action, len(self), "action")]
        try:
            return motion_of(cmd.get("linear_x", 0.0), cmd.get("linear_y", 0.0), cmd.get("angular_z", 0.0))
        except ValueError as exc:
            raise NavConfigError(f"{self.source}: action {action}: {exc}") from exc

    def velocity_msg(self, vx: float, vy: float, wz: float, stamp=(0, 0)) -> Twist | TwistStamped:
        """The command body-frame ``(vx, vy, wz)`` (m/s, m/s, rad/s), stamped ``stamp`` if the table is."""
        return self._msg({"linear_x": vx, "linear_y": vy, "angular_z": wz}, stamp)

    def _msg(self, cmd: dict[str, float], stamp) -> Twist | TwistStamped:
        linear, angular = (Vector3(**{axis: cmd.get(f"{kind}_{axis}", 0.0) for axis in "xyz"})
                           for kind in ("linear", "angular"))
        twist = Twist(linear=linear, angular=angular)
        if not self.stamped:
            return twist
        return TwistStamped(header=Header(stamp=_time(stamp), frame_id=self.frame_id), twist=twist)

    def twist_msg(self, action, stamp=(0, 0)) -> Twist | TwistStamped:
        """Command of action ``action``; ``stamp`` is used only when stamped."""
        return self._msg(self.commands[_index(action, len(self), "action")], stamp)

    def stop_msg(self, stamp=(0, 0)) -> Twist | TwistStamped:
        """The all-zero command (publish it on shutdown)."""
        return self._msg({}, stamp)


def costmap_to_observation(msg, robot_xy=None, view_cells: int = 5, size: int = 44, *, robot_yaw=None,
                           cell_size_m: float | None = None, lethal: int = LETHAL, goals_xy=(), agent_xy=None,
                           unknown: str = "wall") -> np.ndarray:
    """``(size, size, 3) uint8``: a gridworld-style observation of an OccupancyGrid.

    A ``view_cells`` x ``view_cells`` window of simulator cells of side ``cell_size_m``
    (default 5 x resolution) centred on ``robot_xy`` (costmap frame, m; default: the centre
    of cell ``(width // 2, height // 2)``, where a rolling local costmap keeps the robot).
    Each cell is sampled at ``n x n`` points, ``n = ceil(cell_size_m / resolution)``; it is
    a wall if any sample has cost >= ``lethal``, is unknown (-1) or lies outside the grid,
    else free (max aggregation); a view turned against the grid (not by a multiple of 90
    degrees: a costmap in ``odom`` under a turned ``map -> odom``) counts only the samples at
    least half a grid cell's diagonal inside the cell, since the grid's cells straddle its
    border. The centre cell shows the agent. ``robot_yaw=None``: image
    up = costmap +y (north-up, like the simulator's allocentric moves); a yaw (rad): image
    up = the robot's heading (egocentric). ``goals_xy``: optional ``(x, y)`` of subgoal
    ``g = 0, 1, ...`` (costmap frame; ``None``: not drawn, e.g. collected), drawn in goal
    ``g``'s colour when inside the window. ``agent_xy``: where the agent is drawn (default
    the centre cell; elsewhere only when inside the window: a window centred on a subgoal).
    ``unknown``: how a cell with unknown samples (-1, or outside the grid) and no lethal one
    is drawn: ``"wall"`` (grey, the safe default) or ``"outside"`` (black, as the simulator
    draws cells beyond its map). The costmap origin's orientation is assumed identity (as
    Nav2 publishes it).
    Upscaled by nearest neighbour exactly like the simulator.
    """
    info = msg.info
    w, h, res = int(info.width), int(info.height), float(info.resolution)
    data = as_array(msg.data, np.int8)
    if not (math.isfinite(res) and res > 0):
        raise NavConfigError(f"costmap resolution must be positive, got {res}")
    if w * h == 0 or w * h != data.size:
        raise NavConfigError(f"costmap is {w}x{h} cells but has {data.size} data values")
    odd = isinstance(view_cells, (int, np.integer)) and not isinstance(view_cells, bool) and view_cells % 2 == 1
    if not odd or view_cells < 1:
        raise ValueError(f"view_cells must be a positive odd integer, got {view_cells!r}")
    if not 1 <= lethal <= 100:
        raise ValueError(f"lethal must be in [1, 100], got {lethal!r}")
    cell = 5 * res if cell_size_m is None else float(cell_size_m)
    if not (math.isfinite(cell) and cell > 0):
        raise ValueError(f"cell_size_m must be positive, got {cell_size_m!r}")
    ox, oy = float(info.origin.position.x), float(info.origin.position.y)
    if not (math.isfinite(ox) and math.isfinite(oy)):
        raise NavConfigError(f"costmap origin must be finite, got ({ox}, {oy})")
    rx, ry = (ox + (w // 2 + 0.5) * res, oy + (h // 2 + 0.5) * res) if robot_xy is None else map(float, robot_xy)
    fx, fy = (0.0, 1.0) if robot_yaw is None else (math.cos(robot_yaw), math.sin(robot_yaw))  # image up
    per_cell = max(1, math.ceil(cell / res - 1e-6))
    samples = view_cells * per_cell
    off = (np.arange(samples) + 0.5 - samples / 2) * (cell / per_cell)  # sample offsets, m; rows: top -> bottom = -up
    up, right = -off[:, None], off[None, :]
    px, py = rx + up * fx + right * fy, ry + up * fy - right * fx  # right = heading rotated by -90 deg
    # samples on a cell border go to the upper cell (the 1e-6 absorbs rounding)
    col, row = (np.floor((p - o) / res + 1e-6).astype(np.int64) for p, o in ((px, ox), (py, oy)))
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    cost = np.where(inside, data.reshape(h, w)[row.clip(0, h - 1), col.clip(0, w - 1)], -1).astype(np.int16)
    if unknown not in ("wall", "outside"):
        raise ValueError(f"unknown must be 'wall' or 'outside', got {unknown!r}")

    # a grid turned against the view (not by a multiple of 90 degrees) puts an obstacle up to
    # half a grid cell's diagonal across a cell border: only samples further in than that count
    along = (np.arange(per_cell) + 0.5) * (cell / per_cell)  # each sample's offset into its cell, m
    inset = np.minimum(along, cell - along)
    turned = robot_yaw is not None and abs(math.remainder(robot_yaw, math.pi / 2)) > 1e-9
    trusted = inset >= min(res / math.sqrt(2), inset.max()) if turned else np.ones(per_cell, bool)

    def any_in_cell(mask: np.ndarray) -> np.ndarray:
        cells = mask.reshape(view_cells, per_cell, view_cells, per_cell)
        return cells[:, trusted][:, :, :, trusted].any(axis=(1, 3))

    lethal_cells, unknown_cells = any_in_cell(cost >= lethal), any_in_cell(cost < 0)
    codes = np.where(lethal_cells, WALL, np.where(unknown_cells, WALL if unknown == "wall" else OUTSIDE, FREE))
    if len(goals_xy) > len(GOAL_NAMES):
        raise ValueError(f"at most {len(GOAL_NAMES)} goals can be drawn, got {len(goals_xy)}")

    def window_cell(x: float, y: float) -> tuple[int, int] | None:
        """(row, col) of the window cell holding point (x, y), as for the samples above."""
        dx, dy = float(x) - rx, float(y) - ry
        row = math.floor(view_cells / 2 - (dx * fx + dy * fy) / cell)  # up = d . heading
        col = math.floor(view_cells / 2 + (dx * fy - dy * fx) / cell)  # right = d . (fy, -fx)
        return (row, col) if 0 <= row < view_cells and 0 <= col < view_cells else None

    for goal, goal_xy in enumerate(goals_xy):
        if goal_xy is not None and (at := window_cell(*goal_xy)) is not None:
            codes[at] = GOAL0 + goal
    agent_at = (view_cells // 2, view_cells // 2) if agent_xy is None else window_cell(*agent_xy)
    if agent_at is not None:
        codes[agent_at] = AGENT
    counts = np.bincount((np.arange(size) * view_cells) // size, minlength=view_cells)  # as the simulator
    return np.repeat(np.repeat(PALETTE[codes], counts, axis=0), counts, axis=1)
