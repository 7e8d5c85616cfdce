"""LoopbackWorld (hdrqn_ros.robot.loopback_world) beyond test_robot_world.py: long moves
stop at walls, arcs are integrated exactly, goals the robot cannot stand on are refused,
the costmaps give the simulator's view at every free cell, constructor arguments are checked;
and the parts that make it a Nav2 robot in miniature: Nav2's inflation costs
(hdrqn_ros.robot.nav2_costmap), the 1 s command deadman, differential drive from any start
yaw, a drifting ``map -> odom`` under which ``map -> odom -> base_link`` stays the true pose,
the local costmap in ``odom``, and AMCL's rule for when it publishes a pose."""
import itertools
import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdrqn_ros.envs.gridworld import GridWorldBatch
from hdrqn_ros.nodes.nav import costmap_to_observation
from hdrqn_ros.robot.loopback_world import AmclUpdates, LoopbackWorld, compose, inverse
from hdrqn_ros.robot.nav2_costmap import distance_to_lethal, inflate, inflation_cost, occupancy_values


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


# -- Nav2's costs ------------------------------------------------------------------------------------
def test_costs_translate_to_occupancy_values_as_nav2_publishes_them():
    """0 free, 1..252 graded onto 1..98, 253 inscribed 99, 254 lethal 100, 255 unknown -1."""
    costs = np.arange(256)
    values = occupancy_values(costs)
    assert (values[0], values[1], values[252], values[253], values[254], values[255]) == (0, 1, 98, 99, 100, -1)
    graded = values[1:253].astype(int)
    assert graded.min() == 1 and graded.max() == 98 and (np.diff(graded) >= 0).all()
    assert values[127] == 1 + 97 * 126 // 251
    with pytest.raises(ValueError, match="0..255"):
        occupancy_values(np.array([256]))


def test_inflation_costs_decay_from_lethal_through_inscribed():
    """At the wall 254, within the inscribed radius 253, then 252 * exp(-k (d - r)) falling with d."""
    d = np.array([0.0, 0.05, 0.12, 0.1201, 0.2, 0.4, 0.7, 2.0])
    cost = inflation_cost(d, 0.12, 3.0).astype(int)
    assert cost[0] == 254 and cost[1] == cost[2] == 253
    assert cost[3] == 251 and cost[4] == int(252 * math.exp(-3.0 * 0.08))
    assert (np.diff(cost) <= 0).all() and cost[-1] == int(252 * math.exp(-3.0 * 1.88))


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 25), st.integers(1, 25), st.integers(0, 12), st.integers(0, 2**32 - 1))
def test_distance_to_lethal_is_the_exact_euclidean_distance(h, w, max_cells, seed):
    lethal = np.random.default_rng(seed).random((h, w)) < 0.08
    got = distance_to_lethal(lethal, max_cells)
    cells = np.argwhere(lethal)
    for (r, c), value in np.ndenumerate(got):
        nearest = np.sqrt(((cells - (r, c)) ** 2).sum(axis=1)).min() if len(cells) else np.inf
        assert value == (pytest.approx(nearest) if nearest <= max_cells else np.inf), (r, c)


def test_inflated_grid_wall_inscribed_graded_free_unknown():
    """One lethal cell in a free 41 x 41 grid at 0.05 m with an unknown column: 100 on it, 99
    within 0.12 m, values falling with distance out to 0.7 m, 0 beyond; unknown cells stay -1
    unless inscribed."""
    grid = np.zeros((41, 41), np.int8)
    grid[20, 20] = 100
    grid[:, 22] = -1
    out = inflate(grid, 0.05, 0.12, 0.7, 3.0).astype(int)
    rows, cols = np.indices(grid.shape)
    cells = np.hypot(rows - 20, cols - 20)  # 0.7 m is 14 cells, 0.12 m 2.4
    known = grid != -1
    assert out[20, 20] == 100
    assert (out[(cells > 0) & (cells <= 2.4) & known] == 99).all()
    assert (out[(cells > 2.4) & (cells <= 14) & known] < 99).all()
    assert (out[cells > 14] == np.where(known, 0, -1)[cells > 14]).all()
    assert out[20, 22] == 99 and (out[:, 22][cells[:, 22] > 2.4] == -1).all()
    ring = sorted({(round(float(d), 6), int(v)) for d, v in zip(cells[known & (cells > 0)], out[known & (cells > 0)])})
    assert all(a[1] >= b[1] for a, b in zip(ring, ring[1:])), "costs rise somewhere with distance"
    assert 1 <= min(v for d, v in ring if d <= 14) and max(v for d, v in ring if d > 2.4) <= 98
    np.testing.assert_array_equal(inflate(grid, 0.05, 0.12, 0.0, 3.0), grid)
    with pytest.raises(ValueError, match="lethal"):
        inflate(np.full((2, 2), 50, np.int8), 0.05, 0.12, 0.7, 3.0)


