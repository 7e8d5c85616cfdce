"""Nav2 adapters (hdrqn_ros.nodes.nav): tables from YAML, messages, costmap -> observation.
Messages are rclpy's (skipped where rclpy cannot be imported)."""
import array
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from hdrqn_ros.envs.gridworld import AGENT, FREE, GOAL0, PALETTE, WALL, GridWorldBatch  # noqa: E402
from hdrqn_ros.nodes.nav import (OCCUPANCY_GRID, TWIST, TWIST_STAMPED, ActionTable, NavConfigError,  # noqa: E402
                                 SubgoalTable, costmap_to_observation)
from hdrqn_ros.nodes.ros_messages import interface_class as message_class  # noqa: E402
from hdrqn_ros.nodes.ros_messages import pack  # noqa: E402
from hdrqn_ros.recording.bag_format import TYPESTORE  # noqa: E402

CONFIG = Path(__file__).parents[1] / "config"
FREE_RGB, WALL_RGB, AGENT_RGB = (tuple(PALETTE[c]) for c in (FREE, WALL, AGENT))


def write(tmp_path, text, name="table.yaml"):
    p = tmp_path / name
    p.write_text(text, encoding="utf-8")
    return p


# --------------------------------------------------------------------------- tables
def test_shipped_tables_load():
    sub = SubgoalTable.load(CONFIG / "nav2/subgoals.yaml", num_subgoals=2)
    assert len(sub) == 2 and sub.frame_id == "map"
    assert sub.poses[1] == (3.5, -1.0, 1.57)
    act = ActionTable.load(CONFIG / "nav2/actions.yaml", num_actions=4)
    assert len(act) == 4 and not act.stamped and act.type_name == TWIST
    up, down, left, right = act.commands
    assert up["linear_x"] > 0 > down["linear_x"] and left["angular_z"] > 0 > right["angular_z"]


GOOD_SUBGOALS = "frame_id: map\nsubgoals:\n  - {x: 1.0, y: 2.0, yaw: 0.0}\n  - {x: 3, y: -1}\n"


@pytest.mark.parametrize("text, problem", [
    ("subgoals: [", "not valid YAML"),
    ("- {x: 1, y: 2}\n", "top level must be a mapping"),
    ("frame_id: map\n", r"missing key\(s\) \['subgoals'\]"),
    ("subgoals: []\n", "non-empty list"),
    ("subgoals:\n  - {x: 1.0}\n  - {x: 1, y: 2}\n", r"subgoals\[0\]: missing key\(s\) \['y'\]"),
    ("subgoals:\n  - {x: 1, y: two}\n  - {x: 1, y: 2}\n", r"subgoals\[0\]: y must be a finite number, got 'two'"),
    ("subgoals:\n  - {x: 1, y: 2}\n  - {x: true, y: 2}\n", r"subgoals\[1\]: x must be a finite number"),
    ("subgoals:\n  - {x: 1, y: .nan}\n  - {x: 1, y: 2}\n", "finite number"),
    ("subgoals:\n  - {x: 1, y: 2, yaw_deg: 90}\n  - {x: 1, y: 2}\n", r"unknown key\(s\) \['yaw_deg'\]"),
    ("subgoals:\n  - [1, 2]\n  - {x: 1, y: 2}\n", r"subgoals\[0\] must be a mapping"),
    ("subgoals:\n  - {x: 1, y: 2}\n", "has 1 entries but the agent has 2"),
    ("frame_id: ''\n" + GOOD_SUBGOALS.split("\n", 1)[1], "frame_id must be a non-empty string"),
    ("frames: map\n" + GOOD_SUBGOALS, r"unknown key\(s\) \['frames'\]"),
])
def test_bad_subgoal_table_names_file_and_problem(tmp_path, text, problem):
    path = write(tmp_path, text, "my_subgoals.yaml")
    with pytest.raises(NavConfigError, match=problem) as err:
        SubgoalTable.load(path, num_subgoals=2)
    assert str(path) in str(err.value)
    assert isinstance(err.value, ValueError)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(NavConfigError, match=r"cannot read .*nope\.yaml"):
        SubgoalTable.load(tmp_path / "nope.yaml")


def test_subgoal_count_is_checked_only_when_given(tmp_path):
    assert len(SubgoalTable.load(write(tmp_path, GOOD_SUBGOALS))) == 2


