"""Montezuma's Revenge domain (hdrqn_ros/envs/montezuma.py); needs ale-py (ROMs bundled)."""
from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import hdrqn_ros  # noqa: F401  (registers the ids)
from hdrqn_ros.config import build_config
from hdrqn_ros.envs.critic import MONTEZUMA_CRITIC
from hdrqn_ros.envs import montezuma as mz
from hdrqn_ros.envs.domain import NO_SUBGOAL, OBS_SHAPE
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.recording.transitions import TransitionRecorder, read_episodes
from hdrqn_ros.training.episodes import EpisodeBuilder
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.learner import build_agent

ENV_ID = "hdrqn/MontezumaRevenge-v0"
NOOP, FIRE, UP, RIGHT, LEFT, DOWN, RIGHTFIRE, LEFTFIRE = 0, 1, 2, 3, 4, 5, 11, 12

# Deterministic (frame skip 4, no sticky actions) route found by search with ALE state
# cloning: down the middle ladder, jump onto the rope, jump to the right platform, down the
# right ladder, jump over the skull, up the left ladder, jump into the key (step 90).
KEY_ROUTE = [
    (DOWN, 8), (RIGHT, 8), (RIGHTFIRE, 1), (NOOP, 4), (DOWN, 2), (RIGHTFIRE, 1), (NOOP, 5),
    (RIGHT, 1), (DOWN, 9), (LEFT, 12), (LEFTFIRE, 1), (LEFT, 15), (UP, 14), (LEFT, 6),
    (FIRE, 1), (NOOP, 8),
]
# ... and back: over the skull, up the right ladder, rope, conveyor, middle ladder, jump to
# the top-left ledge and into the left door (+300), then out of the room.
DOOR_ROUTE = KEY_ROUTE + [
    (RIGHT, 3), (DOWN, 14), (RIGHT, 9), (RIGHTFIRE, 1), (RIGHT, 19), (UP, 14), (LEFTFIRE, 1),
    (NOOP, 6), (LEFTFIRE, 1), (NOOP, 8), (UP, 14), (LEFT, 2), (LEFTFIRE, 1), (LEFT, 20),
]
# Down the middle ladder and carried off the conveyor's left end: falls and dies.
FALL_ROUTE = [(DOWN, 24), (NOOP, 20)]


def expand(route):
    return [a for a, n in route for _ in range(n)]


def run(batch, actions):
    steps = []
    for a in actions:
        steps.append(batch.step(np.full(batch.num_envs, a)))
    return steps


def sprite_centre(frame):
    """Centre (row, col) of the agent's sprite: its red body and yellow hat, below the HUD."""
    play = frame[40:].astype(int)
    m = (play == [200, 72, 72]).all(-1) | (play == [210, 182, 86]).all(-1)
    rows, cols = np.nonzero(m)
    assert rows.size > 0
    return (rows.min() + rows.max()) / 2 + 40, (cols.min() + cols.max()) / 2


@pytest.fixture(scope="module")
def key_run():
    b = mz.MontezumaBatch(num_envs=1)
    obs0 = b.reset(seed=0)[0]
    frames, steps = [b.frames[0].copy()], []
    for a in expand(KEY_ROUTE):
        steps.append(b.step([a]))
        frames.append(b.frames[0].copy())
    return obs0, steps, frames


def test_check_env_registered_id():
    env = gym.make(ENV_ID).unwrapped
    assert isinstance(env, mz.MontezumaEnv)
    check_env(env, skip_render_check=False)
    assert env.observation_space.shape == OBS_SHAPE and env.action_space.n == 18
    env.close()


def test_batch_contract_and_factory():
    b = make_batch(ENV_ID, num_envs=2)
    assert (b.num_envs, b.num_actions, b.num_subgoals) == (2, 18, 7)
    assert b.critic() is MONTEZUMA_CRITIC
    obs = b.reset(seed=1)
    assert obs.shape == (2, 44, 44, 3) and obs.dtype == np.uint8
    s = b.step(np.array([0, 0]))
    assert s.obs.shape == (2, 44, 44, 3)
    assert s.classical.dtype == np.float32 and s.extrinsic.dtype == np.float32
    assert s.agent_pos.dtype == np.int32 and s.at_subgoal.dtype == np.int32
    assert s.agent_pos.tolist() == [[77, 235], [77, 235]]  # start: top of the middle ladder
    assert s.at_subgoal.tolist() == [1, 1]
    assert mz.ACTION_NAMES[11] == "RIGHTFIRE" and len(mz.SUBGOAL_NAMES) == 7


