"""LoopbackWorld (hdrqn_ros.robot.loopback_world) beyond test_robot_world.py: long moves
stop at walls, arcs are integrated exactly, goals the robot cannot stand on are refused,
the costmaps give the simulator's view at every free cell, constructor arguments are checked."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from hdrqn_ros.envs.gridworld import GridWorldBatch
from hdrqn_ros.nodes.nav import costmap_to_observation
from hdrqn_ros.robot.loopback_world import LoopbackWorld


def world_at(layout: str, cell: tuple[int, int], **kwargs) -> LoopbackWorld:
    world = LoopbackWorld(layout, 2, 0, **kwargs)
    world.new_episode()
    world.x, world.y = world.cell_centre(*cell)
    return world


def as_msg(costmap):
    """The fields of an OccupancyGrid that costmap_to_observation reads."""
    origin = SimpleNamespace(position=SimpleNamespace(x=costmap.origin_xy[0], y=costmap.origin_xy[1]))
    info = SimpleNamespace(width=costmap.width, height=costmap.height, resolution=costmap.resolution_m, origin=origin)
    return SimpleNamespace(info=info, data=costmap.data.reshape(-1))


@pytest.mark.parametrize("ticks", [[1.0], [0.1] * 10, [0.3] * 4])
def test_a_long_move_stops_at_the_wall_instead_of_jumping_it(ticks):
    """Cell (2, 4) of four-rooms is left of the middle wall (col 5): 1 m to the right in one
    advance must stop touching the wall, as in small ticks, not land in the other room."""
    world = world_at("fourrooms", (2, 4))
    world.command(1.0, 0.0, 0.0, 2.0)
    for dt in ticks:
        world.advance(dt)
    assert world.x == pytest.approx(5 * 0.25 - world.radius, abs=1e-9) and world.cell_of(*world.pose[:2]) == (2, 4)
    world.advance(0.1)  # still pushing against the wall
    assert world.moving and world.velocity == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("holonomic, body_v, expected", [
    (False, (0.125, 0.0), (1.0, 1.0)),  # forward on a quarter circle to the left: +x then +y
    (True, (0.0, 0.125), (-1.0, 1.0)),  # sideways (+y) while turning: +y then -x
])
@pytest.mark.parametrize("tick", [0.1, 0.3, 2.0])
def test_arcs_are_exact_whatever_the_tick(holonomic, body_v, expected, tick):
    """A velocity held with a turn rate follows its circle exactly: the end pose of a quarter
    turn (pi/4 rad/s for 2 s) does not depend on the tick."""
    world = world_at("gridworld", (5, 5), holonomic=holonomic)
    x0, y0 = world.pose[:2]
    world.command(*body_v, math.pi / 4, 2.0)
    world.advance(tick)
    assert world.velocity == pytest.approx((*body_v, math.pi / 4))
    for _ in range(math.ceil(2.0 / tick) + 1):
        world.advance(tick)
    radius = 0.125 / (math.pi / 4)
    assert world.pose == pytest.approx((x0 + expected[0] * radius, y0 + expected[1] * radius, math.pi / 2), abs=1e-9)
    assert not world.moving


def test_a_goal_the_robot_cannot_stand_on_is_refused():
    """A point of a free cell closer to a wall than the robot's radius: the robot could never
    reach it, so navigate_to refuses it (and keeps what it was doing)."""
    world = world_at("fourrooms", (2, 4))
    x, y = world.cell_centre(2, 4)
    world.navigate_to(*world.cell_centre(2, 2))
    with pytest.raises(ValueError, match=r"goal \(1\.245, 2\.125\).*robot_radius_m"):
        world.navigate_to(x + 0.12, y)
    assert world.moving
    world.navigate_to(x + 0.004, y)  # 0.121 m from the wall: fits
    while world.moving:
        world.advance(0.1)
    assert world.pose[:2] == pytest.approx((x + 0.004, y), abs=1e-12)


@pytest.mark.parametrize("layout", ["gridworld", "fourrooms"])
def test_local_costmap_gives_the_simulators_view_at_every_free_cell(layout):
    world = world_at(layout, (1, 1))
    layout_now = world.layout
    sim = GridWorldBatch(1, layout=layout, obstacles=False)
    sim.reset(seed=0)
    free = [(r, c) for r, c in np.argwhere(~world.walls) if (r, c) not in layout_now.goal_cells]
    for r, c in free:
        world.x, world.y = world.cell_centre(r, c)
        sim.set_state(0, (r, c), layout_now.goal_cells, [])
        local = world.local_costmap(3.0)
        ours = costmap_to_observation(as_msg(local), robot_xy=world.pose[:2], goals_xy=layout_now.goal_xy,
                                      unknown="outside")
        np.testing.assert_array_equal(ours, sim.render_obs()[0], err_msg=f"cell {(r, c)}")


@pytest.mark.parametrize("kwargs, problem", [
    ({"seed": -1}, "seed"), ({"seed": 1.5}, "seed"), ({"seed": True}, "seed"), ({"n_goals": 4}, "n_goals"),
    ({"layout": "maze"}, "layout"), ({"cell_size_m": 0.0}, "cell_size_m"), ({"resolution_m": math.nan}, "resolution_m"),
    ({"nav_speed_m_s": -0.1}, "nav_speed_m_s"), ({"nav_speed_m_s": "fast"}, "nav_speed_m_s"),
    ({"robot_radius_m": 0.125}, "robot_radius_m"),
])
def test_bad_construction_names_the_argument(kwargs, problem):
    with pytest.raises(ValueError, match=problem):
        LoopbackWorld(**kwargs)


@pytest.mark.parametrize("call, problem", [
    (lambda w: w.advance("0.1"), "dt_s"), (lambda w: w.command(0.1, 0.0, 0.0, None), "duration_s"),
    (lambda w: w.command("a", 0.0, 0.0, 1.0), "velocity"), (lambda w: w.navigate_to(-0.1, 1.0), "off the map"),
    (lambda w: w.local_costmap(math.inf), "size_m"),
])
def test_bad_arguments_name_the_argument(call, problem):
    world = LoopbackWorld()
    world.new_episode()
    with pytest.raises(ValueError, match=problem):
        call(world)
