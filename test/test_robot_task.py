"""The robot-side task and the robot graph's settings, without a ROS graph: ordered visits
(hdrqn_ros.robot.ordered_visits), the costmap drawing a robot step needs (places, the agent
off-centre, unknown as outside; on rclpy's messages), and the parameters of ``hdrqn robot`` /
robot.launch.py."""
import array

import numpy as np
import pytest

from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.gridworld import AGENT, GOAL0, OUTSIDE, PALETTE, GridWorldBatch
from hdrqn_ros.nodes.ros_messages import interface_class as message_class
from hdrqn_ros.nodes.nav import NavConfigError, SubgoalTable, costmap_to_observation, robot_pose
from hdrqn_ros.robot.episode_requests import EpisodeRequests
from hdrqn_ros.robot.ordered_visits import CellVisits, OrderedVisits
from hdrqn_ros.robot_graph import RobotRun, robot_parameters

from conftest import NEEDS_RCLPY

PLACES = [(1.0, 1.0), (2.0, 1.0), (2.0, 2.0)]


def test_visits_in_order_pay_one_and_terminate_with_success():
    task = OrderedVisits(3, tolerance_m=0.1, max_steps=50)
    task.start(PLACES)
    assert task.step((0.0, 0.0))["at_subgoal"] == NO_SUBGOAL
    first = task.step((1.05, 1.0))
    assert (first["at_subgoal"], first["collected"], first["extrinsic"], first["decision_point"]) == (0, True, 1.0, True)
    again = task.step((1.0, 1.02))  # still there: a place, not a new visit
    assert (again["at_subgoal"], again["collected"], again["extrinsic"]) == (0, False, 0.0)
    task.step((2.0, 1.0))
    last = task.step((2.0, 2.0))
    assert last["terminated"] and last["success"] and not last["decision_point"] and task.visits == [0, 1, 2]
    assert task.uncollected_xy() == [None, None, None]


def test_out_of_order_pays_a_hundredth_and_fails():
    task = OrderedVisits(2, tolerance_m=0.1, max_steps=50)
    task.start(PLACES[:2])
    wrong = task.step((2.0, 1.0))
    assert (wrong["collected"], wrong["extrinsic"]) == (True, pytest.approx(0.01))
    assert task.uncollected_xy() == [(1.0, 1.0), None]
    end = task.step((1.0, 1.0))
    assert end["terminated"] and not end["success"]


def test_step_limit_truncates_and_lethal_costs_one():
    task = OrderedVisits(2, tolerance_m=0.1, max_steps=2)
    task.start(PLACES[:2])
    assert task.step((0, 0), on_lethal=True)["classical"] == -1.0
    end = task.step((0, 0))
    assert end["truncated"] and not end["terminated"] and not end["decision_point"]


@pytest.mark.parametrize("kwargs, problem", [({"tolerance_m": 0.0}, "tolerance_m"), ({"max_steps": 0}, "max_steps")])
def test_bad_task_settings(kwargs, problem):
    with pytest.raises(ValueError, match=problem):
        OrderedVisits(2, **{"tolerance_m": 0.1, "max_steps": 5, **kwargs})


NEIGHBOURS = [(1.0, 1.0), (1.25, 1.25)]
"""Diagonal neighbours, 0.354 m apart: both within a 0.25 m tolerance of a point between them."""
STOP = (1.0 + 0.248 * 0.8, 1.0 + 0.248 * 0.6)
"""Where Nav2 stops when sent to place 0: 0.248 m from it, 0.097 m from place 1."""


def test_the_aimed_place_within_tolerance_is_where_the_robot_is():
    """A navigator sent to place 0 stops within its tolerance, nearer to place 1: the visit
    is place 0's (the option's), in order; without an aimed place the nearest counts."""
    task = OrderedVisits(2, tolerance_m=0.25, max_steps=50)
    task.start(NEIGHBOURS)
    assert task.where(STOP) == 1 and task.where(STOP, aimed=0) == 0 and task.where(STOP, aimed=1) == 1
    arrival = task.step(STOP, aimed=0)
    assert (arrival["at_subgoal"], arrival["collected"], arrival["extrinsic"]) == (0, True, 1.0)
    assert task.visits == [0] and task.in_order
    end = task.step(NEIGHBOURS[1], aimed=1)
    assert end["terminated"] and end["success"] and task.visits == [0, 1]


def test_an_aimed_place_out_of_tolerance_leaves_the_nearest():
    task = OrderedVisits(2, tolerance_m=0.25, max_steps=50)
    task.start(NEIGHBOURS)
    assert task.where(NEIGHBOURS[1], aimed=0) == 1  # 0.354 m from the aimed place
    assert task.where((3.0, 3.0), aimed=0) == NO_SUBGOAL
    with pytest.raises(ValueError, match="aimed must be a place 0..1"):
        task.where(STOP, aimed=2)


def test_cell_visits_are_unchanged_by_the_aimed_place():
    """Cells of places a cell apart never overlap: the robot is in one place's cell or none."""
    task = CellVisits(2, cell_m=0.25, max_steps=50)
    task.start([(1.0, 1.0), (1.25, 1.0)])
    for xy in [(1.1, 1.0), (1.13, 1.0), (1.2, 1.1), (1.0, 1.2)]:
        assert task.where(xy, aimed=0) == task.where(xy, aimed=1) == task.where(xy)
    assert task.where((1.1, 1.0), aimed=1) == 0 and task.where((1.0, 1.2), aimed=0) == NO_SUBGOAL