def test_ram_position_matches_drawn_agent(key_run):
    _, steps, frames = key_run
    # frames after every step of the route: the sprite centre is within the rendering lag
    # (one frame: up to 3 rows while jumping) of the mapped RAM position.
    for s, f in zip(steps, frames[1:]):
        x, y = s.agent_pos[0]
        r, c = mz.ram_to_pixel(x, y)
        sr, sc = sprite_centre(f)
        assert abs(sr - r) <= 3.5 and abs(sc - c) <= 1.5, (x, y, sr, sc)
    # standing still the mapping is exact: rows 308-y .. 327-y
    b = mz.MontezumaBatch(1)
    b.reset(seed=0)
    b.step([NOOP])
    sr, sc = sprite_centre(b.frames[0])
    assert (sr, sc) == (317 - 235 + 0.5, 77 + 2.5)
    assert b.room[0] == mz.START_ROOM


def test_observation_is_agent_centred_crop(key_run):
    obs0, _, frames = key_run
    r, c = mz.ram_to_pixel(77, 235)
    expected = mz.crop_view(frames[0][None], [r], [c])[0]
    np.testing.assert_array_equal(obs0, expected)
    # the agent's red is near the centre of the observation
    red = np.argwhere((obs0 == [200, 72, 72]).all(-1))
    assert red.size and np.abs(red.mean(0) - 22).max() < 6
    # outside the screen is black: a crop centred on the top-left corner
    corner = mz.crop_view(frames[0][None], [0], [0])[0]
    assert (corner[:21, :] == 0).all() and (corner[:, :21] == 0).all()


def test_key_route_rewards_subgoals_and_critic(key_run):
    _, steps, _ = key_run
    classical = np.array([s.classical[0] for s in steps])
    extrinsic = np.array([s.extrinsic[0] for s in steps])
    at = np.array([s.at_subgoal[0] for s in steps])
    success = np.array([s.success[0] for s in steps])
    k = int(np.flatnonzero(classical)[0])
    assert classical[k] == 100 and classical.sum() == 100  # eq. 4.6
    assert extrinsic[k] == 1 and extrinsic.sum() == 1  # eq. 4.5
    assert not success[:k].any() and success[k:].all()
    assert at[k] == mz.KEY_SUBGOAL
    # boxes visited in the order of thesis fig. 4.14
    visited = [g for i, g in enumerate(at) if g != NO_SUBGOAL and (i == 0 or at[i - 1] != g)]
    assert visited == [3, 4, 5, 6]
    assert not any(s.life_lost[0] or s.done[0] for s in steps)
    # eq. 4.4: 1 on the steps inside the option's subgoal box, 0 elsewhere (even in another box)
    for g in range(7):
        for s in steps:
            c = MONTEZUMA_CRITIC.evaluate(s, np.array([g]))
            assert c.intrinsic[0] == (1.0 if s.at_subgoal[0] == g else 0.0)
            assert c.reached[0] == (s.at_subgoal[0] == g) == c.option_done[0]


def test_door_route_opens_door_and_leaves_room():
    b = mz.MontezumaBatch(1)
    b.reset(seed=0)
    steps = run(b, expand(DOOR_ROUTE))
    classical = np.array([s.classical[0] for s in steps])
    extrinsic = np.array([s.extrinsic[0] for s in steps])
    done = np.array([s.done[0] for s in steps])
    assert sorted(classical[classical != 0].tolist()) == [100.0, 300.0]
    d = int(np.flatnonzero(classical == 300)[0])
    assert extrinsic[d] == 1 and extrinsic.sum() == 2
    assert steps[d].at_subgoal[0] == 0  # left-door box
    assert not b._ram[0, mz.RAM_INVENTORY] & mz.INVENTORY_KEY_BIT  # the door used the key
    end = int(np.flatnonzero(done)[0])
    assert end > d and steps[end].terminated[0] and not steps[end].truncated[0]
    assert b.room[0] != mz.START_ROOM and steps[end].success[0]
    assert steps[end].at_subgoal[0] == NO_SUBGOAL


