"""Multiple goals in gridworld / four-rooms: rules, rendering, vectorisation, seeding."""
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st

import hdrqn_ros  # noqa: F401  (registers the ids)
from hdrqn_ros.envs.gridworld import GridWorldBatch, GridWorldEnv
from hdrqn_ros.envs.registration import GRID_IDS, make_batch

UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3
WHITE, GREY, BLACK = (255, 255, 255), (128, 128, 128), (0, 0, 0)
BLUE, GREEN, CYAN, RED = (0, 0, 255), (0, 255, 0), (0, 255, 255), (255, 0, 0)
GOAL_COLOURS = [BLUE, GREEN, CYAN]
DOORS = {(3, 5), (7, 5), (5, 3), (5, 7)}


def expected_walls(layout):
    """The wall cells, written out independently of the implementation."""
    walls = set()
    for r in range(11):
        for c in range(11):
            if r in (0, 10) or c in (0, 10):
                walls.add((r, c))
            elif layout == "fourrooms" and (r == 5 or c == 5) and (r, c) not in DOORS:
                walls.add((r, c))
    return walls


def batch1(layout="gridworld", n_goals=2, view=5, **kw):
    b = GridWorldBatch(1, layout=layout, n_goals=n_goals, view=view, **kw)
    b.reset(seed=0)
    return b


def step1(b, a):
    return b.step(np.array([a]))


# ----------------------------------------------------------------------------- gym API
@pytest.mark.parametrize("env_id", sorted(GRID_IDS))
@pytest.mark.parametrize("view", [3, 5, 11, "full"])
def test_check_env(env_id, view):
    env = gym.make(env_id, view=view, render_mode="rgb_array").unwrapped
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env)
    assert env.observation_space == gym.spaces.Box(0, 255, (44, 44, 3), np.uint8)
    assert env.action_space == gym.spaces.Discrete(4)
    img = env.render()
    assert img.shape == (11 * 32, 11 * 32, 3) and img.dtype == np.uint8


def test_registered_kwargs_and_make_batch():
    for env_id, kw in GRID_IDS.items():
        env = gym.make(env_id).unwrapped
        assert env.batch.layout == kw["layout"] and env.batch.n_goals == kw["n_goals"]
        b = make_batch(env_id, num_envs=3, view=3)
        assert (b.num_envs, b.num_actions, b.num_subgoals, b.view) == (3, 4, kw["n_goals"], 3)
        obs = b.reset(seed=1)
        assert obs.shape == (3, 44, 44, 3) and obs.dtype == np.uint8


def test_info_keys_and_types():
    env = GridWorldEnv()
    obs, info = env.reset(seed=3)
    assert obs.shape == (44, 44, 3) and obs.dtype == np.uint8
    keys = {"extrinsic", "classical", "intrinsic", "subgoal_reached", "at_subgoal", "hit_obstacle",
            "life_lost", "agent_pos", "success"}
    assert keys <= set(info)
    obs, r, term, trunc, info = env.step(0)
    assert keys <= set(info)
    assert r == info["classical"]
    assert info["life_lost"] is False
    assert info["agent_pos"].dtype == np.int32 and info["agent_pos"].shape == (2,)


# ----------------------------------------------------------------------------- layout
@pytest.mark.parametrize("layout", ["gridworld", "fourrooms"])
def test_walls_and_doors(layout):
    b = batch1(layout)
    walls = expected_walls(layout)
    codes = b.codes()[0]
    for r in range(11):
        for c in range(11):
            assert bool(b.walls[r, c]) == ((r, c) in walls), (r, c)
            assert (codes[r, c] == 1) == ((r, c) in walls), (r, c)
    assert len(walls) == (40 if layout == "gridworld" else 40 + 13)


def test_fourrooms_door_passage_and_wall_block():
    b = batch1("fourrooms")
    # through the door (3, 5) from the left room into the right room
    b.set_state(0, agent=(3, 4), goals=[(9, 9), (9, 8)], obstacles=[(1, 1), (1, 2)])
    s = step1(b, RIGHT)
    assert s.agent_pos[0].tolist() == [3, 5]
    s = step1(b, RIGHT)
    assert s.agent_pos[0].tolist() == [3, 6]
    # the cross wall at (2, 5) blocks
    b.set_state(0, agent=(2, 4), goals=[(9, 9), (9, 8)], obstacles=[(1, 1), (1, 2)])
    s = step1(b, RIGHT)
    assert s.agent_pos[0].tolist() == [2, 4]
    assert s.classical[0] == 0 and s.extrinsic[0] == 0 and not s.hit_obstacle[0]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), layout=st.sampled_from(["gridworld", "fourrooms"]), n_goals=st.sampled_from([2, 3]))