@pytest.mark.parametrize("text, problem", [
    ("actions:\n  - {linear_x: 0.2}\n", "has 1 entries but the agent has 2"),
    ("stamped: maybe\nactions:\n  - {}\n  - {}\n", "stamped must be true or false"),
    ("actions:\n  - {linear_x: fast}\n  - {}\n", r"actions\[0\]: linear_x must be a finite number"),
    ("actions:\n  - {linear_xx: 0.2}\n  - {}\n", r"actions\[0\]: unknown key\(s\) \['linear_xx'\]"),
    ("actions: {up: 1}\n", "actions must be a non-empty list"),
])
def test_bad_action_table_names_file_and_problem(tmp_path, text, problem):
    path = write(tmp_path, text, "my_actions.yaml")
    with pytest.raises(NavConfigError, match=problem) as err:
        ActionTable.load(path, num_actions=2)
    assert str(path) in str(err.value)


# --------------------------------------------------------------------------- messages
@pytest.mark.parametrize("yaw", [0.0, 0.5, math.pi / 2, math.pi, -math.pi / 2, -3.0])
def test_quaternion_from_yaw(yaw):
    q = SubgoalTable([(1.0, 2.0, yaw)]).pose_msg(0).pose.orientation
    assert (q.x, q.y) == (0.0, 0.0)
    assert math.isclose(q.x**2 + q.y**2 + q.z**2 + q.w**2, 1.0)
    back = math.atan2(2 * q.w * q.z, 1 - 2 * q.z**2)
    assert math.isclose(math.remainder(back - yaw, 2 * math.pi), 0.0, abs_tol=1e-12)


def test_pose_msg_fields_and_index_checks():
    table = SubgoalTable([(1.0, 2.0, 0.0), (3.5, -1.0, 1.57)], frame_id="map")
    m = table.pose_msg(1, stamp=(12, 34))
    assert isinstance(m, message_class("geometry_msgs/msg/PoseStamped"))
    assert (m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec) == ("map", 12, 34)
    assert (m.pose.position.x, m.pose.position.y, m.pose.position.z) == (3.5, -1.0, 0.0)
    for bad in (2, -1, True, 1.0):
        with pytest.raises(IndexError, match=r"subgoal must be an integer in \[0, 2\)"):
            table.pose_msg(bad)


def test_twist_or_twist_stamped():
    cmds = [{"linear_x": 0.2}, {"angular_z": -0.8, "linear_y": 0.1}]
    plain = ActionTable(cmds, stamped=False)
    m = plain.twist_msg(1, stamp=(5, 6))
    assert plain.type_name == TWIST and isinstance(m, message_class(TWIST))
    assert (m.linear.x, m.linear.y, m.angular.z) == (0.0, 0.1, -0.8)
    stamped = ActionTable(cmds, stamped=True, frame_id="base_footprint")
    s = stamped.twist_msg(0, stamp=7_250_000_000)  # integer nanoseconds
    assert stamped.type_name == TWIST_STAMPED and isinstance(s, message_class(TWIST_STAMPED))
    assert (s.header.stamp.sec, s.header.stamp.nanosec, s.header.frame_id) == (7, 250_000_000, "base_footprint")
    assert s.twist.linear.x == 0.2
    assert stamped.twist_msg(0, stamp=(1, 2)).header.stamp.nanosec == 2
    with pytest.raises(IndexError, match="action"):
        plain.twist_msg(2)


@pytest.mark.parametrize("stamped", [False, True])
def test_stop_msg_is_all_zero(stamped):
    m = ActionTable([{"linear_x": 0.2, "angular_z": 1.0}], stamped=stamped).stop_msg((1, 0))
    t = m.twist if stamped else m
    assert [t.linear.x, t.linear.y, t.linear.z, t.angular.x, t.angular.y, t.angular.z] == [0.0] * 6


def test_messages_serialize_like_ros():
    """Built messages serialize and round-trip; rosbags (the bags' codec) reads the bytes and
    re-encodes them to as many bytes, which rclpy reads back as the same message."""
    sub = SubgoalTable([(1.0, 2.0, 0.3)])
    act = ActionTable([{"linear_x": 0.2, "angular_z": 0.5}], stamped=True)
    msgs = [sub.pose_msg(0, (1, 2)), act.twist_msg(0, (3, 4)), act.stop_msg(),
            ActionTable([{"linear_x": 0.2}]).twist_msg(0)]
    for m in msgs:
        raw = serialize_message(m)
        assert deserialize_message(raw, type(m)) == m
        type_name = f"{type(m).__module__.split('.')[0]}/msg/{type(m).__name__}"
        theirs = bytes(TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(raw, type_name), type_name))
        assert len(theirs) == len(raw) and deserialize_message(theirs, type(m)) == m, type_name