def test_inflated_costmaps_keep_the_walls_and_cost_the_corridors():
    """With Nav2's 0.7 m inflation: exactly the wall cells are 100; no free cell of the map
    is lethal and none is inscribed at a grid cell's centre (the robot fits every corridor)."""
    world = LoopbackWorld("fourrooms", 2, 0, inflation_radius_m=0.7)
    world.new_episode()
    whole = world.global_costmap().data.astype(int)
    np.testing.assert_array_equal(whole == 100, np.kron(world.walls[::-1], np.ones((5, 5), bool)))
    centres = whole[2::5, 2::5][::-1]  # (row, col) of the map
    assert (centres[~world.walls] < 99).all() and (centres[~world.walls] >= 1).all()


# -- motion --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("tick", [0.1, 0.3])
def test_the_deadman_stops_a_command_one_second_old(tick):
    """A command held for cmd_vel_timeout 1 s (Nav2's velocity_timeout): 0.125 m/s moves 0.125 m, then stands."""
    world = world_at("gridworld", (5, 5))
    x0 = world.x
    world.command(0.125, 0.0, 0.0, 1.0)
    for _ in range(math.ceil(3.0 / tick)):
        world.advance(tick)
    assert world.x - x0 == pytest.approx(0.125, abs=1e-12) and not world.moving and world.velocity == (0, 0, 0)


