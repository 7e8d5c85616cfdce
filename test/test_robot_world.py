"""The loopback robot's kinematics (hdrqn_ros.robot.loopback_world), without ROS: the
simulator's layouts, its moves reproduced by velocity commands, the navigator, costmaps."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from hdrqn_ros.envs.gridworld import GridWorldBatch
from hdrqn_ros.nodes.nav import costmap_to_observation
from hdrqn_ros.robot.loopback_world import LoopbackWorld

MOVES = {0: (0.0, 0.125), 1: (0.0, -0.125), 2: (-0.125, 0.0), 3: (0.125, 0.0)}
"""The holonomic action table (config/nav2/actions_holonomic.yaml): up is +y, right is +x."""


def as_msg(costmap):
    """The fields of an OccupancyGrid that costmap_to_observation reads."""
    origin = SimpleNamespace(position=SimpleNamespace(x=costmap.origin_xy[0], y=costmap.origin_xy[1]))
    info = SimpleNamespace(width=costmap.width, height=costmap.height, resolution=costmap.resolution_m, origin=origin)
    return SimpleNamespace(info=info, data=costmap.data.reshape(-1))


def drive(world: LoopbackWorld, action: int, tick: float) -> None:
    world.command(*MOVES[action], 0.0, 2.0)
    for _ in range(math.ceil(2.0 / tick) + 2):
        world.advance(tick)


@pytest.mark.parametrize("layout", ["gridworld", "fourrooms"])
@pytest.mark.parametrize("seed", [0, 7])
def test_layouts_are_the_simulators_without_fire(layout, seed):
    world = LoopbackWorld(layout, 2, seed)
    sim = GridWorldBatch(1, layout=layout, obstacles=False)
    for episode in range(20):
        sim.reset(seed=seed) if episode == 0 else sim.reset_where(np.ones(1, bool))
        got = world.new_episode()
        assert got.episode == episode and got.agent_cell == tuple(sim.agent_pos[0])
        assert got.goal_cells == tuple(map(tuple, sim.goal_pos[0]))
        assert world.pose[:2] == world.cell_centre(*got.agent_cell) and world.velocity == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("layout, tick", [("gridworld", 0.1), ("fourrooms", 0.1), ("fourrooms", 0.3)])
def test_velocity_commands_reproduce_the_simulators_moves(layout, tick):
    """Each action as 0.125 m/s held 2 s: the robot's cell is the simulator's after every
    step (walls stop both), within 0.01 m of its centre."""
    world, sim = LoopbackWorld(layout, 2, 3), GridWorldBatch(1, layout=layout, obstacles=False)
    world.new_episode()
    sim.reset(seed=3)
    rng = np.random.default_rng(1)
    for _ in range(200):
        if sim.done[0]:
            sim.reset_where(np.ones(1, bool))
            world.new_episode()
        action = int(rng.integers(4))
        sim.step(np.array([action]))
        drive(world, action, tick)
        cell = world.cell_of(*world.pose[:2])
        assert cell == tuple(sim.agent_pos[0])
        assert np.abs(np.subtract(world.cell_centre(*cell), world.pose[:2])).max() < 0.01
        assert not world.moving and world.velocity == (0.0, 0.0, 0.0)


def test_differential_drive_turns_and_goes_forward():
    world = LoopbackWorld("gridworld", 2, 0, holonomic=False)
    world.new_episode()
    world.x, world.y = world.cell_centre(5, 5)
    world.command(0.0, 0.0, math.pi / 4, 2.0)
    for _ in range(20):
        world.advance(0.1)
    assert world.yaw == pytest.approx(math.pi / 2)
    y0 = world.y
    world.command(0.125, 0.3, 0.0, 2.0)  # vy ignored
    world.advance(0.5)
    assert world.velocity[0] == pytest.approx(0.125) and world.velocity[1] == pytest.approx(0.0, abs=1e-9)
    for _ in range(20):
        world.advance(0.1)
    assert world.y - y0 == pytest.approx(0.25) and world.x == pytest.approx(world.cell_centre(5, 5)[0])


def test_navigator_goes_through_a_door_on_free_cells():
    world = LoopbackWorld("fourrooms", 2, 0, nav_speed_m_s=0.25)
    world.new_episode()
    world.x, world.y = world.cell_centre(2, 2)
    goal = world.cell_centre(8, 8)
    world.navigate_to(*goal)
    elapsed = 0.0
    while world.moving:
        world.advance(0.1)
        elapsed += 0.1
        assert not world.walls[world.cell_of(*world.pose[:2])]
        assert elapsed < 60
    assert world.pose[:2] == pytest.approx(goal, abs=1e-6)
    assert elapsed == pytest.approx(12 * 0.25 / 0.25, abs=0.11)  # 12 cells through a door
    with pytest.raises(ValueError, match="wall"):
        world.navigate_to(0.1, 0.1)


def test_costmaps_hold_the_walls_and_draw_the_simulators_view():
    world = LoopbackWorld("fourrooms", 2, 4)
    layout = world.new_episode()
    whole = world.global_costmap()
    assert (whole.width, whole.height) == (55, 55)
    np.testing.assert_array_equal(whole.data == 100, np.kron(world.walls[::-1], np.ones((5, 5), bool)))
    sim = GridWorldBatch(1, layout="fourrooms", obstacles=False)
    sim.reset(seed=4)
    local = world.local_costmap(3.0)
    assert (local.width, local.height) == (60, 60) and (local.data == -1).any()
    ours = costmap_to_observation(as_msg(local), robot_xy=world.pose[:2], goals_xy=layout.goal_xy,
                                  unknown="outside")
    np.testing.assert_array_equal(ours, sim.render_obs()[0])


@pytest.mark.parametrize("call, problem", [
    (lambda w: w.advance(0.0), "dt_s"), (lambda w: w.command(float("nan"), 0, 0, 1.0), "velocity"),
    (lambda w: w.command(0.1, 0, 0, -1.0), "duration_s"), (lambda w: w.local_costmap(0.0), "size_m"),
    (lambda w: w.navigate_to(float("inf"), 0.0), "goal"),
])
def test_bad_arguments_name_the_argument(call, problem):
    world = LoopbackWorld()
    world.new_episode()
    with pytest.raises(ValueError, match=problem):
        call(world)


def test_bad_construction():
    with pytest.raises(ValueError, match="robot_radius_m"):
        LoopbackWorld(robot_radius_m=0.2)
    with pytest.raises(ValueError, match="layout"):
        LoopbackWorld("maze")