# --------------------------------------------------------------------------- costmap
def grid(cost: np.ndarray, res=0.05, origin=(0.0, 0.0)):
    """An OccupancyGrid message from a (height, width) cost array (row 0 = lowest y)."""
    m = message_class
    h, w = cost.shape
    info = m("nav_msgs/msg/MapMetaData")(resolution=res, width=w, height=h, origin=m("geometry_msgs/msg/Pose")(
        position=m("geometry_msgs/msg/Point")(x=origin[0], y=origin[1], z=0.0),
        orientation=m("geometry_msgs/msg/Quaternion")(w=1.0)))
    return m(OCCUPANCY_GRID)(info=info, data=pack(np.ascontiguousarray(cost, dtype=np.int8).reshape(-1)))


def colours(obs):
    """The 5x5 cell colours of a 44x44 observation (sampled at each cell's first pixel)."""
    starts = [0, 9, 18, 27, 36]  # pixel i shows cell floor(i * 5 / 44)
    return [[tuple(obs[r, c]) for c in starts] for r in starts]


def test_free_costmap_shows_free_cells_and_the_agent():
    obs = costmap_to_observation(grid(np.zeros((60, 60))))
    assert obs.shape == (44, 44, 3) and obs.dtype == np.uint8
    cells = colours(obs)
    assert cells[2][2] == AGENT_RGB
    assert sum(row.count(FREE_RGB) for row in cells) == 24


# Default robot position on a 60x60, 0.05 m grid: centre of cell (30, 30) = (1.525, 1.525) m.
# Window columns (0.25 m grid cells): x in [0.9, 1.15), [1.15, 1.4), [1.4, 1.65), [1.65, 1.9), [1.9, 2.15),
# i.e. costmap columns 18-22, 23-27, 28-32, 33-37, 38-42.
def test_wall_to_the_right_shows_in_the_right_part():
    cost = np.zeros((60, 60))
    cost[:, 38:] = 100  # a wall at x >= 1.9 m
    cost[:, 33:38] = 64  # below the lethal threshold: free
    obs = costmap_to_observation(grid(cost))
    assert (obs[:, 36:] == WALL_RGB).all()  # pixel columns 36..43 show window column 4
    left = obs[:, :36].reshape(-1, 3)
    agent = (left == AGENT_RGB).all(axis=1)
    assert agent.sum() == 9 * 9 and (left[~agent] == FREE_RGB).all()


def test_lethal_cells_and_unknown_are_walls():
    for value in (100, -1):
        cost = np.zeros((60, 60))
        cost[:, 40:] = value  # x >= 2.0 m: window column 4 is partly blocked, which blocks it
        cells = colours(costmap_to_observation(grid(cost)))
        assert [row[4] for row in cells] == [WALL_RGB] * 5, value
        assert all(row[c] in (FREE_RGB, AGENT_RGB) for row in cells for c in range(4)), value
    cost = np.zeros((60, 60))
    cost[:, 40:] = 99  # Nav2's inscribed and inflation costs lie beside walls, in cells the robot may reach
    assert colours(costmap_to_observation(grid(cost)))[0][4] == FREE_RGB
    assert colours(costmap_to_observation(grid(cost), lethal=50))[0][4] == WALL_RGB
    cost[:, 43:] = 100  # beyond the window
    assert all(FREE_RGB in row for row in colours(costmap_to_observation(grid(cost))))


def test_unknown_costmap_is_all_walls():
    cells = colours(costmap_to_observation(grid(np.full((60, 60), -1))))
    assert sum(row.count(WALL_RGB) for row in cells) == 24 and cells[2][2] == AGENT_RGB


def test_heading_up_rotates_the_view():
    cost = np.zeros((60, 60))
    cost[:, 40:] = 100  # wall at +x
    north_up = colours(costmap_to_observation(grid(cost)))
    facing_x = colours(costmap_to_observation(grid(cost), robot_yaw=0.0))  # wall ahead -> top row
    facing_y = colours(costmap_to_observation(grid(cost), robot_yaw=math.pi / 2))
    assert facing_x[0] == [WALL_RGB] * 5 and facing_x[4] == [FREE_RGB] * 5
    assert facing_y == north_up
    facing_minus_y = colours(costmap_to_observation(grid(cost), robot_yaw=-math.pi / 2))  # +x is on the left
    assert [row[0] for row in facing_minus_y] == [WALL_RGB] * 5


def test_outside_the_grid_is_wall_and_robot_xy_moves_the_window():
    cells = colours(costmap_to_observation(grid(np.zeros((60, 60))), robot_xy=(0.1, 1.5)))
    assert [row[0] for row in cells] == [WALL_RGB] * 5 and [row[1] for row in cells] == [WALL_RGB] * 5
    assert cells[2][3] == FREE_RGB