def test_life_loss_ends_option_not_episode():
    b = mz.MontezumaBatch(1)
    b.reset(seed=0)
    steps = run(b, expand(FALL_ROUTE))
    lost = [i for i, s in enumerate(steps) if s.life_lost[0]]
    assert len(lost) == 1
    s = steps[lost[0]]
    assert not s.done[0] and s.classical[0] == 0 and s.extrinsic[0] == 0
    c = MONTEZUMA_CRITIC.evaluate(s, np.array([mz.KEY_SUBGOAL]))
    assert c.option_done[0] and not c.reached[0] and c.intrinsic[0] == 0
    # the game goes on: the agent re-spawns at the start
    assert steps[-1].agent_pos[0].tolist() == [77, 235] and not steps[-1].done[0]


def test_subgoal_box_lookup():
    assert mz.subgoal_at(77, 235) == 1
    assert mz.subgoal_at(24, 235) == 0 and mz.subgoal_at(130, 235) == 2
    assert mz.subgoal_at(133, 192) == 3 and mz.subgoal_at(133, 148) == 4
    assert mz.subgoal_at(21, 148) == 5 and mz.subgoal_at(9, 203) == 6
    assert mz.subgoal_at(77, 192) == NO_SUBGOAL and mz.subgoal_at(9, 192) == NO_SUBGOAL
    xs, ys = np.meshgrid(np.arange(256), np.arange(256), indexing="ij")
    b = mz.SUBGOAL_BOXES
    inside = ((xs[..., None] >= b[:, 0]) & (xs[..., None] <= b[:, 1]) & (ys[..., None] >= b[:, 2])
              & (ys[..., None] <= b[:, 3]))
    assert inside.sum(-1).max() == 1  # disjoint
    np.testing.assert_array_equal(mz.subgoal_at(xs, ys), np.where(inside.any(-1), inside.argmax(-1), -1))


def test_subgoal_images():
    b = mz.MontezumaBatch(2)
    b.reset(seed=0)
    imgs = b.subgoal_images(np.array([6, 0]))
    assert imgs.shape == (2, 44, 44, 3) and imgs.dtype == np.uint8
    c = mz.subgoal_centres_pixels()[[6, 0]]
    np.testing.assert_array_equal(imgs, mz.crop_view(b.frames, c[:, 0], c[:, 1]))
    # key image: the key's yellow fills the centre (the door's yellow is further up)
    assert (imgs[0][14:30, 14:30] == [232, 204, 99]).all(-1).sum() >= 12
    # left-door image: its left part lies outside the screen, hence black
    assert (imgs[1][:, :5] == 0).all()
    with pytest.raises(ValueError):
        b.subgoal_images(np.array([7, 0]))
    with pytest.raises(ValueError):
        b.subgoal_images(np.array([0]))
    env = gym.make(ENV_ID).unwrapped
    env.reset(seed=0)
    assert env.subgoal == mz.KEY_SUBGOAL
    np.testing.assert_array_equal(env.subgoal_image(), imgs[0])
    env.set_subgoal(0)
    np.testing.assert_array_equal(env.subgoal_image(), imgs[1])
    with pytest.raises(ValueError):
        env.set_subgoal(7)


def test_seeding_batch_rows_replay_single_envs():
    rng = np.random.default_rng(3)
    acts = rng.integers(0, 18, size=(60, 3))
    b = mz.MontezumaBatch(3, repeat_action_probability=0.25)
    b.reset(seed=10)
    batch_pos = np.array([b.step(a).agent_pos for a in acts])  # (T, 3, 2)
    batch_obs = b.observations()
    for i in range(3):
        e = mz.MontezumaBatch(1, repeat_action_probability=0.25)
        e.reset(seed=10 + i)
        pos = np.array([e.step(acts[:, i][t:t + 1]).agent_pos[0] for t in range(len(acts))])
        np.testing.assert_array_equal(pos, batch_pos[:, i])
        np.testing.assert_array_equal(e.observations()[0], batch_obs[i])
    # same seed -> same trajectory again
    b.reset(seed=10)
    again = np.array([b.step(a).agent_pos for a in acts])
    np.testing.assert_array_equal(again, batch_pos)


