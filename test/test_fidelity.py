"""hDRQNv2's meta-controller input on a real rollout (thesis framework 2, DESIGN section 4):
the meta frame at each decision is the sub-controller's LSTM state (c by default, h with
``meta_state="h"``) at the end of the previous option, zeros at an episode's first."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hdrqn_ros.agents.algorithms import stack_subgoal
from hdrqn_ros.config import build_config
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.episodes import EpisodeBuilder
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.learner import build_agent

ENV = "hdrqn/GridWorld-3Goals-v0"  # three goals: several options an episode
UP, DOWN, LEFT, RIGHT = range(4)


class TowardsSubgoal:
    """Wraps the sub-controller's ``act``: the network runs as usual (its LSTM state is the
    real one), but the action is a step towards the option's goal cell (one in four at
    random), so options end by reaching their subgoal several times an episode."""

    def __init__(self, controller, rollout, rng):
        self.act, self.rollout, self.rng = controller.act, rollout, rng
        controller.act = self

    def __call__(self, x, state):
        q, new_state = self.act(x, state)
        b = self.rollout.batch
        rows = np.arange(b.num_envs)
        (r, c), (gr, gc) = b._rowcol(b._agent).T, b._rowcol(b._goals[rows, self.rollout.subgoal]).T
        move = np.where(r != gr, np.where(gr < r, UP, DOWN), np.where(gc < c, LEFT, RIGHT))
        move = np.where(self.rng.random(b.num_envs) < 0.25, self.rng.integers(0, 4, b.num_envs), move)
        return np.eye(q.shape[1], dtype=q.dtype)[move], new_state


def _segment_end_states(agent, sub_ep):
    """(K, 2, 256): (h, c) of the sub-controller at the last step of each option, recomputed
    from the stored episode alone: ``act`` over the option's frames (stacked with its
    subgoal image) from the zero state, one option at a time."""
    ends = np.append(sub_ep.segment_starts[1:], sub_ep.num_steps)
    out = []
    with torch.no_grad():
        for k, (s, e) in enumerate(zip(sub_ep.segment_starts, ends)):
            x = stack_subgoal(sub_ep.frames[s:e], sub_ep.segment_data["subgoal_image"][k])
            state = None
            for t in range(e - s):
                _, state = agent.sub.act(x[t:t + 1], state)
            out.append(np.stack([state[0][0].numpy(), state[1][0].numpy()]))
    return np.array(out)


@pytest.mark.parametrize("meta_state", ["c", "h"])
def test_v2_meta_frames_are_the_sub_lstm_state_at_each_option_end(meta_state):
    torch.manual_seed(0)
    cfg = build_config([], algo="hdrqn-v2", env=ENV, meta_state=meta_state)
    agent = build_agent(cfg)
    rollout = Rollout(make_batch(ENV, 2), agent, seed=3, meta_state=meta_state)
    TowardsSubgoal(agent.sub, rollout, np.random.default_rng(1))
    seen = []  # the meta inputs the meta-controller really acted on, per env
    meta_act = agent.meta.act

    def spy(x, state):
        seen.append((np.flatnonzero(rollout.need_meta), np.array(x, copy=True)))
        return meta_act(x, state)

    agent.meta.act = spy
    builder = EpisodeBuilder(2, True)
    rng = np.random.default_rng(0)
    finished = []
    while len(finished) < 6:
        finished += builder.add(rollout.step(0.0, 1.0, rng))

    which = 1 if meta_state == "c" else 0
    options = 0
    acted = {i: [x[list(rows).index(i)] for rows, x in seen if i in rows] for i in (0, 1)}
    for i, sub_ep, meta_ep, stats in finished:
        k = sub_ep.num_segments
        assert meta_ep.num_steps == k and meta_ep.frames.shape == (k + 1, 256)
        np.testing.assert_array_equal(meta_ep.frames[0], 0.0)  # an episode's first decision sees zeros
        ends = _segment_end_states(agent, sub_ep)
        # frame j + 1 (the decision after option j, or the final next-input) is that option's end state
        np.testing.assert_allclose(meta_ep.frames[1:], ends[:, which], atol=1e-5, rtol=0)
        assert np.abs(meta_ep.frames[1:] - ends[:, 1 - which]).max() > 1e-3  # c and h differ: the choice matters
        # and the decisions' frames are what the meta-controller was given
        decided, acted[i] = acted[i][:k], acted[i][k:]
        np.testing.assert_array_equal(np.array(decided), meta_ep.frames[:-1])
        options += k
    assert options >= 15 and max(stats.options for *_, stats in finished) >= 4