def test_reset_places_objects_on_distinct_free_cells(seed, layout, n_goals):
    b = GridWorldBatch(4, layout=layout, n_goals=n_goals)
    b.reset(seed=seed)
    walls = expected_walls(layout)
    for i in range(4):
        cells = [tuple(b.agent_pos[i])] + [tuple(p) for p in b.goal_pos[i]] + [tuple(p) for p in b.obstacle_pos[i]]
        assert len(cells) == 1 + n_goals + 2
        assert len(set(cells)) == len(cells)
        assert not any(c in walls for c in cells)
        assert all(0 < r < 10 and 0 < c < 10 for r, c in cells)
    assert not b.goals_collected.any() and (b.next_goal == 0).all() and (b.steps == 0).all()


# ----------------------------------------------------------------------------- rewards
def test_moves_and_wall_bump():
    b = batch1()
    b.set_state(0, agent=(5, 5), goals=[(9, 9), (9, 8)], obstacles=[(1, 9), (2, 9)])
    for a, pos in [(UP, (4, 5)), (DOWN, (5, 5)), (LEFT, (5, 4)), (RIGHT, (5, 5))]:
        s = step1(b, a)
        assert tuple(s.agent_pos[0]) == pos
    b.set_state(0, agent=(1, 1), goals=[(9, 9), (9, 8)], obstacles=[(1, 9), (2, 9)])
    for a in (UP, LEFT):
        s = step1(b, a)
        assert tuple(s.agent_pos[0]) == (1, 1)
        assert s.classical[0] == 0 and s.extrinsic[0] == 0
        assert not s.hit_obstacle[0] and s.at_subgoal[0] == -1
        assert not s.terminated[0] and not s.truncated[0]


@pytest.mark.parametrize("single", [False, True])
def test_right_order_goals(single):
    env = GridWorldEnv(n_goals=2)
    env.reset(seed=0)
    b = env.batch
    b.set_state(0, agent=(2, 2), goals=[(2, 3), (2, 5)], obstacles=[(8, 8), (8, 9)])

    def do(a):
        if single:
            _, r, term, trunc, info = env.step(a)
            return r, info["extrinsic"], info["at_subgoal"], term, trunc, info["success"]
        s = step1(b, a)
        return (s.classical[0], s.extrinsic[0], s.at_subgoal[0], s.terminated[0], s.truncated[0], s.success[0])

    r, ex, at, term, trunc, _ = do(RIGHT)
    assert (r, ex, at, term, trunc) == (1.0, 1.0, 0, False, False)
    assert b.goals_collected[0].tolist() == [True, False] and b.next_goal[0] == 1
    r, ex, at, term, _, _ = do(RIGHT)  # the collected goal's cell is empty now
    assert (r, ex, at, term) == (0.0, 0.0, -1, False)
    assert b.codes()[0][2, 3] == 0
    r, ex, at, term, trunc, success = do(RIGHT)
    assert (r, ex, at, term, trunc, success) == (1.0, 1.0, 1, True, False, True)
    with pytest.raises(RuntimeError):
        do(LEFT)


@pytest.mark.parametrize("single", [False, True])
def test_wrong_order_goals(single):
    env = GridWorldEnv(n_goals=2)
    env.reset(seed=0)
    b = env.batch
    b.set_state(0, agent=(2, 4), goals=[(2, 3), (2, 5)], obstacles=[(8, 8), (8, 9)])

    def do(a):
        if single:
            _, r, term, trunc, info = env.step(a)
            return r, info["extrinsic"], info["at_subgoal"], term, info["success"]
        s = step1(b, a)
        return s.classical[0], s.extrinsic[0], s.at_subgoal[0], s.terminated[0], s.success[0]

    r, ex, at, term, _ = do(RIGHT)  # green before blue
    assert r == pytest.approx(0.01) and ex == pytest.approx(0.01) and at == 1 and not term
    assert np.float32(r) == np.float32(0.01)
    assert b.next_goal[0] == 0 and not b.in_order[0]
    do(LEFT)
    r, ex, at, term, success = do(LEFT)  # blue after green: still improper order
    assert r == pytest.approx(0.01) and ex == pytest.approx(0.01) and at == 0
    assert term and not success


