"""Exact motion primitives: one agent action as a closed-loop move of one cell or a 90 degree turn (no ROS).

An action's velocity command (an action table's entry, body frame ``(vx, vy, wz)``) says
which primitive it is (:func:`motion_of`): a translation moves exactly ``cell_m`` along its
direction, a rotation turns exactly 90 degrees its way, the zero command stays. With a
north-up observation the direction is taken in the measuring frame (the observation's: body
``+x`` at yaw 0 is the frame's ``+x``), whatever the robot's yaw; heading-up, in the robot's
heading.

Poses are ``(x, y, yaw)`` in metres and radians in the measuring frame (tf or odometry);
times are seconds of the caller's clock. A :class:`Lattice` anchored at an episode's first
pose keeps the primitives on the grid the agent believes in: each primitive starts from the
lattice point (and lattice heading, multiples of 90 degrees from the anchor's yaw) nearest
the measured pose, so small errors do not add up over an episode.

A :class:`Primitive` is driven by calling :meth:`Primitive.control` with each new pose: it
returns the body-frame command ``(vx, vy, wz)`` (m/s, m/s, rad/s) of a proportional
controller within the :class:`Limits`, and ``None`` once it ended: ``completed`` (within the
position and angle tolerances), ``blocked`` (no progress for ``blocked_after_s`` while
driven: a gap of over half that between two calls restarts the wait) or
``timed_out`` (``timeout_s`` after its start). A differential-drive robot (not
``holonomic``) turns to face a move's direction (or its opposite, backing up) first.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

Pose2 = tuple[float, float, float]
Command = tuple[float, float, float]
COMPLETED, BLOCKED, TIMED_OUT, CANCELED = "completed", "blocked", "timed_out", "canceled"
OUTCOMES = (COMPLETED, BLOCKED, TIMED_OUT, CANCELED)
QUARTER = math.pi / 2
ALIGNED_RAD = 0.1
"""A differential-drive robot drives once it faces a move's direction within this (rad)."""


def _wrap(angle: float) -> float:
    return math.remainder(angle, 2 * math.pi)


def _clamp(error: float, gain: float, low: float, high: float) -> float:
    """``gain * error`` with its magnitude between ``low`` and ``high``, signed as ``error``."""
    return math.copysign(min(max(gain * abs(error), low), high), error)


@dataclass(frozen=True)
class Limits:
    """The controller's settings: gains (1/s), speed limits (m/s, rad/s; the minimum speeds
    finish the approach in finite time), tolerances (m, rad), and the blocked and timeout
    rules (s)."""

    linear_gain: float = 3.0
    angular_gain: float = 4.0
    max_linear: float = 0.3
    max_angular: float = 1.5
    min_linear: float = 0.03
    min_angular: float = 0.1
    position_tolerance: float = 0.01
    angle_tolerance: float = 0.02
    blocked_after_s: float = 0.5
    timeout_s: float = 2.0

    def __post_init__(self):
        for name, value in vars(self).items():
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"motion primitive limit {name} must be a positive number, got {value!r}")
        if self.min_linear > self.max_linear or self.min_angular > self.max_angular:
            raise ValueError(f"the minimum speeds ({self.min_linear} m/s, {self.min_angular} rad/s) must not exceed "
                             f"the maximum ones ({self.max_linear} m/s, {self.max_angular} rad/s)")


@dataclass(frozen=True)
class Motion:
    """What one action does: ``kind`` ``move`` (one cell along ``direction``, a unit vector in
    the body frame at yaw 0), ``turn`` (90 degrees, ``sign`` +1 counter-clockwise) or ``stay``."""

    kind: str
    direction: tuple[float, float] = (0.0, 0.0)
    sign: int = 0


def motion_of(vx: float, vy: float, wz: float) -> Motion:
    """The primitive of velocity command ``(vx, vy, wz)``; ValueError for one that both moves and turns."""
    values = (vx, vy, wz)
    if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        raise ValueError(f"a velocity command must be finite numbers, got {values!r}")
    speed = math.hypot(vx, vy)
    if speed > 0 and wz != 0:
        raise ValueError(f"a motion primitive moves or turns, not both: command (linear_x {vx}, linear_y {vy}, "
                         f"angular_z {wz})")
    if speed > 0:
        return Motion("move", (vx / speed, vy / speed))
    if wz != 0:
        return Motion("turn", sign=1 if wz > 0 else -1)
    return Motion("stay")


class Lattice:
    """The grid of an episode: points ``anchor + cell_m * (i, j)`` along axes turned by
    ``axes_yaw`` (rad; 0: the frame's axes), headings ``anchor_yaw + k * 90 degrees``."""

    def __init__(self, anchor: Pose2, cell_m: float, axes_yaw: float = 0.0):
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"cell_m must be a positive number, got {cell_m!r}")
        self.anchor, self.cell, self.axes_yaw = anchor, float(cell_m), float(axes_yaw)

    def snap(self, pose: Pose2) -> Pose2:
        """The lattice point and heading nearest ``pose``."""
        ax, ay, ayaw = self.anchor
        c, s = math.cos(self.axes_yaw), math.sin(self.axes_yaw)
        dx, dy = pose[0] - ax, pose[1] - ay
        i, j = round((c * dx + s * dy) / self.cell), round((-s * dx + c * dy) / self.cell)
        k = round(_wrap(pose[2] - ayaw) / QUARTER)
        return (ax + self.cell * (c * i - s * j), ay + self.cell * (s * i + c * j), _wrap(ayaw + k * QUARTER))


