"""Motion primitives in closed loop (hdrqn_ros.robot.motion_primitives), no ROS.

A pure-Python robot (holonomic or differential drive) holds each body-frame command until a
1 s deadman stops it, as Nav2's velocity smoother does; the controller sees its pose one
control period late (20 Hz) and streams commands. Every action of the holonomic (north-up)
and the differential-drive (heading-up) tables ends within tolerance of its cell or its
90 degrees from any start yaw, within the timeout; an episode of moves stays on its lattice;
a wall ends a move as blocked, a slow robot as timed out.
"""
from __future__ import annotations

import math

import pytest

from hdrqn_ros.robot.motion_primitives import (BLOCKED, COMPLETED, TIMED_OUT, Lattice, Limits, Motion, Primitive,
                                               motion_of, target_of)

CELL = 0.25
DEADMAN_S, CONTROL_S, DT = 1.0, 0.05, 0.01
HOLONOMIC = [(0.0, 0.125, 0.0), (0.0, -0.125, 0.0), (-0.125, 0.0, 0.0), (0.125, 0.0, 0.0)]
"""config/nav2/actions_holonomic.yaml: up, down, left, right (north-up)."""
DIFF = [(0.125, 0.0, 0.0), (-0.125, 0.0, 0.0), (0.0, 0.0, 0.785), (0.0, 0.0, -0.785)]
"""config/nav2/actions.yaml: forward, back, turn left, turn right (heading-up)."""
YAWS = [0.0, 0.2, 1.0, -2.5, math.pi, 3 * math.pi / 4]


class Robot:
    """Kinematics with a deadman: ``command`` holds for :data:`DEADMAN_S`; ``wall_x``: the robot
    cannot pass this x; ``speed_scale``: it achieves only this fraction of each command."""

    def __init__(self, pose, holonomic: bool, wall_x: float = math.inf, speed_scale: float = 1.0):
        self.x, self.y, self.yaw = pose
        self.holonomic, self.wall_x, self.scale = holonomic, wall_x, speed_scale
        self.cmd, self.cmd_left = (0.0, 0.0, 0.0), 0.0
        self.t = 0.0

    @property
    def pose(self):
        return self.x, self.y, self.yaw

    def command(self, cmd) -> None:
        self.cmd, self.cmd_left = cmd, DEADMAN_S

    def advance(self, dt: float) -> None:
        if self.cmd_left > 0:
            vx, vy, wz = (v * self.scale for v in self.cmd)
            vy = vy if self.holonomic else 0.0
            c, s = math.cos(self.yaw), math.sin(self.yaw)
            self.x = min(self.x + (c * vx - s * vy) * dt, self.wall_x)
            self.y += (s * vx + c * vy) * dt
            self.yaw = math.remainder(self.yaw + wz * dt, 2 * math.pi)
            self.cmd_left -= dt
        self.t += dt


def run(primitive: Primitive, robot: Robot, limit_s: float = 10.0) -> None:
    """Drive ``robot`` with ``primitive`` at 20 Hz on poses one period old, until it ends; then the zero command."""
    seen = robot.pose
    while robot.t < limit_s:
        cmd = primitive.control(seen, robot.t)
        if cmd is None:
            robot.command((0.0, 0.0, 0.0))
            return
        seen = robot.pose  # what the next control period will see (one period of latency)
        robot.command(cmd)
        for _ in range(round(CONTROL_S / DT)):
            robot.advance(DT)
    raise AssertionError("the primitive never ended")


def start(table, action: int, yaw: float, holonomic: bool, heading_up: bool, **kwargs):
    limits = Limits()
    pose = (1.0, 2.0, yaw)
    primitive = Primitive(motion_of(*table[action]), pose, 0.0, CELL, heading_up, holonomic, limits)
    return primitive, Robot(pose, holonomic, **kwargs), limits


def off(pose, target) -> tuple[float, float]:
    return math.hypot(pose[0] - target[0], pose[1] - target[1]), abs(math.remainder(pose[2] - target[2], 2 * math.pi))