def test_three_goals_order_rewards():
    b = batch1(n_goals=3)
    # blue, green, cyan in a row: 1, 1, 1 and success
    b.set_state(0, agent=(2, 2), goals=[(2, 3), (2, 4), (2, 5)], obstacles=[(8, 8), (8, 9)])
    got = [float(step1(b, RIGHT).extrinsic[0]) for _ in range(2)]
    s = step1(b, RIGHT)
    assert got + [float(s.extrinsic[0])] == [1.0, 1.0, 1.0] and s.terminated[0] and s.success[0]
    # green first: 0.01; then blue: 0.01 (green already taken); then cyan after both: 1 (author's rule)
    b.set_state(0, agent=(2, 3), goals=[(2, 2), (2, 4), (2, 6)], obstacles=[(8, 8), (8, 9)])
    s1 = step1(b, RIGHT)  # green
    step1(b, LEFT)
    s2 = step1(b, LEFT)  # blue
    assert (s1.at_subgoal[0], s2.at_subgoal[0]) == (1, 0)
    assert np.allclose([s1.extrinsic[0], s2.extrinsic[0]], [0.01, 0.01])
    assert b.next_goal[0] == 2
    for _ in range(3):
        step1(b, RIGHT)
    s3 = step1(b, RIGHT)
    assert s3.at_subgoal[0] == 2 and s3.extrinsic[0] == 1.0 and s3.terminated[0] and not s3.success[0]
    # cyan first then blue: blue is improper (a later goal is already collected)
    b.set_state(0, agent=(2, 3), goals=[(2, 2), (7, 7), (2, 4)], obstacles=[(8, 8), (8, 9)])
    assert step1(b, RIGHT).extrinsic[0] == np.float32(0.01)
    step1(b, LEFT)
    assert step1(b, LEFT).extrinsic[0] == np.float32(0.01)


@pytest.mark.parametrize("single", [False, True])
@pytest.mark.parametrize("layout", ["gridworld", "fourrooms"])
def test_obstacle_hit_and_respawn(single, layout):
    env = GridWorldEnv(layout=layout, n_goals=3)
    env.reset(seed=0)
    b = env.batch
    walls = expected_walls(layout)
    for k in range(60):
        env.reset(seed=k)
        b.set_state(0, agent=(1, 1), goals=[(2, 2), (3, 3), (4, 4)], obstacles=[(1, 2), (9, 9)])
        if single:
            _, r, term, trunc, info = env.step(RIGHT)
            ex, hit, at = info["extrinsic"], info["hit_obstacle"], info["at_subgoal"]
        else:
            s = step1(b, RIGHT)
            r, ex, hit, at, term, trunc = (s.classical[0], s.extrinsic[0], s.hit_obstacle[0], s.at_subgoal[0],
                                           s.terminated[0], s.truncated[0])
        assert (r, ex, hit, at, term, trunc) == (-1.0, 0.0, True, -1, False, False)
        assert tuple(b.agent_pos[0]) == (1, 2)
        fires = [tuple(p) for p in b.obstacle_pos[0]]
        assert fires[1] == (9, 9)
        new = fires[0]
        assert new not in walls and new not in {(1, 2), (9, 9), (2, 2), (3, 3), (4, 4)}
        assert b.codes()[0][new] == 5
        assert (b.codes()[0] == 5).sum() == 2
    # respawns may land on the cell of a collected goal, never on a live one
    seen = set()
    for k in range(200):
        env.reset(seed=k)
        b.set_state(0, agent=(1, 1), goals=[(2, 2), (3, 3), (4, 4)], obstacles=[(1, 2), (9, 9)])
        step1(b, RIGHT)
        seen.add(tuple(b.obstacle_pos[0][0]))
    free = {(r, c) for r in range(11) for c in range(11)} - walls - {(1, 2), (9, 9), (2, 2), (3, 3), (4, 4)}
    assert seen <= free and len(seen) > len(free) // 2  # uniform-ish over the free cells


def test_step_on_done_env_raises():
    b = GridWorldBatch(2)
    with pytest.raises(RuntimeError):
        b.step(np.array([0, 0]))  # never reset
    b.reset(seed=0)
    b.set_state(1, agent=(2, 2), goals=[(2, 3), (2, 4)], obstacles=[(8, 8), (8, 9)])
    b.step(np.array([UP, RIGHT]))
    s = b.step(np.array([UP, RIGHT]))
    assert s.terminated.tolist() == [False, True]
    with pytest.raises(RuntimeError, match=r"\[1\]"):
        b.step(np.array([UP, RIGHT]))
    obs = b.reset_where(s.done)
    assert obs.shape == (2, 44, 44, 3)
    b.step(np.array([UP, RIGHT]))


