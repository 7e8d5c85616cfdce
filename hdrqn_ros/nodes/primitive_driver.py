"""The sub-controller's actions as exact motion primitives (``drive: primitives``).

Each action becomes a closed-loop :class:`~hdrqn_ros.robot.motion_primitives.Primitive`:
one ``cell_size_m`` along the action's direction (north-up tables: the observation frame's
axis, whatever the robot's yaw; heading-up: the robot's heading) or exactly 90 degrees,
measured from tf (the observation's frame <- ``robot_base_frame``, the latest transform) or
from odometry (``odom_topic``, in its own frame). Velocity commands stream on ``cmd_vel`` at
``control_rate_hz`` of ROS time (so a 1 s deadman never cuts them), then the zero command
when the primitive completes, is blocked or times out after ``primitive_timeout_s``: keep
that under the robot environment's ``step_period`` and the next step's observation is
taken after the primitive ended. Each outcome is logged and counted on ``/diagnostics``.
While there is no pose (no tf, no odometry yet) an action waits for one, the robot standing
still, with a throttled warning and a WARN on ``/diagnostics``; one that gets none within
``primitive_timeout_s`` ends as timed out.
"""
from __future__ import annotations

from collections import Counter

from nav_msgs.msg import Odometry

from hdrqn_ros.nodes import nav
from hdrqn_ros.nodes.controller_node import ControllerNode
from hdrqn_ros.nodes.nav import ActionTable, NavConfigError
from hdrqn_ros.nodes.nav_adapters import VelocityDriver
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import Param
from hdrqn_ros.nodes.qos import DEFAULT_QOS
from hdrqn_ros.nodes.ros_messages import bounded_subscription
from hdrqn_ros.robot.motion_primitives import OUTCOMES, TIMED_OUT, Lattice, Limits, Primitive
from hdrqn_ros.robot.transforms import TransformError
from hdrqn_ros.throttle import Throttle

PRIMITIVE_PARAMETERS = {
    "drive": Param("primitives", "how an action drives the robot: a closed-loop primitive (one cell or 90 degrees, "
                                 "measured from pose_source), or one command held for the step (commands)",
                   choices=("primitives", "commands")),
    "pose_source": Param("tf", "primitives: the robot's pose from tf (primitive_frame <- robot_base_frame) or "
                               "odometry (odom_topic, in its own frame: north-up moves follow its axes)",
                         choices=("tf", "odometry")),
    "primitive_frame": Param("", "primitives from tf: the frame a move's direction is in ('': the observation's "
                                 "frame_id)"),
    "robot_base_frame": Param("base_link", "primitives from tf: the robot's frame"),
    "odom_topic": Param("odom", "primitives from odometry: nav_msgs/Odometry"),
    "cell_size_m": Param(0.25, "primitives: metres of one move (the observation's cell)", positive=True),
    "control_rate_hz": Param(20.0, "primitives: velocity commands per second of ROS time", low=10.0, high=1000.0),
    "primitive_timeout_s": Param(2.0, "primitives: ROS seconds before a primitive ends as timed out (under the "
                                      "robot environment's step_period)", positive=True),
    "blocked_after_s": Param(0.5, "primitives: ROS seconds without progress before one ends as blocked",
                             positive=True),
    "linear_gain": Param(3.0, "primitives: m/s per m of remaining distance", positive=True),
    "angular_gain": Param(4.0, "primitives: rad/s per rad of remaining turn", positive=True),
    "max_linear_speed": Param(0.3, "primitives: m/s at most (and 0.03 m/s at least while moving)", positive=True),
    "max_angular_speed": Param(1.5, "primitives: rad/s at most (and 0.1 rad/s at least while turning)",
                               positive=True),
    "position_tolerance_m": Param(0.01, "primitives: a move is complete this close to its cell", positive=True),
    "angle_tolerance_rad": Param(0.02, "primitives: a turn is complete this close to its 90 degrees", positive=True),
}
"""How the sub-controller drives (:class:`PrimitiveDriver`, or one command: ``VelocityDriver``)."""


def limits_of(params: dict) -> Limits:
    """The controller's :class:`Limits` from the node's parameters (NavConfigError if they do not go together)."""
    try:
        return Limits(linear_gain=params["linear_gain"], angular_gain=params["angular_gain"],
                      max_linear=params["max_linear_speed"], max_angular=params["max_angular_speed"],
                      min_linear=min(0.03, params["max_linear_speed"]),
                      min_angular=min(0.1, params["max_angular_speed"]),
                      position_tolerance=params["position_tolerance_m"], angle_tolerance=params["angle_tolerance_rad"],
                      blocked_after_s=params["blocked_after_s"], timeout_s=params["primitive_timeout_s"])
    except ValueError as exc:
        raise NavConfigError(str(exc)) from exc