@pytest.mark.parametrize("yaw", YAWS)
@pytest.mark.parametrize("action", range(4))
def test_holonomic_north_up_moves_exactly_one_cell_along_the_frame_axis_whatever_the_yaw(action, yaw):
    primitive, robot, limits = start(HOLONOMIC, action, yaw, holonomic=True, heading_up=False)
    run(primitive, robot)
    assert primitive.outcome == COMPLETED, primitive.report()
    dx, dy = (round(v / 0.125) for v in HOLONOMIC[action][:2])
    assert primitive.target[:2] == pytest.approx((1.0 + CELL * dx, 2.0 + CELL * dy))
    distance, turned = off(robot.pose, primitive.target)
    assert distance <= limits.position_tolerance + 0.005 and turned <= limits.angle_tolerance + 0.01
    assert robot.t <= limits.timeout_s, primitive.report()


@pytest.mark.parametrize("yaw", YAWS)
@pytest.mark.parametrize("action", range(4))
def test_differential_drive_heading_up_moves_a_cell_or_turns_exactly_90_degrees(action, yaw):
    primitive, robot, limits = start(DIFF, action, yaw, holonomic=False, heading_up=True)
    run(primitive, robot)
    assert primitive.outcome == COMPLETED, primitive.report()
    distance, turned = off(robot.pose, primitive.target)
    if action < 2:
        sign = 1 if action == 0 else -1
        assert primitive.target[:2] == pytest.approx((1.0 + sign * CELL * math.cos(yaw),
                                                      2.0 + sign * CELL * math.sin(yaw)))
        assert distance <= limits.position_tolerance + 0.005, primitive.report()
    else:
        assert primitive.target[2] == pytest.approx(math.remainder(yaw + (1 if action == 2 else -1) * math.pi / 2,
                                                                   2 * math.pi))
        assert turned <= limits.angle_tolerance + 0.01 and distance < 1e-9, primitive.report()
    assert robot.t <= limits.timeout_s, primitive.report()


def test_one_command_per_step_is_what_the_deadman_cuts():
    """The control: today's one command, held for a 2.5 s step, moves half a cell under a 1 s deadman."""
    robot = Robot((0.0, 0.0, 0.0), holonomic=True)
    robot.command(HOLONOMIC[3])
    for _ in range(250):
        robot.advance(DT)
    assert robot.x == pytest.approx(0.125, abs=1e-6)


