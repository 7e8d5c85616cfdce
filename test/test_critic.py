"""The internal critic (eq. 4.1 / 4.4): intrinsic reward and option termination."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hdrqn_ros.envs.critic import GRID_CRITIC, MONTEZUMA_CRITIC, InternalCritic, sub_controller_terminal
from hdrqn_ros.envs.domain import StepBatch
from hdrqn_ros.envs.gridworld import GridWorldBatch, GridWorldEnv

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3


def make_step(at, hit=None, term=None, trunc=None, life=None, collected=None):
    at = np.asarray(at, dtype=np.int32)
    n = len(at)
    z = np.zeros(n, dtype=bool)
    collected = at >= 0 if collected is None else np.asarray(collected, bool)
    return StepBatch(
        obs=np.zeros((n, 44, 44, 3), np.uint8), classical=np.zeros(n, np.float32), extrinsic=np.zeros(n, np.float32),
        terminated=z.copy() if term is None else np.asarray(term, bool),
        truncated=z.copy() if trunc is None else np.asarray(trunc, bool),
        agent_pos=np.zeros((n, 2), np.int32), at_subgoal=at, collected=collected,
        hit_obstacle=z.copy() if hit is None else np.asarray(hit, bool),
        life_lost=z.copy() if life is None else np.asarray(life, bool), success=z.copy(),
    )


def test_grid_critic_table():
    # rows: subgoal reached / other goal / obstacle / nothing / nothing but episode over / life lost
    step = make_step(at=[1, 0, -1, -1, -1, -1], hit=[0, 0, 1, 0, 0, 0], term=[0, 0, 0, 0, 1, 0],
                     life=[0, 0, 0, 0, 0, 1])
    res = GRID_CRITIC.evaluate(step, np.array([1, 1, 1, 1, 1, 1]))
    assert res.intrinsic.dtype == np.float32
    assert res.intrinsic.tolist() == [1.0, -1.0, -1.0, 0.0, 0.0, 0.0]
    assert res.reached.tolist() == [True, False, False, False, False, False]
    assert res.option_done.tolist() == [True, False, False, False, True, False]


def test_montezuma_critic_table():
    step = make_step(at=[3, 2, -1, -1], hit=[0, 0, 1, 0], life=[0, 0, 0, 1], trunc=[0, 0, 0, 0])
    res = MONTEZUMA_CRITIC.evaluate(step, np.array([3, 3, 3, 3]))
    assert res.intrinsic.tolist() == [1.0, 0.0, 0.0, 0.0]
    assert res.reached.tolist() == [True, False, False, False]
    assert res.option_done.tolist() == [True, False, False, True]


def test_sub_controller_terminal_table():
    """No bootstrap for the sub-controller: subgoal reached, episode terminated, or a death
    that ends the option (Montezuma); a step-limit cut or a plain step bootstraps."""
    # rows: reached / nothing / death / death at the step limit / step limit / game over /
    # reached while dying
    step = make_step(at=[3, -1, -1, -1, -1, -1, 3], life=[0, 0, 1, 1, 0, 1, 1], trunc=[0, 0, 0, 1, 1, 0, 0],
                     term=[0, 0, 0, 0, 0, 1, 0])
    res = MONTEZUMA_CRITIC.evaluate(step, np.full(7, 3))
    got = sub_controller_terminal(res.reached, step.terminated, step.life_lost, res.option_done)
    assert got.tolist() == [True, False, True, True, False, True, True]
    assert res.option_done.tolist() == [True, False, True, True, True, True, True]
    # a critic whose options a life loss does not end: a life loss alone is not terminal
    keep = InternalCritic(life_loss_ends_option=False).evaluate(step, np.full(7, 3))
    assert sub_controller_terminal(keep.reached, step.terminated, step.life_lost,
                                   keep.option_done)[[1, 2, 4]].tolist() == [False, False, False]


def test_critic_shape_mismatch():
    with pytest.raises(ValueError, match="shape"):
        GRID_CRITIC.evaluate(make_step(at=[0, 1]), np.array([0, 1, 2]))


def test_custom_critic_values():
    c = InternalCritic(2.0, -0.5, -3.0)
    res = c.evaluate(make_step(at=[0, 1, -1], hit=[0, 0, 1]), np.array([0, 0, 0]))
    assert res.intrinsic.tolist() == [2.0, -0.5, -3.0]


@pytest.mark.parametrize("subgoal,expected", [(0, 1.0), (1, -1.0)])
def test_grid_goal_intrinsic(subgoal, expected):
    """Collecting the blue goal: +1 when it is the option's subgoal, -1 when it is not."""
    b = GridWorldBatch(1)
    b.reset(seed=0)
    b.set_state(0, agent=(2, 2), goals=[(2, 3), (6, 6)], obstacles=[(8, 8), (8, 9)])
    s = b.step(np.array([RIGHT]))
    res = b.critic().evaluate(s, np.array([subgoal]))
    assert res.intrinsic.tolist() == [expected]
    assert res.reached.tolist() == [subgoal == 0] and res.option_done.tolist() == [subgoal == 0]
    env = GridWorldEnv()
    env.reset(seed=0)
    env.batch.set_state(0, agent=(2, 2), goals=[(2, 3), (6, 6)], obstacles=[(8, 8), (8, 9)])
    env.set_subgoal(subgoal)
    info = env.step(RIGHT)[-1]
    assert info["intrinsic"] == expected and info["subgoal_reached"] == (subgoal == 0)