class PrimitiveDriver(VelocityDriver):
    """Drives each action as a motion primitive; the zero command at the episode's end, when the
    node stops, and when the observation goes stale, as :class:`VelocityDriver`."""

    def __init__(self, node: ControllerNode, table: ActionTable):
        params = node.params
        for action in range(len(table)):
            table.motion(action)  # NavConfigError naming a command that both moves and turns
        self.limits = limits_of(params)
        super().__init__(node, table)
        self.logger = python_logger(node)
        self.no_pose = Throttle(self.logger, "a motion primitive has no pose")
        self.source = params["pose_source"]
        self.frame = params["primitive_frame"]  # '' until an observation names its frame
        self.frame_warned = False  # odometry in another frame than the observation's: said once
        self.tf = self.odom = None
        self.pose_problem = ""  # why the latest pose could not be had
        if self.source == "tf":
            from hdrqn_ros.nodes.tf_listener import TfListener  # tf2_msgs: ImportError naming scripts/install

            self.tf = TfListener(node, max_message_bytes=params["max_message_bytes"])
        else:
            self.odom_topic = node.resolve_topic_name(params["odom_topic"])
            bounded_subscription(node, Odometry, params["odom_topic"], self._on_odom, DEFAULT_QOS,
                                 params["max_message_bytes"], self.logger)
        self.primitive: Primitive | None = None
        self.pending: tuple[int, float] | None = None  # an action waiting for a pose, and when it came (s)
        self.lattice: Lattice | None = None  # this episode's grid, from its first primitive's pose
        self.outcomes: Counter[str] = Counter()
        self.last_report, self.last_outcome = "none yet", ""
        node.create_timer(1.0 / params["control_rate_hz"], self._control)  # ROS time: simulated with use_sim_time

    # -- the pose ----------------------------------------------------------------------------------
    def _on_odom(self, msg: Odometry) -> None:
        p = msg.pose.pose
        self.odom = (p.position.x, p.position.y, nav.yaw_of(p.orientation))  # in the odometry's frame
        if not self.table.heading_up and self.frame and msg.header.frame_id != self.frame and not self.frame_warned:
            self.frame_warned = True
            self.logger.warning(f"primitives from odometry move along {msg.header.frame_id!r}'s axes and the "
                                f"observation is drawn in {self.frame!r}: north-up moves are right only while "
                                f"{msg.header.frame_id!r} is not turned from {self.frame!r} (pose_source tf "
                                f"measures in the observation's frame)")

    def observed(self, frame_id: str = "") -> None:
        """An observation arrived (drawn in ``frame_id``): the commands go on."""
        super().observed()
        if frame_id and not self.node.params["primitive_frame"]:
            self.frame = frame_id

    def _where(self) -> str:
        if self.tf is not None:
            return f"tf {self.frame or '(the observation frame)'} <- {self.node.params['robot_base_frame']}"
        return f"odometry on {self.odom_topic}"

    def pose(self) -> tuple[float, float, float] | None:
        """The robot's latest ``(x, y, yaw)`` (m, rad) in the measuring frame; ``None`` (and
        ``pose_problem`` says why) while there is none."""
        if self.tf is None:
            self.pose_problem = "" if self.odom else f"no odometry yet on {self.odom_topic}"
            return self.odom
        if not self.frame:
            self.pose_problem = "no observation yet to name the frame of the moves (or set primitive_frame)"
            return None
        try:
            pose = self.tf.pose_in(self.frame, self.node.params["robot_base_frame"])
        except TransformError as exc:
            self.pose_problem = str(exc)
            return None
        self.pose_problem = ""
        return pose

    def _now_s(self) -> float:
        return self.node.get_clock().now().nanoseconds / 1e9

    # -- the primitives ----------------------------------------------------------------------------
    def command(self, action: int | None, stamp=(0, 0)) -> tuple:
        """The (publisher, first command) of ``action``'s primitive, which then streams from the
        timer; ``None`` (the episode ended): the zero command, and the next episode gets a new grid."""
        self._end_running("canceled by the next action" if action is not None else "canceled at the episode's end")
        if action is None:
            self.lattice = None
            return super().command(None, stamp)
        self.pending = (action, self._now_s())
        return self._begin(stamp) or super().command(None, stamp)

    def _begin(self, stamp) -> tuple | None:
        """Start the pending action's primitive if there is a pose: its (publisher, first command);
        ``None`` while it waits (until ``primitive_timeout_s`` after the action: then timed out)."""
        action, t0 = self.pending
        pose = self.pose()
        if pose is None:
            self.no_pose.warn(f"action {action} waits for a pose: {self._where()}: {self.pose_problem}")
            if self._now_s() - t0 >= self.limits.timeout_s:
                self.pending = None
                self.outcomes[TIMED_OUT] += 1
                self.last_outcome = TIMED_OUT
                self.last_report = f"action {action} timed out waiting for a pose ({self._where()})"
                self.logger.warning(f"motion primitive: {self.last_report}")
            return None
        self.pending = None
        params = self.node.params
        if self.lattice is None:
            self.lattice = Lattice(pose, params["cell_size_m"], pose[2] if self.table.heading_up else 0.0)
        self.primitive = Primitive(self.table.motion(action), self.lattice.snap(pose), t0, params["cell_size_m"],
                                   self.table.heading_up, self.table.holonomic, self.limits)
        return self._next(pose, stamp)

    def _poll_pending(self) -> None:
        """A pending action starts as soon as its pose is there (also while a simulated clock stands still)."""
        if self.pending is not None and (reply := self._begin(self.node.get_clock().now().nanoseconds)):
            reply[0].publish(reply[1])

    def _next(self, pose, stamp) -> tuple:
        """The running primitive's command at ``pose``; the zero one once it ended (reported)."""
        velocity = self.primitive.control(pose, self._now_s())
        if velocity is None:
            self._report(self.primitive)
            self.primitive = None
            self.moving = False
            return self.pub, self.table.stop_msg(stamp)
        self.moving = True
        return self.pub, self.table.velocity_msg(*velocity, stamp)

    def _control(self) -> None:
        """Stream the running primitive's command (the zero one, and keep trying, while the pose is missing)."""
        if self.primitive is None:
            return self._poll_pending()
        now = self.node.get_clock().now().nanoseconds
        pose = self.pose()
        if pose is None:
            self.no_pose.warn(f"stopped mid-primitive: {self._where()}: {self.pose_problem}")
            if self._now_s() - self.primitive.t0 >= self.limits.timeout_s:
                self.primitive.outcome = TIMED_OUT
                self._report(self.primitive)
                self.primitive = None
            pub, msg = super().command(None, now)
        else:
            pub, msg = self._next(pose, now)
        pub.publish(msg)

    def _report(self, primitive: Primitive) -> None:
        self.outcomes[primitive.outcome] += 1
        self.last_report, self.last_outcome = primitive.report(), primitive.outcome
        (self.logger.warning if primitive.outcome == TIMED_OUT else self.logger.info)(
            f"motion primitive: {self.last_report}")

    def _end_running(self, why: str) -> None:
        if self.primitive is not None:
            self.primitive.cancel()
            self.outcomes[self.primitive.outcome] += 1
            self.last_report, self.last_outcome = f"{self.primitive.report()} ({why})", self.primitive.outcome
            self.logger.info(f"motion primitive: {self.last_report}")
            self.primitive = None

    def halt(self) -> None:
        """The zero command, delivered before the node stops acting; the running primitive ends."""
        self._end_running("the node stopped")
        self.pending = None
        self.lattice = None
        super().halt()

    def _stop_if_stale(self) -> None:
        """Also (every :data:`~hdrqn_ros.nodes.nav_adapters.STALE_CHECK_S` of wall time) start a pending
        action whose pose came."""
        if self.moving and self.stale():
            self._end_running("the observation went stale")
            self.lattice, self.pending = None, None
        super()._stop_if_stale()
        self._poll_pending()

    # -- health ------------------------------------------------------------------------------------
    def problems(self) -> list[str]:
        found = super().problems()
        if self.pose_problem:
            found.append(f"motion primitives have no pose ({self._where()}): {self.pose_problem}; actions wait "
                         f"for one, the robot standing still")
        if self.last_outcome == TIMED_OUT:
            found.append(f"the last motion primitive timed out (the robot is slower than the limits, or "
                         f"primitive_timeout_s too short): {self.last_report}")
        return found

    def values(self) -> dict[str, str]:
        counts = ", ".join(f"{outcome} {self.outcomes[outcome]}" for outcome in OUTCOMES)
        return {"drive": f"primitives from {self._where()} at {self.node.params['control_rate_hz']:g} Hz",
                "primitives": counts, "last_primitive": self.last_report}

    def release(self) -> None:
        """Stop listening to tf."""
        if self.tf is not None:
            self.tf.destroy()
            self.tf = None