@pytest.mark.parametrize(
    "env_id,limit", [("hdrqn/GridWorld-2Goals-v0", 50), ("hdrqn/GridWorld-3Goals-v0", 50),
                     ("hdrqn/FourRooms-2Goals-v0", 50), ("hdrqn/FourRooms-3Goals-v0", 100)])
def test_step_limits(env_id, limit):
    b = make_batch(env_id, num_envs=2)
    assert b.max_steps == limit
    b.reset(seed=0)
    G = b.n_goals
    goals = [(9, 9), (9, 8), (8, 9)][:G]
    for i in range(2):
        b.set_state(i, agent=(1, 1), goals=goals, obstacles=[(9, 1), (8, 1)])
    for t in range(1, limit + 1):
        s = b.step(np.array([UP, LEFT]))  # bump walls forever
        assert not s.terminated.any()
        assert s.truncated.all() == (t == limit) and s.truncated.any() == (t == limit)
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    env.batch.set_state(0, agent=(1, 1), goals=goals, obstacles=[(9, 1), (8, 1)])
    truncs = [env.step(UP)[3] for _ in range(limit)]
    assert truncs == [False] * (limit - 1) + [True]


def test_max_steps_override():
    b = GridWorldBatch(1, max_steps=3)
    b.reset(seed=0)
    b.set_state(0, agent=(1, 1), goals=[(9, 9), (9, 8)], obstacles=[(9, 1), (8, 1)])
    assert [bool(b.step(np.array([UP])).truncated[0]) for _ in range(3)] == [False, False, True]
    env = GridWorldEnv(max_steps=7)
    assert env.batch.max_steps == 7


# ----------------------------------------------------------------------------- rendering
def expected_image(layout, agent, goals, fires, collected, view, center=None):
    """Render independently: cell colours, then pixel (y, x) shows cell floor(y*v/44)."""
    walls = expected_walls(layout)
    colour = {}
    for r in range(11):
        for c in range(11):
            colour[(r, c)] = GREY if (r, c) in walls else WHITE
    for g, p in enumerate(goals):
        if not collected[g]:
            colour[tuple(p)] = GOAL_COLOURS[g]
    for p in fires:
        colour[tuple(p)] = RED
    colour[tuple(agent)] = BLACK
    center = tuple(agent) if center is None else tuple(center)
    if view == "full":
        v, top, left = 11, 0, 0
    else:
        v = view
        top, left = center[0] - v // 2, center[1] - v // 2
    img = np.zeros((44, 44, 3), dtype=np.uint8)
    for y in range(44):
        for x in range(44):
            cell = (top + (y * v) // 44, left + (x * v) // 44)
            img[y, x] = colour.get(cell, BLACK)
    return img


@pytest.mark.parametrize("layout", ["gridworld", "fourrooms"])
@pytest.mark.parametrize("view", [3, 5, 11, "full"])
def test_hand_built_render_pixel_exact(layout, view):
    b = batch1(layout, n_goals=3, view=view)
    agent, goals, fires = (1, 2), [(2, 2), (1, 4), (9, 9)], [(2, 1), (8, 2)]
    b.set_state(0, agent=agent, goals=goals, obstacles=fires)
    obs = b.render_obs()[0]
    exp = expected_image(layout, agent, goals, fires, [False] * 3, view)
    np.testing.assert_array_equal(obs, exp)
    # a few literal pixels (view 5: pixels 0..8 show the first column of cells)
    if view == 5:
        assert obs[0, 0].tolist() == list(BLACK)  # cell (-1, 0): outside
        assert obs[9, 9].tolist() == list(GREY)  # cell (0, 1): border wall
        assert obs[22, 22].tolist() == list(BLACK)  # the agent at the centre
        assert obs[31, 22].tolist() == list(BLUE)  # cell (2, 2)
        assert obs[22, 43].tolist() == list(GREEN)  # cell (1, 4)
        assert obs[31, 13].tolist() == list(RED)  # cell (2, 1)
    if view == "full":
        assert obs[4 * 9 + 1, 4 * 9 + 2].tolist() == list(CYAN)
        assert obs[4 * 1, 4 * 2].tolist() == list(BLACK)
    # subgoal images: centred on each goal's cell, the same view
    for g in range(3):
        img = b.subgoal_images(np.array([g]))[0]
        np.testing.assert_array_equal(img, expected_image(layout, agent, goals, fires, [False] * 3, view, goals[g]))
    # step onto the blue goal: it disappears, its image stays centred on its cell
    s = b.step(np.array([DOWN]))
    assert s.at_subgoal[0] == 0
    exp = expected_image(layout, (2, 2), goals, fires, [True, False, False], view)
    np.testing.assert_array_equal(s.obs[0], exp)
    img = b.subgoal_images(np.array([0]))[0]
    exp = expected_image(layout, (2, 2), goals, fires, [True, False, False], view, goals[0])
    np.testing.assert_array_equal(img, exp)


def test_single_env_subgoal_image_and_render():
    env = GridWorldEnv(n_goals=2, view=3, render_mode="rgb_array")
    env.reset(seed=0)
    env.batch.set_state(0, agent=(5, 5), goals=[(2, 2), (8, 8)], obstacles=[(1, 1), (9, 9)])
    np.testing.assert_array_equal(env.subgoal_image(1), env.batch.subgoal_images(np.array([1]))[0])
    env.set_subgoal(1)
    np.testing.assert_array_equal(env.subgoal_image(), env.subgoal_image(1))
    centre = env.subgoal_image(1)[22, 22]
    assert centre.tolist() == list(GREEN)
    frame = env.render()
    assert frame[5 * 32 + 16, 5 * 32 + 16].tolist() == list(BLACK)
    assert frame[2 * 32, 2 * 32].tolist() == list(BLUE)
    assert frame[0, 0].tolist() == list(GREY)


# ----------------------------------------------------------------------------- vectorised == single
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), layout=st.sampled_from(["gridworld", "fourrooms"]),
       n_goals=st.sampled_from([2, 3]), view=st.sampled_from([3, 5, 11, "full"]),
       actions=st.lists(st.lists(st.integers(0, 3), min_size=3, max_size=3), min_size=1, max_size=150))