def test_single_env_agrees_with_batch():
    acts = expand(KEY_ROUTE)[:40]
    env = gym.make(ENV_ID).unwrapped
    obs, info = env.reset(seed=4)
    b = mz.MontezumaBatch(1)
    np.testing.assert_array_equal(obs, b.reset(seed=4)[0])
    assert info["at_subgoal"] == 1 and info["agent_pos"].tolist() == [77, 235]
    env.set_subgoal(3)
    for a in acts:
        obs, r, term, trunc, info = env.step(a)
        s = b.step([a])
        np.testing.assert_array_equal(obs, s.obs[0])
        assert r == s.classical[0] == info["classical"] and (term, trunc) == (s.terminated[0], s.truncated[0])
        assert info["at_subgoal"] == s.at_subgoal[0]
        assert info["intrinsic"] == float(s.at_subgoal[0] == 3) and info["subgoal_reached"] == (s.at_subgoal[0] == 3)
        assert set(info) == {"extrinsic", "classical", "intrinsic", "subgoal_reached", "at_subgoal",
                             "hit_obstacle", "life_lost", "agent_pos", "success"}
    assert env.render() is None
    env2 = mz.MontezumaEnv(render_mode="rgb_array")
    env2.reset(seed=0)
    assert env2.render().shape == (210, 160, 3)


def test_bad_actions_raise():
    b = mz.MontezumaBatch(2)
    b.reset(seed=0)
    for bad in ([0, 18], [-1, 0], [0.5, 0], [0], [[0, 0]]):
        with pytest.raises(ValueError):
            b.step(np.array(bad))
    env = mz.MontezumaEnv()
    env.reset(seed=0)
    for bad in (18, -1, 2.5, [1, 2]):
        with pytest.raises(ValueError):
            env.step(bad)
    with pytest.raises(ValueError):
        mz.MontezumaBatch(0)
    with pytest.raises(ValueError):
        mz.MontezumaBatch(1, frame_skip=0)
    with pytest.raises(ValueError):
        mz.MontezumaBatch(1, repeat_action_probability=1.5)


def test_frame_skip_sticky_and_step_limit():
    for k in (1, 4, 7):
        b = mz.MontezumaBatch(1, frame_skip=k)
        b.reset(seed=0)
        f0 = b._ales[0].getEpisodeFrameNumber()
        run(b, [NOOP] * 3)
        assert b._ales[0].getEpisodeFrameNumber() - f0 == 3 * k
    b = mz.MontezumaBatch(1, repeat_action_probability=0.3)
    assert b._ales[0].getFloat("repeat_action_probability") == pytest.approx(0.3)
    assert mz.MontezumaBatch(1)._ales[0].getFloat("repeat_action_probability") == 0.0
    # sticky actions change the trajectory of the key route (same seed, same actions)
    b.reset(seed=0)
    sticky = [s.agent_pos[0].tolist() for s in run(b, expand(KEY_ROUTE))]
    d = mz.MontezumaBatch(1)
    d.reset(seed=0)
    assert sticky != [s.agent_pos[0].tolist() for s in run(d, expand(KEY_ROUTE))]
    # step limit
    b = mz.MontezumaBatch(2, max_steps=5)
    b.reset(seed=0)
    steps = run(b, [NOOP] * 5)
    assert not any(s.truncated.any() for s in steps[:4])
    assert steps[4].truncated.all() and not steps[4].terminated.any()


def test_reset_where_restarts_only_masked():
    b = mz.MontezumaBatch(2)
    b.reset(seed=0)
    run(b, [DOWN] * 6)
    obs = b.reset_where(np.array([True, False]))
    assert obs.shape == (2, 44, 44, 3)
    assert b.agent_pos[0].tolist() == [77, 235] and b.agent_pos[1].tolist() != [77, 235]
    assert b.steps.tolist() == [0, 6]
    with pytest.raises(ValueError):
        b.reset_where(np.array([True]))


def test_reward_mapping_functions():
    key, door = mz.reward_events(np.array([100.0, 300.0, 0.0, 100.0]), [0, 2, 0, 0], [2, 0, 0, 2],
                                 [False, True, False, True])
    assert key.tolist() == [True, False, False, False] and door.tolist() == [False, True, False, False]
    assert mz.extrinsic_reward(key, door).tolist() == [1.0, 1.0, 0.0, 0.0]


def test_missing_ale_py_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ale_py", None)
    with pytest.raises(ImportError, match="pip install ale-py"):
        mz.MontezumaBatch(1)