def test_grid_obstacle_intrinsic_and_nothing():
    env = GridWorldEnv()
    env.reset(seed=0)
    env.batch.set_state(0, agent=(2, 2), goals=[(5, 5), (6, 6)], obstacles=[(2, 3), (8, 9)])
    info = env.step(RIGHT)[-1]
    assert info["hit_obstacle"] and info["intrinsic"] == -1.0 and not info["subgoal_reached"]
    info = env.step(DOWN)[-1]
    assert info["intrinsic"] == 0.0 and not info["subgoal_reached"] and not info["hit_obstacle"]


def test_single_env_subgoal_defaults_and_advances():
    env = GridWorldEnv(n_goals=3)
    env.reset(seed=0)
    assert env.subgoal == 0
    env.batch.set_state(0, agent=(2, 2), goals=[(2, 3), (2, 4), (2, 5)], obstacles=[(8, 8), (8, 9)])
    info = env.step(RIGHT)[-1]
    assert info["subgoal_reached"] and info["intrinsic"] == 1.0
    assert env.subgoal == 1  # the next goal in order
    env.set_subgoal(2)
    info = env.step(RIGHT)[-1]  # green while pursuing cyan
    assert info["intrinsic"] == -1.0 and not info["subgoal_reached"] and env.subgoal == 2


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), subgoals=st.lists(st.integers(0, 2), min_size=200, max_size=200),
       actions=st.lists(st.integers(0, 3), min_size=200, max_size=200))
def test_single_env_intrinsic_agrees_with_critic(seed, subgoals, actions):
    """The single env fills ``intrinsic``/``subgoal_reached`` exactly as GRID_CRITIC does."""
    env = GridWorldEnv(layout="fourrooms", n_goals=3, view=3)
    env.reset(seed=seed)
    for g, a in zip(subgoals, actions):
        env.set_subgoal(g)
        b = env.batch
        # replay the same step on a twin batch through the vectorised path
        twin = GridWorldBatch(1, layout="fourrooms", n_goals=3, view=3)
        twin.reset(seed=0)
        twin.set_state(0, agent=b.agent_pos[0], goals=b.goal_pos[0], obstacles=b.obstacle_pos[0],
                       collected=b.goals_collected[0], steps=int(b.steps[0]))
        twin._in_order[:] = b._in_order
        s = twin.step(np.array([a]))
        res = GRID_CRITIC.evaluate(s, np.array([g]))
        _, _, term, trunc, info = env.step(a)
        assert np.float32(info["intrinsic"]) == res.intrinsic[0]
        assert info["subgoal_reached"] == res.reached[0]
        if term or trunc:
            env.reset()


def test_walking_over_a_collected_goal_is_not_penalised_but_reaches_it_as_a_subgoal():
    # the agent stands on goal 0's old cell (collected earlier): no penalty for option 1,
    # and an option whose subgoal is goal 0 ends with +1 (a subgoal is a place)
    step = make_step(at=[0, 0], collected=[False, False])
    r = GRID_CRITIC.evaluate(step, np.array([1, 0]))
    assert r.intrinsic.tolist() == [0.0, 1.0]
    assert r.reached.tolist() == [False, True]