def test_origin_offset_and_rclpy_style_data():
    cost = np.zeros((60, 60))
    cost[:, 40:] = 100
    msg = grid(cost, origin=(-10.0, 5.0))
    assert isinstance(msg.data, array.array)  # what rclpy gives
    cells = colours(costmap_to_observation(msg, robot_xy=(-8.475, 6.525)))
    assert [row[4] for row in cells] == [WALL_RGB] * 5


@pytest.mark.parametrize("layout, agent, view, goals", [
    ("gridworld", (2, 2), 5, [(9, 9), (9, 8)]), ("fourrooms", (4, 4), 5, [(9, 9), (9, 8)]),
    ("fourrooms", (4, 6), 3, [(9, 9), (9, 8)]), ("fourrooms", (5, 3), 5, [(9, 9), (9, 8)]),
    ("gridworld", (3, 3), 5, [(2, 4), (5, 2)]), ("fourrooms", (7, 7), 5, [(8, 9), (6, 6)]),
])
def test_matches_the_simulator_observation(layout, agent, view, goals):
    """A costmap drawn from the simulator's walls (5 costmap cells per grid cell), with the
    goals at their cells' centres, gives the simulator's own observation, pixel for pixel."""
    env = GridWorldBatch(1, layout=layout, view=view)
    env.reset(seed=0)
    env.set_state(0, agent, goals, [(9, 1), (1, 9)])  # fires out of view
    k, res = 5, 0.05
    walls = env.walls[::-1]  # costmap row 0 = map row 10 (image up = +y)
    cost = np.kron(walls.astype(np.int8) * 100, np.ones((k, k), np.int8))

    def xy(rc):
        return (rc[1] + 0.5) * k * res, (10 - rc[0] + 0.5) * k * res

    ours = costmap_to_observation(grid(cost, res=res), robot_xy=xy(agent), view_cells=view,
                                  goals_xy=[xy(g) for g in goals])
    np.testing.assert_array_equal(ours, env.render_obs()[0])


def test_goals_are_drawn_in_their_colours_when_in_view():
    msg = grid(np.zeros((60, 60)))
    robot = (1.525, 1.525)
    goals = [(robot[0] + 0.25, robot[1]), (robot[0], robot[1] + 0.5), (robot[0] + 2.0, robot[1])]
    cells = colours(costmap_to_observation(msg, goals_xy=goals))
    assert cells[2][3] == tuple(PALETTE[GOAL0]) and cells[0][2] == tuple(PALETTE[GOAL0 + 1])
    assert sum(row.count(tuple(PALETTE[GOAL0 + 2])) for row in cells) == 0  # out of view
    facing_x = colours(costmap_to_observation(msg, goals_xy=goals[:2], robot_yaw=0.0))
    assert facing_x[1][2] == tuple(PALETTE[GOAL0]) and facing_x[2][0] == tuple(PALETTE[GOAL0 + 1])
    with pytest.raises(ValueError, match="at most 3 goals"):
        costmap_to_observation(msg, goals_xy=[robot] * 4)


def test_deserialized_costmap_gives_the_same_observation():
    cost = np.zeros((60, 60))
    cost[10:20, 35:] = 100
    cost[:5] = -1
    msg = grid(cost)
    back = deserialize_message(serialize_message(msg), type(msg))
    np.testing.assert_array_equal(costmap_to_observation(back), costmap_to_observation(msg))


@pytest.mark.parametrize("kwargs, problem", [
    ({"msg": grid(np.zeros((4, 4)), res=0.0)}, "resolution must be positive"),
    ({"msg": grid(np.zeros((4, 4))), "view_cells": 4}, "view_cells must be a positive odd integer"),
    ({"msg": grid(np.zeros((4, 4))), "view_cells": -3}, "view_cells must be a positive odd integer"),
    ({"msg": grid(np.zeros((4, 4))), "lethal": 0}, "lethal must be in"),
    ({"msg": grid(np.zeros((4, 4))), "cell_size_m": -1.0}, "cell_size_m must be positive"),
])
def test_bad_costmap_arguments(kwargs, problem):
    with pytest.raises(ValueError, match=problem):
        costmap_to_observation(**kwargs)


def test_costmap_size_mismatch_is_a_clear_error():
    msg = grid(np.zeros((4, 4)))
    msg.info.width = 5
    with pytest.raises(NavConfigError, match="costmap is 5x4 cells but has 16 data values"):
        costmap_to_observation(msg)


def test_a_costmap_origin_that_is_not_finite_is_a_clear_error():
    msg = grid(np.zeros((4, 4)))
    msg.info.origin.position.x = float("nan")
    with pytest.raises(NavConfigError, match=r"costmap origin must be finite, got \(nan, "):
        costmap_to_observation(msg)