def target_of(motion: Motion, start: Pose2, cell_m: float, heading_up: bool) -> Pose2:
    """Where ``motion`` from ``start`` ends: one ``cell_m`` along its direction (heading-up:
    turned by ``start``'s yaw), or ``start``'s yaw turned 90 degrees."""
    x, y, yaw = start
    if motion.kind == "turn":
        return x, y, _wrap(yaw + motion.sign * QUARTER)
    if motion.kind == "stay":
        return start
    dx, dy = motion.direction
    if heading_up:
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = c * dx - s * dy, s * dx + c * dy
    return x + cell_m * dx, y + cell_m * dy, yaw


class Primitive:
    """One action's closed-loop motion from ``start`` (the reference pose, e.g. a lattice
    point) to :func:`target_of`, begun at time ``t0`` (s)."""

    def __init__(self, motion: Motion, start: Pose2, t0: float, cell_m: float, heading_up: bool, holonomic: bool,
                 limits: Limits):
        self.motion, self.start, self.t0, self.holonomic, self.limits = motion, start, t0, holonomic, limits
        self.target = target_of(motion, start, cell_m, heading_up)
        self.outcome: str | None = None  # one of OUTCOMES once ended
        self.error_m = self.error_rad = math.inf  # the last pose's distance and yaw from the target
        self.elapsed_s = 0.0
        self._best = math.inf  # the least remaining error so far (m, or rad for a turn)
        self._best_at = self._last_t = t0  # when progress was last made; the last call
        self._drive_yaw = start[2]  # a differential-drive move's heading: the direction, or its opposite
        if motion.kind == "move" and not holonomic:
            direction = math.atan2(self.target[1] - start[1], self.target[0] - start[0])
            backwards = abs(_wrap(direction - start[2])) > QUARTER
            self._drive_yaw = _wrap(direction + math.pi) if backwards else direction

    def _errors(self, pose: Pose2) -> tuple[float, float, float, float]:
        """(ex, ey) m to the target in the frame, the yaw error (rad) to hold, and the remaining
        error that must fall (m along the way, rad for a turn)."""
        ex, ey = self.target[0] - pose[0], self.target[1] - pose[1]
        if self.motion.kind == "turn":
            eyaw = _wrap(self.target[2] - pose[2])
            return ex, ey, eyaw, abs(eyaw)
        if self.holonomic:
            return ex, ey, _wrap(self.target[2] - pose[2]), math.hypot(ex, ey)
        along = ex * math.cos(self._drive_yaw) + ey * math.sin(self._drive_yaw)  # what driving can close
        return ex, ey, _wrap(self._drive_yaw - pose[2]), abs(along)

    def control(self, pose: Pose2, t: float) -> Command | None:
        """The body-frame command at ``pose`` (measured at time ``t``, s), or ``None`` once ended."""
        if self.outcome is not None:
            return None
        lim = self.limits
        ex, ey, eyaw, remaining = self._errors(pose)
        self.error_m, self.error_rad, self.elapsed_s = math.hypot(ex, ey), abs(_wrap(self.target[2] - pose[2])), \
            t - self.t0
        done = remaining <= (lim.angle_tolerance if self.motion.kind == "turn" else lim.position_tolerance)
        if self.motion.kind == "stay" or done:
            return self._end(COMPLETED)
        if remaining < self._best - (lim.angle_tolerance if self.motion.kind == "turn" else lim.position_tolerance) / 2:
            self._best, self._best_at = remaining, t
        elif t - self._last_t > lim.blocked_after_s / 2:
            self._best_at = t  # not driven for a while (this caller stalled): no progress was asked for
        elif t - self._best_at >= lim.blocked_after_s:
            return self._end(BLOCKED)
        self._last_t = t
        if t - self.t0 >= lim.timeout_s:
            return self._end(TIMED_OUT)
        if self.motion.kind == "turn":
            return 0.0, 0.0, _clamp(eyaw, lim.angular_gain, lim.min_angular, lim.max_angular)
        hold = _clamp(eyaw, lim.angular_gain, 0.0, lim.max_angular) if abs(eyaw) > lim.angle_tolerance else 0.0
        c, s = math.cos(pose[2]), math.sin(pose[2])
        bx, by = c * ex + s * ey, -s * ex + c * ey  # the error in the body frame
        if self.holonomic:
            speed = min(max(lim.linear_gain * remaining, lim.min_linear), lim.max_linear)
            return speed * bx / remaining, speed * by / remaining, hold
        if abs(eyaw) > ALIGNED_RAD:  # face the way first
            return 0.0, 0.0, _clamp(eyaw, lim.angular_gain, lim.min_angular, lim.max_angular)
        return _clamp(bx, lim.linear_gain, lim.min_linear, lim.max_linear), 0.0, hold

    def _end(self, outcome: str) -> None:
        self.outcome = outcome
        return None

    def cancel(self) -> None:
        """End it now (another action came, or the robot must stop)."""
        if self.outcome is None:
            self.outcome = CANCELED

    def report(self) -> str:
        """The outcome in words: what, the errors (m, degrees) and the time (s)."""
        what = {"move": "move of one cell", "turn": f"turn {'left' if self.motion.sign > 0 else 'right'}",
                "stay": "stay"}[self.motion.kind]
        return (f"{what} {self.outcome or 'running'}: {self.error_m:.3f} m and {math.degrees(self.error_rad):.1f} deg "
                f"from the target after {self.elapsed_s:.2f} s")