@pytest.mark.parametrize("holonomic, table, heading_up", [(True, HOLONOMIC, False), (False, DIFF, True)])
def test_an_episode_of_primitives_stays_on_its_lattice(holonomic, table, heading_up):
    """Each primitive starts from the lattice point nearest the robot: 40 actions end within
    tolerance of where the simulator's moves put the agent, not 40 tolerances away."""
    yaw = 0.3
    robot, limits = Robot((0.5, 0.5, yaw), holonomic), Limits()
    lattice = Lattice(robot.pose, CELL, axes_yaw=yaw if heading_up else 0.0)
    expected = robot.pose
    actions = [(3 * i + i // 3) % 4 for i in range(40)]
    for action in actions:
        motion = motion_of(*table[action])
        primitive = Primitive(motion, lattice.snap(robot.pose), robot.t, CELL, heading_up, holonomic, limits)
        expected = target_of(motion, expected, CELL, heading_up)
        run(primitive, robot, limit_s=robot.t + 10)
        assert primitive.outcome == COMPLETED, primitive.report()
    distance, turned = off(robot.pose, expected)
    assert distance <= limits.position_tolerance + 0.005 and turned <= limits.angle_tolerance + 0.01


def test_a_wall_ends_a_move_as_blocked():
    primitive, robot, limits = start(HOLONOMIC, 3, 0.0, holonomic=True, heading_up=False, wall_x=1.05)
    run(primitive, robot)
    assert primitive.outcome == BLOCKED, primitive.report()
    assert robot.x == pytest.approx(1.05) and primitive.error_m == pytest.approx(0.2, abs=0.01)
    assert robot.t < limits.blocked_after_s + 1.0 and "blocked" in primitive.report()


def test_a_slow_robot_times_out():
    primitive, robot, limits = start(HOLONOMIC, 0, 0.0, holonomic=True, heading_up=False, speed_scale=0.2)
    run(primitive, robot)
    assert primitive.outcome == TIMED_OUT, primitive.report()
    assert limits.timeout_s <= robot.t < limits.timeout_s + 0.1 and 0.0 < robot.y - 2.0 < CELL


def test_the_lattice_snaps_to_cells_and_quarter_turns():
    lattice = Lattice((1.0, 1.0, 0.3), CELL)
    assert lattice.snap((1.26, 0.76, 0.3 + math.pi / 2 + 0.1)) == pytest.approx((1.25, 0.75, 0.3 + math.pi / 2))
    turned = Lattice((0.0, 0.0, math.pi / 2), CELL, axes_yaw=math.pi / 2)
    assert turned.snap((-0.01, 0.24, math.pi / 2)) == pytest.approx((0.0, 0.25, math.pi / 2))


def test_bad_commands_and_limits_are_named():
    assert motion_of(0.0, 0.0, 0.0) == Motion("stay")
    with pytest.raises(ValueError, match="moves or turns, not both"):
        motion_of(0.1, 0.0, 0.5)
    with pytest.raises(ValueError, match="finite"):
        motion_of(float("nan"), 0.0, 0.0)
    with pytest.raises(ValueError, match="timeout_s must be a positive number"):
        Limits(timeout_s=0.0)
    with pytest.raises(ValueError, match="minimum speeds"):
        Limits(min_linear=1.0, max_linear=0.5)
    stay = Primitive(Motion("stay"), (0.0, 0.0, 0.0), 0.0, CELL, False, True, Limits())
    assert stay.control((0.0, 0.0, 0.0), 0.0) is None and stay.outcome == COMPLETED


def test_action_tables_say_what_each_action_does(tmp_path):
    """The shipped tables: the simulator's moves (holonomic, north-up) and forward/back/turns
    (differential drive, heading-up); ``observation`` says it outright; a command that both
    moves and turns is refused naming the table and the action."""
    pytest.importorskip("geometry_msgs.msg", reason="the action table builds ROS messages")
    from hdrqn_ros.nodes.nav import ActionTable, NavConfigError
    from hdrqn_ros.robot_graph import HOLONOMIC_ACTIONS

    holonomic = ActionTable.load(HOLONOMIC_ACTIONS, 4)
    assert holonomic.holonomic and not holonomic.heading_up
    assert [holonomic.motion(a) for a in range(4)] == [Motion("move", d) for d in
                                                       ((0.0, 1.0), (0.0, -1.0), (-1.0, 0.0), (1.0, 0.0))]
    diff = ActionTable.load(HOLONOMIC_ACTIONS.with_name("actions.yaml"), 4)
    assert diff.heading_up and not diff.holonomic
    assert [diff.motion(a) for a in range(4)] == [Motion("move", (1.0, 0.0)), Motion("move", (-1.0, 0.0)),
                                                  Motion("turn", sign=1), Motion("turn", sign=-1)]
    assert diff.velocity_msg(0.1, 0.0, -0.5).angular.z == -0.5
    path = tmp_path / "actions.yaml"
    path.write_text("observation: heading_up\nactions:\n  - {linear_x: 0.1}\n  - {linear_x: 0.1, angular_z: 0.5}\n")
    table = ActionTable.load(path, 2)
    assert table.heading_up and table.motion(0) == Motion("move", (1.0, 0.0))
    with pytest.raises(NavConfigError, match=r"actions.yaml: action 1: a motion primitive moves or turns, not both"):
        table.motion(1)
    path.write_text("observation: sideways\nactions:\n  - {linear_x: 0.1}\n")
    with pytest.raises(NavConfigError, match=r"observation must be one of \['north_up', 'heading_up'\], got 'sideways'"):
        ActionTable.load(path, 1)


def test_a_stalled_controller_is_not_a_blocked_robot():
    """The first command went nowhere and the caller did not run for 0.6 s (a loaded
    machine): the robot stood still, but no progress was asked for meanwhile, so that is no
    wall (without the rule it would end blocked), and the move goes on to its cell."""
    primitive, robot, limits = start(HOLONOMIC, 3, 0.0, holonomic=True, heading_up=False)
    assert primitive.control(robot.pose, 0.0) is not None
    for _ in range(round(0.6 / DT)):
        robot.advance(DT)
    run(primitive, robot)
    assert primitive.outcome == COMPLETED and robot.t < limits.timeout_s, primitive.report()