def test_episode_requests_one_each_start_or_back_to_back():
    one = EpisodeRequests(autostart=False)
    assert not one.wanted
    assert one.start(False, running=False, finished=False, episode=-1) == \
        (True, "episode 0 starts when the inputs are fresh")
    assert one.wanted
    one.started()
    assert not one.wanted, "one episode per start_episode: the request is cleared once it starts"
    assert one.start(False, running=True, finished=False, episode=0)[0] is False
    assert one.start(False, running=False, finished=True, episode=3) == (False, "finished: max_episodes reached")
    assert one.stop(running=True, episode=0) == (True, "episode 0 ends at the next step") and one.stop_requested
    one.ended()
    assert not one.stop_requested and not one.wanted
    auto = EpisodeRequests(autostart=True)
    assert auto.wanted and auto.stop(running=False, episode=-1) == (True, "no episode running") and not auto.wanted
    assert auto.start(True, False, False, 2) == (True, "episode 3 starts when the inputs are fresh (autostart: then "
                                                       "back to back)")
    auto.started()
    assert auto.wanted


def test_places_must_match_the_goal_count():
    with pytest.raises(ValueError, match="2 finite"):
        OrderedVisits(2, 0.1, 5).start(PLACES)


def grid(cost: np.ndarray, res=0.05, origin=(0.0, 0.0)):
    msg = message_class("nav_msgs/msg/OccupancyGrid")()
    msg.info.width, msg.info.height, msg.info.resolution = cost.shape[1], cost.shape[0], res
    msg.info.origin.position.x, msg.info.origin.position.y = origin
    msg.data = array.array("b", cost.astype(np.int8).tobytes())
    return msg


@NEEDS_RCLPY
def test_subgoal_image_draws_the_agent_where_it_is_and_skips_visited_places():
    """A window centred on a place: the place in its colour, the robot at its own cell, a
    visited place (None) not drawn; cells beyond the grid black with unknown='outside'."""
    msg = grid(np.zeros((40, 40)))
    centre = (1.0 - 0.125, 1.0 - 0.125)  # window cells of 0.25 m centred here
    image = costmap_to_observation(msg, robot_xy=centre, goals_xy=[centre, None], agent_xy=(centre[0] + 0.25,
                                                                                              centre[1]),
                                   unknown="outside")
    assert tuple(image[22, 22]) == tuple(PALETTE[GOAL0])
    assert tuple(image[22, 31]) == tuple(PALETTE[AGENT])  # one cell to the right
    corner = costmap_to_observation(msg, robot_xy=(0.125, 0.125), unknown="outside")
    assert tuple(corner[0, 0]) == tuple(PALETTE[OUTSIDE])
    with pytest.raises(ValueError, match="unknown"):
        costmap_to_observation(msg, unknown="free")


@NEEDS_RCLPY
def test_border_observation_matches_the_simulator_with_outside_black():
    """At the map's edge the simulator draws cells beyond the map black: so does a costmap
    of the map alone (unknown beyond it) with unknown='outside'."""
    env = GridWorldBatch(1, obstacles=False)
    env.reset(seed=0)
    env.set_state(0, (1, 1), [(9, 9), (9, 8)], np.zeros((0, 2)))
    cost = np.kron(env.walls[::-1].astype(np.int8) * 100, np.ones((5, 5), np.int8))
    ours = costmap_to_observation(grid(cost), robot_xy=(0.375, 2.375), unknown="outside")
    np.testing.assert_array_equal(ours, env.render_obs()[0])


@NEEDS_RCLPY
def test_robot_pose_reads_each_pose_type_and_refuses_non_finite():
    odom = message_class("nav_msgs/msg/Odometry")()
    odom.pose.pose.position.x, odom.pose.pose.orientation.z, odom.pose.pose.orientation.w = 1.5, 1.0, 0.0
    assert robot_pose(odom) == pytest.approx((1.5, 0.0, np.pi))
    amcl = message_class("geometry_msgs/msg/PoseWithCovarianceStamped")()
    amcl.pose.pose.position.y = -2.0
    assert robot_pose(amcl)[:2] == (0.0, -2.0)
    stamped = message_class("geometry_msgs/msg/PoseStamped")()
    stamped.pose.position.x = float("nan")
    with pytest.raises(NavConfigError, match="not finite"):
        robot_pose(stamped)


@NEEDS_RCLPY
def test_places_from_a_pose_array():
    msg = message_class("geometry_msgs/msg/PoseArray")()
    msg.header.frame_id = "map"
    msg.poses = [message_class("geometry_msgs/msg/Pose")() for _ in range(2)]
    msg.poses[1].position.x = 2.0
    table = SubgoalTable.from_pose_array(msg, 2, "/subgoal_poses")
    assert table.frame_id == "map" and table.poses[1][0] == 2.0
    with pytest.raises(NavConfigError, match="3 subgoals"):
        SubgoalTable.from_pose_array(msg, 3, "/subgoal_poses")


def test_robot_graph_parameters_by_mode():
    run = RobotRun(algo="hdrqn-v2", env="hdrqn/GridWorld-2Goals-v0", view="5", checkpoint="c.pt")
    drives = robot_parameters(run)
    assert drives["sub_controller"]["action_table"].endswith("actions_holonomic.yaml")
    assert drives["loopback_robot"]["lockstep"] == "control" and drives["critic"]["option_timeout"] == 0.0
    assert "subgoal_poses_topic" not in drives["meta_controller"] and drives["/**"]["use_sim_time"]
    run.mode = "meta-only"
    meta = robot_parameters(run)
    assert "action_table" not in meta["sub_controller"] and meta["meta_controller"]["subgoal_poses_topic"]
    assert meta["loopback_robot"]["lockstep"] == "action" and meta["critic"]["option_timeout"] > 0
    run.policy = "p"
    with pytest.raises(ValueError, match="exactly one"):
        robot_parameters(run)