def test_vectorised_matches_single(seed, layout, n_goals, view, actions):
    K = 3
    b = GridWorldBatch(K, layout=layout, n_goals=n_goals, view=view, max_steps=40)
    envs = [GridWorldEnv(layout=layout, n_goals=n_goals, view=view, max_steps=40) for _ in range(K)]
    obs = b.reset(seed=seed)
    for i, e in enumerate(envs):
        o, _ = e.reset(seed=seed + i)
        np.testing.assert_array_equal(obs[i], o)
    for acts in actions:
        s = b.step(np.array(acts))
        for i, e in enumerate(envs):
            o, r, term, trunc, info = e.step(acts[i])
            np.testing.assert_array_equal(s.obs[i], o)
            assert np.float32(r) == s.classical[i] and np.float32(info["extrinsic"]) == s.extrinsic[i]
            assert (term, trunc) == (bool(s.terminated[i]), bool(s.truncated[i]))
            assert info["at_subgoal"] == s.at_subgoal[i] and info["hit_obstacle"] == s.hit_obstacle[i]
            assert info["success"] == s.success[i]
            assert info["agent_pos"].tolist() == s.agent_pos[i].tolist()
            assert e.batch.next_goal[0] == b.next_goal[i]
            if term or trunc:
                e.reset()  # continues the env's own generator, like reset_where
        if s.done.any():
            obs = b.reset_where(s.done)
            for i in np.flatnonzero(s.done):
                np.testing.assert_array_equal(obs[i], envs[i].batch.render_obs()[0])
        np.testing.assert_array_equal(b.obstacle_pos, np.concatenate([e.batch.obstacle_pos for e in envs]))


# ----------------------------------------------------------------------------- seeding
def test_seeding_deterministic():
    rng = np.random.default_rng(5)
    acts = rng.integers(0, 4, size=(120, 8))

    def run(seed):
        b = GridWorldBatch(8, layout="fourrooms", n_goals=3)
        out = [b.reset(seed=seed)]
        for a in acts:
            s = b.step(a)
            out += [s.obs, s.classical, s.agent_pos]
            if s.done.any():
                out.append(b.reset_where(s.done))
        return out

    a, b2, c = run(11), run(11), run(12)
    assert all(np.array_equal(x, y) for x, y in zip(a, b2))
    assert not np.array_equal(a[0], c[0])
    # a single env reset with seed s + i replays row i
    b = GridWorldBatch(4)
    obs = b.reset(seed=100)
    e = GridWorldBatch(1)
    np.testing.assert_array_equal(e.reset(seed=102)[0], obs[2])
    np.testing.assert_array_equal(e.agent_pos[0], b.agent_pos[2])
    np.testing.assert_array_equal(e.goal_pos[0], b.goal_pos[2])
    np.testing.assert_array_equal(e.obstacle_pos[0], b.obstacle_pos[2])