class Scripted:
    """Replaces a controller's ``act``: its network still runs (so the LSTM state is the
    real one), but the Q-values are one-hot on the scripted choice, so a greedy rollout
    follows the script. Keeps the state each call was given."""

    def __init__(self, controller, choices):
        self.act, self.choices, self.states_in = controller.act, iter(choices), []
        controller.act = self

    def __call__(self, x, state):
        self.states_in.append(None if state is None else tuple(t.clone() for t in state))
        q, new_state = self.act(x, state)
        scripted = np.zeros_like(q)
        scripted[:, next(self.choices)] = 1.0
        return scripted, new_state


def test_a_death_is_terminal_for_the_sub_controller_in_both_paths(tmp_path):
    """Thesis 4.5: a life loss ends the option. The dying step's sub-controller transition
    must not bootstrap (from the death animation, under the old subgoal), the next option
    starts fresh, and the episode goes on. The in-process rollout's episode and the one the
    node graph's assembler builds from the same messages (here via a bag) agree."""
    torch.manual_seed(0)
    steps = 40  # the episode is truncated at the step limit, 16 steps after the death
    cfg = build_config([], algo="hdrqn-v2", env=ENV_ID, env_kwargs={"max_steps": steps})
    agent = build_agent(cfg)
    sub = Scripted(agent.sub, expand(FALL_ROUTE))
    Scripted(agent.meta, [mz.KEY_SUBGOAL] * 5)  # an option the fall never reaches
    batch = make_batch(ENV_ID, 1, **cfg.env_kwargs)
    rollout = Rollout(batch, agent, seed=0, record_subgoal_images=True)
    builder = EpisodeBuilder(1, True)
    sink = TransitionRecorder(tmp_path / "bag", cfg, 1)
    records, finished, lives = [], [], []
    rng = np.random.default_rng(0)
    for _ in range(steps):
        records.append(rollout.step(0.0, 0.0, rng))
        lives.append(batch._ales[0].lives())  # ALE's own count (the last step resets the game)
        sink.write(records[-1])
        finished += builder.add(records[-1])
    sink.close()

    death = 23  # down the middle ladder, carried off the conveyor's left end
    assert [t for t, r in enumerate(records) if r.env.life_lost[0]] == [death]
    assert lives[:death] == [6] * death and lives[death:-1] == [5] * (steps - 1 - death)
    assert not any(r.env.done[0] for r in records[:-1]) and records[-1].env.truncated[0]
    r = records[death]
    assert r.option_done[0] and r.sub_terminal[0] and r.intrinsic[0] == 0 and not r.env.done[0]
    # the next option starts fresh: a new subgoal decision and a zero sub-controller state
    assert records[death + 1].new_option[0] and not records[death].new_option[0]
    assert all(not t.any() for t in sub.states_in[death + 1])
    assert all(t.abs().sum() > 0 for t in sub.states_in[death])

    [(_, sub_ep, meta_ep, stats)] = finished
    assert sub_ep.num_steps == steps and stats.options == 2
    terminal = np.zeros(steps, bool)
    terminal[death] = True  # the dying step, and nothing else (the truncated last step bootstraps)
    np.testing.assert_array_equal(sub_ep.fields["terminal"], terminal)
    np.testing.assert_array_equal(sub_ep.segment_starts, [0, death + 1])
    np.testing.assert_array_equal(meta_ep.fields["terminal"], [False, False])  # the game goes on
    np.testing.assert_array_equal(meta_ep.fields["action"], [mz.KEY_SUBGOAL] * 2)

    # the node graph's path: the learner's assembler joins the per-step messages (env_step
    # with life_lost, critic with option_done, ...) into the same episodes
    [(_, graph_sub, graph_meta, _)] = list(read_episodes([sink.path], cfg, batch.num_subgoals))
    np.testing.assert_array_equal(graph_sub.fields["terminal"], terminal)
    for mine, theirs in ((sub_ep, graph_sub), (meta_ep, graph_meta)):
        np.testing.assert_array_equal(mine.frames, theirs.frames)
        np.testing.assert_array_equal(mine.segment_starts, theirs.segment_starts)
        for k in mine.fields:
            np.testing.assert_array_equal(mine.fields[k], theirs.fields[k], err_msg=k)