@pytest.mark.parametrize("start_yaw", [0.0, 0.7, -2.5, math.pi])
def test_differential_drive_goes_where_it_faces_from_any_start_yaw(start_yaw):
    """Forward moves along the heading, sideways commands do nothing, turns add to the yaw."""
    world = LoopbackWorld("gridworld", 2, 0, holonomic=False, start_yaw=start_yaw)
    world.new_episode()
    world.x, world.y = world.cell_centre(5, 5)
    assert world.yaw == pytest.approx(math.remainder(start_yaw, 2 * math.pi))
    x0, y0 = world.x, world.y
    world.command(0.1, 0.1, 0.0, 1.0)
    for _ in range(12):
        world.advance(0.1)
    assert (world.x - x0, world.y - y0) == pytest.approx((0.1 * math.cos(start_yaw), 0.1 * math.sin(start_yaw)))
    world.command(0.0, 0.0, math.pi / 4, 2.0)
    for _ in range(25):
        world.advance(0.1)
    assert math.remainder(world.yaw - start_yaw - math.pi / 2, 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


# -- frames -------------------------------------------------------------------------------------------
def drive_around(world: LoopbackWorld, check) -> None:
    """Forward, arcs and turns for 40 s at 0.1 s ticks, ``check()`` after each tick."""
    for vx, wz in ((0.1, 0.0), (0.1, 0.3), (0.0, -0.5), (0.05, 0.2)):
        world.command(vx, 0.0, wz, 10.0)
        for _ in range(100):
            world.advance(0.1)
            check()


@pytest.mark.parametrize("odom_error", [(0.0, 0.0), (0.02, 0.01), (-0.05, 0.03)])
def test_map_odom_base_link_is_always_the_true_pose(odom_error):
    world = LoopbackWorld("gridworld", 2, 0, holonomic=False, map_to_odom=(0.8, 0.4, 0.2), odom_error=odom_error)
    world.new_episode()
    world.x, world.y = world.cell_centre(5, 5)

    def check():
        assert compose(world.map_to_odom, world.odom_pose) == pytest.approx(world.pose, abs=1e-9)

    drive_around(world, check)
    if not any(odom_error):
        assert world.map_to_odom == (0.8, 0.4, 0.2), "no odometry error: map -> odom stays put"


def test_map_to_odom_drifts_slowly_with_the_odometry_error():
    """2 % distance error: odometry reads 2 % more than the robot drove, map -> odom moves
    back along the way by the difference; standing still it does not move; a new episode
    moves it instead of odometry (REP 105: odom is continuous)."""
    world = LoopbackWorld("gridworld", 2, 0, holonomic=False, map_to_odom=(0.8, 0.4, 0.2), odom_error=(0.02, 0.0))
    world.new_episode()
    world.x, world.y = world.cell_centre(5, 3)
    start_odom = world.odom_pose
    world.command(0.1, 0.0, 0.0, 5.0)  # 0.5 m along +x (yaw 0)
    for _ in range(60):
        world.advance(0.1)
    moved = compose(inverse(start_odom), world.odom_pose)
    assert moved == pytest.approx((0.51, 0.0, 0.0), abs=1e-9)
    drift = world.map_to_odom
    assert math.hypot(drift[0] - 0.8, drift[1] - 0.4) == pytest.approx(0.01, abs=1e-9) and drift[2] == pytest.approx(0.2)
    for _ in range(30):
        world.advance(0.1)
    assert world.map_to_odom == drift
    odom = world.odom_pose
    world.new_episode()
    assert world.odom_pose == pytest.approx(odom, abs=1e-12) and world.map_to_odom != drift
    assert compose(world.map_to_odom, world.odom_pose) == pytest.approx(world.pose, abs=1e-12)


@pytest.mark.parametrize("layout, map_to_odom", [("gridworld", (0.8, 0.4, 0.2)), ("fourrooms", (-0.3, 1.1, -2.0))])
def test_local_costmap_in_odom_agrees_with_the_map_through_the_transform(layout, map_to_odom):
    """Every cell of the rolling window in ``odom``: lethal exactly where its centre, taken
    into the map by ``map -> odom``, lies in a wall; unknown off the map; the window is
    centred on the robot's odometry pose."""
    world = LoopbackWorld(layout, 2, 0, map_to_odom=map_to_odom)
    world.new_episode()
    local = world.local_costmap(3.0, in_odom=True)
    ox, oy, _ = world.odom_pose
    assert (local.width, local.height) == (60, 60)
    assert local.origin_xy[0] <= ox - 1.5 + 1e-9 < local.origin_xy[0] + 0.05
    data = local.data.astype(int)
    for (r, c), value in np.ndenumerate(data):
        x, y, _ = compose(world.map_to_odom, (local.origin_xy[0] + (c + 0.5) * 0.05,
                                              local.origin_xy[1] + (r + 0.5) * 0.05, 0.0))
        row, col = world.cell_of(x, y)
        on_map = 0 <= row < 11 and 0 <= col < 11
        assert value == (-1 if not on_map else 100 if world.walls[row, col] else 0), (r, c, x, y)
    assert world.local_costmap(3.0, in_odom=True) is local, "the same window is not computed twice"


@pytest.mark.parametrize("layout", ["gridworld", "fourrooms"])
@pytest.mark.parametrize("yaw", [0.2, -0.5, 1.0])
def test_a_turned_odom_costmap_gives_the_simulators_view_at_every_free_cell(layout, yaw):
    """The local costmap in ``odom`` under ``map -> odom`` turned by ``yaw``, drawn north-up in
    the map's axes (as the robot environment draws it) around a robot up to 0.01 m off its
    cell's centre: the simulator's view at every free cell. Counting every sample, a free cell
    beside a wall showed as wall (the turned grid's lethal cells straddle the border)."""
    world = world_at(layout, (1, 1), map_to_odom=(0.8, 0.4, yaw))
    layout_now, to_odom = world.layout, inverse(world.map_to_odom)
    sim = GridWorldBatch(1, layout=layout, obstacles=False)
    sim.reset(seed=0)
    goals = [compose(to_odom, (x, y, 0.0))[:2] for x, y in layout_now.goal_xy]
    free = [(r, c) for r, c in np.argwhere(~world.walls) if (r, c) not in layout_now.goal_cells]
    for (r, c), (dx, dy) in zip(free, itertools.cycle([(0.0, 0.0), (0.01, 0.0), (0.0, -0.01), (0.007, 0.007)])):
        x, y = world.cell_centre(r, c)
        world.x, world.y = x + dx, y + dy
        sim.set_state(0, (r, c), layout_now.goal_cells, [])
        ours = costmap_to_observation(as_msg(world.local_costmap(3.0, in_odom=True)),
                                      robot_xy=compose(to_odom, (world.x, world.y, 0.0))[:2], goals_xy=goals,
                                      robot_yaw=math.pi / 2 - yaw, unknown="outside")
        np.testing.assert_array_equal(ours, sim.render_obs()[0], err_msg=f"cell {(r, c)}")


def test_identity_odom_costmap_is_the_map_frame_one():
    world = world_at("fourrooms", (2, 2))
    np.testing.assert_array_equal(world.local_costmap(3.0, in_odom=True).data, world.local_costmap(3.0).data)


# -- AMCL -------------------------------------------------------------------------------------------------
def test_amcl_publishes_on_an_initial_pose_then_only_after_motion():
    """Nav2 AMCL's rule: the filter updates when odometry moved more than update_min_d along
    x or along y (not the diagonal), or turned more than update_min_a, since its last update."""
    amcl = AmclUpdates(0.25, 0.2)
    assert not amcl.due((0.0, 0.0, 0.0)), "no pose before an initial pose"
    amcl.initial_pose((1.0, 1.0, 0.0))
    assert not amcl.due((1.0, 1.0, 0.0)) and not amcl.due((1.25, 1.0, 0.0)), "exactly 0.25 m is not more"
    assert not amcl.due((1.2, 1.2, 0.0)), "0.28 m diagonally: 0.2 along each axis"
    assert not amcl.due((1.0, 1.0, 0.2)) and not amcl.due((1.0, 1.0, -0.19))
    assert amcl.due((1.26, 1.0, 0.0))
    assert not amcl.due((1.4, 1.0, 0.0)), "measured from the last update"
    assert amcl.due((1.4, 1.0, -0.21)) and amcl.due((1.4, 0.7, -0.21))
    assert amcl.due((1.4, 0.7, math.pi)) and not amcl.due((1.4, 0.7, -math.pi + 0.1)), "yaw wraps"
    amcl.initial_pose((5.0, 5.0, 0.0))
    assert not amcl.due((5.1, 5.0, 0.0))


def test_amcl_on_the_robot_one_cell_is_not_enough():
    """One 0.25 m cell from the initial pose (the holonomic table's step) leaves AMCL silent,
    the second updates it; a robot standing still gets no update."""
    world = world_at("gridworld", (5, 3))
    amcl = AmclUpdates()
    amcl.initial_pose(world.odom_pose)
    updates = []
    for step in range(5):
        if step < 3:
            world.command(0.125, 0.0, 0.0, 2.0)
        for _ in range(25):
            world.advance(0.1)
            if amcl.due(world.odom_pose):
                updates.append(step)
    assert updates[0] == 1 and updates[-1] == 2


@pytest.mark.parametrize("kwargs, problem", [
    ({"map_to_odom": (0.0, 0.0)}, "map_to_odom"), ({"map_to_odom": (0.0, math.nan, 0.0)}, "map_to_odom"),
    ({"map_to_odom": "abc"}, "map_to_odom"), ({"odom_error": (0.1,)}, "odom_error"),
    ({"odom_error": (1.0, 0.0)}, "odom_error"), ({"start_yaw": math.inf}, "start_yaw"),
    ({"inflation_radius_m": -0.1}, "inflation_radius_m"), ({"cost_scaling_factor": "x"}, "cost_scaling_factor"),
])
def test_bad_nav2_arguments_name_the_argument(kwargs, problem):
    with pytest.raises(ValueError, match=problem):
        LoopbackWorld(**kwargs)
    with pytest.raises(ValueError, match="update_min_d"):
        AmclUpdates(-1.0, 0.2)
