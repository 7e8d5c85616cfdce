"""Recurrent replay that trains on the states the agent acts from, and the value bound:
whole-segment sampling, the time limit as terminal, the return obtained, Q by option index
in losses.csv, the warning when the meta-controller's mean Q passes the return bound, and
``hdrqn values`` (acting Q against zero-state windows)."""
import json

import numpy as np
import pytest
import torch

from hdrqn_ros.agents.controller import INDEX_BUCKETS, UpdateStats
from hdrqn_ros.agents.replay import Episode, EpisodeReplay
from hdrqn_ros.cli import main
from hdrqn_ros.config import build_config
from hdrqn_ros.training.learner import Learner
from hdrqn_ros.training.trainer import Trainer
from hdrqn_ros.training.update_means import UpdateMeans
from test_agents import HAND_ONLINE, HAND_TARGET, _controller, _episode, _update_on_step


def _segmented(lengths, terminal_last=True, seed=0):
    """An episode of segments of ``lengths`` steps; frame t holds t, reward t + 1."""
    t = sum(lengths)
    rng = np.random.default_rng(seed)
    terminal = np.zeros(t, bool)
    terminal[-1] = terminal_last
    return Episode(frames=np.arange(t + 1, dtype=np.float32)[:, None],
                   fields={"action": rng.integers(0, 2, t).astype(np.uint8),
                           "reward": np.arange(1, t + 1, dtype=np.float32), "terminal": terminal},
                   segment_starts=np.cumsum([0, *lengths[:-1]]).astype(np.int32))


def test_whole_segments_begin_where_acting_begins_and_carry_the_loss_on_every_step():
    """seq_len None: every window is the whole segment of its random step, from the segment's
    start, all steps in the loss; the batch is as long as its longest window."""
    replay = EpisodeReplay(10, seed=3)
    replay.add(_segmented([3, 5, 2]))
    replay.add(_segmented([7], terminal_last=False))
    batch = replay.sample(64, None)
    assert batch.valid.shape == (64, 7) and batch.frames.shape == (64, 8, 1)
    lengths = batch.valid.sum(1)
    for row in range(64):
        ep = replay[int(batch.episode_index[row])]
        assert batch.start[row] in ep.segment_starts.tolist()
        assert lengths[row] == ep.segment_lengths[ep.segment_starts.tolist().index(batch.start[row])]
        np.testing.assert_array_equal(batch.frames[row, :lengths[row] + 1, 0],
                                      np.arange(batch.start[row], batch.start[row] + lengths[row] + 1))
        ends_episode = batch.start[row] + lengths[row] == ep.num_steps
        assert batch.episode_end[row].tolist() == [ends_episode and t == lengths[row] - 1 for t in range(7)]
    np.testing.assert_array_equal(batch.loss_mask, batch.valid)
    assert set(lengths.tolist()) == {3, 5, 2, 7}


def test_the_return_obtained_stops_at_a_segments_end_and_at_a_terminal_step():
    """G_t = r_t + d_t (1 - terminal_t) G_{t+1} inside a segment; with smdp_discount
    d_t = gamma ** option_steps[t]."""
    ep = _segmented([2, 3])
    g = EpisodeReplay.return_to_go(ep, 0.5)
    np.testing.assert_allclose(g, [1 + 0.5 * 2, 2, 3 + 0.5 * 4 + 0.25 * 5, 4 + 0.5 * 5, 5])
    ep.fields["option_steps"] = np.array([1, 2, 3, 1, 1], np.int32)
    ep.fields["terminal"][3] = True
    g = EpisodeReplay.return_to_go(ep, 0.5, smdp_discount=True)
    np.testing.assert_allclose(g, [1 + 0.5 * 2, 2, 3 + 0.125 * 4, 4, 5])