# ----------------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("kw,match", [
    ({"view": 4}, "4"), ({"view": "partial"}, "partial"), ({"view": True}, "True"), ({"view": 7.0}, "7.0"),
    ({"n_goals": 1}, "1"), ({"n_goals": 4}, "4"), ({"layout": "maze"}, "maze"),
    ({"max_steps": 0}, "0"), ({"num_envs": 0}, "0"),
])
def test_bad_constructor_args(kw, match):
    with pytest.raises(ValueError, match=match):
        GridWorldBatch(**{"num_envs": 2, **kw})
    if "num_envs" not in kw:
        with pytest.raises(ValueError, match=match):
            GridWorldEnv(**kw)


@pytest.mark.parametrize("actions,match", [
    ([0, 4], "4"), ([-1, 0], "-1"), ([0, 1, 2], r"\(3,\)"), ([0.5, 1.0], "float"), (["a", "b"], "dtype"),
])
def test_bad_actions(actions, match):
    b = GridWorldBatch(2)
    b.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        b.step(np.array(actions))


def test_bad_single_inputs():
    env = GridWorldEnv()
    env.reset(seed=0)
    for a, match in [(4, "4"), (-1, "-1"), (np.int64(9), "9"), (1.5, "float")]:
        with pytest.raises(ValueError, match=match):
            env.step(a)
    env.step(np.int64(1))  # numpy integers are fine
    with pytest.raises(ValueError, match="2"):
        env.set_subgoal(2)
    with pytest.raises(ValueError, match="5"):
        env.subgoal_image(5)
    b = GridWorldBatch(2)
    b.reset(seed=0)
    with pytest.raises(ValueError):
        b.reset_where(np.array([True]))
    with pytest.raises(ValueError):
        b.subgoal_images(np.array([0, 2]))
    with pytest.raises(ValueError, match="-3"):
        b.reset(seed=-3)
    with pytest.raises(ValueError, match="not a free cell"):
        b.set_state(0, agent=(0, 0), goals=[(2, 2), (3, 3)], obstacles=[(4, 4), (5, 5)])
    with pytest.raises(ValueError, match="distinct"):
        b.set_state(0, agent=(2, 2), goals=[(2, 2), (3, 3)], obstacles=[(4, 4), (5, 5)])


def test_a_collected_goals_cell_is_still_its_subgoal_place():
    """Leaving and re-entering a collected goal's cell: at_subgoal names it, nothing is
    collected, no reward; collecting an uncollected goal sets ``collected``."""
    b = GridWorldBatch(1, view=5)
    b.reset(seed=0)
    b.set_state(0, agent=(3, 3), goals=[(4, 3), (8, 8)], obstacles=[(1, 9), (9, 1)])
    s = b.step(np.array([DOWN]))  # collect blue
    assert (s.at_subgoal[0], bool(s.collected[0]), s.extrinsic[0]) == (0, True, 1.0)
    s = b.step(np.array([UP]))
    assert (s.at_subgoal[0], bool(s.collected[0])) == (-1, False)
    s = b.step(np.array([DOWN]))  # back on blue's old cell
    assert (s.at_subgoal[0], bool(s.collected[0]), s.extrinsic[0], s.classical[0]) == (0, False, 0.0, 0.0)
    env = GridWorldEnv(view=5)
    env.reset(seed=0)
    env.batch.set_state(0, agent=(3, 3), goals=[(4, 3), (8, 8)], obstacles=[(1, 9), (9, 1)])
    env.set_subgoal(1)
    _, _, _, _, info = env.step(DOWN)  # collecting blue while pursuing green: -1
    assert info["intrinsic"] == -1.0 and not info["subgoal_reached"]
    env.step(UP)
    env.set_subgoal(0)
    _, _, _, _, info = env.step(DOWN)  # blue's old cell as a subgoal place: +1
    assert info["intrinsic"] == 1.0 and info["subgoal_reached"] and info["extrinsic"] == 0.0