@pytest.mark.parametrize("time_limit, bootstrapped", [("bootstrap", True), ("terminal", False)])
def test_a_time_limit_bootstraps_or_ends_the_value(time_limit, bootstrapped):
    """An episode cut by the step limit after step 1 (not terminal): its last step's target is
    r + gamma * Q_target(s_2, argmax Q(s_2)) = -100 + 0.9 * 5, or r = -100 with time_limit
    terminal; a step inside the episode bootstraps either way."""
    ctrl = _controller(seq_len=1)
    ctrl.cfg = ctrl.cfg.model_copy(update={"time_limit": time_limit})
    cut = _episode()
    ctrl.replay.add(Episode(frames=cut.frames[:3], fields={k: v[:2] for k, v in cut.fields.items()}))
    stats = _update_on_step(ctrl, 1, HAND_ONLINE, HAND_TARGET)
    assert float(stats.target) == pytest.approx(-100.0 + (0.9 * 5.0 if bootstrapped else 0.0))
    ctrl = _controller(seq_len=1)
    ctrl.cfg = ctrl.cfg.model_copy(update={"time_limit": time_limit})
    ctrl.replay.add(_episode())
    assert float(_update_on_step(ctrl, 1, HAND_ONLINE, HAND_TARGET).target) == pytest.approx(-100.0 + 0.9 * 5.0)


def _tiny(**overrides):
    base = dict(env="hdrqn/GridWorld-3Goals-v0", episodes=8, num_envs=2, learning_starts=0, eval_every=0,
                checkpoint_every=8, log_every_updates=2, sub={"batch_size": 2, "replay_episodes": 50},
                meta={"batch_size": 2, "replay_episodes": 50})
    return build_config([], **{**base, **overrides})


def test_whole_meta_episodes_train_the_q_values_the_policy_acts_on(tmp_path):
    """hDRQNv2 with meta.sampling whole: the update's input for a stored episode, run from a
    zero state, gives at every option the Q-values the meta-controller computed when it
    chose that option step by step (acting), and the update trains every option's step."""
    trainer = Trainer(_tiny(meta={"batch_size": 2, "replay_episodes": 50, "sampling": "whole"}), tmp_path,
                      progress=False, tensorboard=False)
    trainer.run()
    meta = trainer.agent.meta
    assert meta.seq_len is None
    longest = max(range(len(meta.replay)), key=lambda i: meta.replay[i].num_steps)
    batch = meta.replay.whole_segments([longest])
    assert batch.loss_mask.all() and batch.loss_mask.shape[1] == meta.replay[longest].num_steps >= 2
    with torch.no_grad():
        trained, _ = meta.online(torch.as_tensor(meta.build_input(batch)))
    state, acted = meta.initial_state(1), []
    for t in range(batch.frames.shape[1]):
        q, state = meta.act(batch.frames[:, t], state)
        acted.append(q[0])
    np.testing.assert_allclose(trained[0].numpy(), np.stack(acted), rtol=1e-5, atol=1e-6)


def test_update_means_average_q_and_the_return_by_option_index():
    """Sums over a block's updates divided by the block's counts; NaN where no step had that index."""
    means = UpdateMeans(every=2)
    scalars = [torch.tensor(1.0)] * 4

    def by_index(counts, q, ret):
        return torch.tensor([counts, q, ret], dtype=torch.float32)

    assert means.add("meta", UpdateStats(*scalars, by_index(
        [2, 1, 0, 0], [4.0, 1.0, 0, 0], [2.0, 0.5, 0, 0]))) is None
    row = means.add("meta", UpdateStats(*scalars, by_index([2, 0, 0, 1], [0.0, 0, 0, 9.0], [2.0, 0, 0, 3.0])))
    assert (row["q_opt0"], row["return_opt0"], row["q_opt1"], row["q_opt3"], row["return_opt3"]) == (1.0, 1.0, 1.0,
                                                                                                     9.0, 3.0)
    assert np.isnan(row["q_opt2"]) and np.isnan(row["return_opt2"]) and INDEX_BUCKETS == 4


def test_a_meta_q_above_the_return_bound_warns_once_and_is_kept_in_the_summary(tmp_path):
    """Three goals: no episode returns more than 3. A losses.csv row with the meta mean Q at 2.5
    passes; at 4.0 the run warns once, naming the value and the bound, and summary.json keeps
    where; a later row at 7.0 does not warn again."""
    warnings = []
    learner = Learner(_tiny(log_every_updates=1), tmp_path, progress=False, tensorboard=False, warn=warnings.append)
    assert learner.return_bound == 3.0

    def row(q):
        learner._record(learner.agent.meta, UpdateStats(*[torch.tensor(float(v)) for v in (1.0, q, q, 1.0)]))

    row(2.5)
    assert warnings == []
    row(4.0)
    row(7.0)
    assert len(warnings) == 1 and "mean Q is 4 " in warnings[0] and "above 3," in warnings[0]
    summary = learner.summary(None)
    assert summary["meta_q_above_bound"]["mean_q"] == 4.0 and summary["meta_q_above_bound"]["return_bound"] == 3.0


def test_hdrqn_values_sets_acting_q_beside_zero_state_windows_and_returns(tmp_path, capsys):
    """A tiny hDRQNv2 run with the thesis's windows; ``hdrqn values`` prints each recurrent
    controller's table. A window begun at the segment's start is the acting state: at
    position t the zero-state Q at window position t equals the acting Q; at window position
    0 (a zero state in mid-episode) it does not."""
    run = tmp_path / "run"
    assert main(["train", "--env", "hdrqn/GridWorld-3Goals-v0", "--episodes", "8", "--out", str(run),
                 "--no-progress", "--set", "num_envs=2", "--set", "learning_starts=0", "--set", "eval_every=0",
                 "--set", "sub.batch_size=2", "--set", "meta.batch_size=2", "--set", "sub.seq_len=3"]) == 0
    capsys.readouterr()
    assert main(["values", str(run), "--json", str(tmp_path / "values.json")]) == 0
    out = capsys.readouterr().out
    assert "| position t | steps | return obtained | Q acting | Q window pos 0 |" in out
    tables = {t["controller"]: t for t in json.loads((tmp_path / "values.json").read_text())}
    assert set(tables) == {"meta", "sub"} and tables["sub"]["window"] == 3 and tables["meta"]["window"] == 2
    sub_rows = {r["position"]: r for r in tables["sub"]["rows"]}
    for t in range(3):
        assert sub_rows[str(t)]["q_window"][t] == pytest.approx(sub_rows[str(t)]["q_acting"], rel=1e-5, abs=1e-6)
        assert all(q is None for q in sub_rows[str(t)]["q_window"][t + 1:])
    assert sub_rows["2"]["q_window"][0] != pytest.approx(sub_rows["2"]["q_acting"], rel=1e-3)
    assert tables["sub"]["gap"][0] > 0 and sum(r["count"] for r in tables["sub"]["rows"]) == tables["sub"]["steps"]


def test_hdrqn_values_names_a_directory_without_a_run(tmp_path, capsys):
    assert main(["values", str(tmp_path)]) == 2
    assert "holds no checkpoints/last.pt" in capsys.readouterr().err


def test_resuming_a_run_begun_before_whole_episodes_names_the_switch():
    """A checkpoint's config without ``sampling``/``time_limit`` learned on windows with the
    limit bootstrapped: resumed with today's defaults, the change is named."""
    saved = build_config([]).model_dump()
    for section in ("sub", "meta", "flat"):
        del saved[section]["sampling"], saved[section]["time_limit"]
    assert build_config([]).changes_since(saved) == ["meta.sampling: 'windows' -> 'whole'",
                                                     "meta.time_limit: 'bootstrap' -> 'terminal'"]
    kept = build_config([], meta={"sampling": "windows", "time_limit": "bootstrap"})
    assert kept.changes_since(saved) == []
