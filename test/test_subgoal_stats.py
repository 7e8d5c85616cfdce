"""Subgoal statistics: every option's start, subgoal, length and outcome and the steps at
each subgoal's place (``options.csv``, ``visits.csv``), the option table, and the phase-1
report of two-phase training (thesis section 4.5)."""
import csv
import json
from collections import Counter

import gymnasium as gym
import numpy as np
import pytest
import torch

import hdrqn_ros  # noqa: F401
from hdrqn_ros.config import build_config
from hdrqn_ros.envs.domain import NO_SUBGOAL
from hdrqn_ros.envs.montezuma import SUBGOAL_NEIGHBOURS
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.episodes import EpisodeBuilder, OptionOutcome
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.subgoals import option_table, option_table_markdown, read_options
from hdrqn_ros.training.learner import build_agent
from hdrqn_ros.training.trainer import Trainer

ENV = "hdrqn/GridWorld-3Goals-v0"


def test_option_log_and_visits_match_a_replay_in_a_single_env():
    """The recorder's option outcomes and visit counts equal what a fresh single
    environment reports (``info['at_subgoal']``) for the same seed, subgoals and actions."""
    torch.manual_seed(3)
    cfg = build_config([], algo="hdrqn-v1", env=ENV)
    agent = build_agent(cfg)
    rollout = Rollout(make_batch(ENV, 2), agent, seed=11)
    builder = EpisodeBuilder(2, True)
    rng = np.random.default_rng(0)
    episodes = {0: [], 1: []}
    for _ in range(260):
        for i, sub, meta, stats in builder.add(rollout.step(0.3, 0.5, rng)):
            episodes[i].append((sub, meta, stats))
    checked = reached = 0
    for i, eps in episodes.items():
        env = gym.make(ENV).unwrapped
        env.reset(seed=11 + i)
        for k, (sub, meta, stats) in enumerate(eps):
            if k:
                env.reset()
            bounds = [*sub.segment_starts.tolist(), sub.num_steps]
            place, visits, expected = NO_SUBGOAL, Counter(), []
            for seg, (a, b) in enumerate(zip(bounds, bounds[1:])):
                g = int(meta.fields["action"][seg])
                env.set_subgoal(g)
                start = place
                for t in range(a, b):
                    *_, info = env.step(int(sub.fields["action"][t]))
                    place = info["at_subgoal"]
                    visits[place] += place != NO_SUBGOAL
                expected.append(OptionOutcome(start, g, b - a, place == g))
            assert stats.option_log == expected
            assert stats.visits == +visits
            assert sum(o.steps for o in stats.option_log) == stats.steps
            checked += len(expected)
            reached += sum(o.reached for o in expected)
    assert checked >= 10 and 0 < reached < checked  # both outcomes occur


def test_option_table_counts_neighbours_apart():
    outcomes = [OptionOutcome(5, 6, 30, True), OptionOutcome(5, 6, 500, False), OptionOutcome(1, 6, 200, False),
                OptionOutcome(-1, 3, 40, True), OptionOutcome(1, 3, 60, True), OptionOutcome(4, 3, 20, False)]
    names = tuple(f"g{g}" for g in range(7))
    rows = {r["name"]: r for r in option_table(outcomes, names, SUBGOAL_NEIGHBOURS)}
    key, ladder = rows["g6"], rows["g3"]
    assert (key["neighbour_attempts"], key["neighbour_reached"], key["neighbour_rate"]) == (2, 1, 0.5)
    assert (key["all_attempts"], key["all_reached"], key["median_steps"]) == (3, 1, 30)
    assert (ladder["neighbour_attempts"], ladder["neighbour_reached"]) == (2, 1)  # from 1 and 4, not from -1
    assert (ladder["all_attempts"], ladder["all_reached"], ladder["median_steps"]) == (3, 2, 50)
    assert rows["g0"]["neighbour_rate"] is None and rows["g0"]["median_steps"] is None
    text = option_table_markdown(list(rows.values()))
    assert "| 6 g6 | g5 | **0.50 (1/2)** | 0.33 (1/3) | 30 |" in text
    assert "| 0 g0 | g1 | **- (0)** | - (0) | - |" in text


def _tiny(**overrides):
    return build_config([], **{**dict(env=ENV, episodes=8, sub_only_episodes=4, num_envs=2, learning_starts=0,
                                      eval_every=0, eval_episodes=3, checkpoint_every=4,
                                      sub={"batch_size": 2, "replay_episodes": 50},
                                      meta={"batch_size": 2, "replay_episodes": 50}), **overrides})


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_two_phase_training_writes_option_visit_and_phase1_files(tmp_path):
    Trainer(_tiny(), tmp_path, progress=False, tensorboard=False).run()
    train, options, visits = (_rows(tmp_path / f) for f in ("train.csv", "options.csv", "visits.csv"))
    assert list(visits[0]) == ["episode", "blue", "green", "cyan"]
    assert [int(r["episode"]) for r in visits] == [int(r["episode"]) for r in train] == list(range(1, 9))
    for row in train:  # one options.csv row per option, their lengths add up to the episode's
        mine = [o for o in options if o["episode"] == row["episode"]]
        assert len(mine) == int(row["options"])
        assert sum(int(o["steps"]) for o in mine) == int(row["steps"])
    report = json.loads((tmp_path / "phase1.json").read_text())
    assert report["phase1_episodes"] == 4 and report["greedy_episodes"] == 3
    assert report["training_episodes"] == [4, 4]
    trained = [o for o in options if o["episode"] == "4"]
    assert sum(r["all_attempts"] for r in report["training"]) == len(trained)
    assert sum(r["all_reached"] for r in report["training"]) == sum(int(o["reached"]) for o in trained)
    assert sum(r["all_attempts"] for r in report["greedy"]) >= 3  # at least one option per episode
    assert read_options(tmp_path / "options.csv", 4, 4) == [
        OptionOutcome(int(o["start"]), int(o["subgoal"]), int(o["steps"]), o["reached"] == "1") for o in trained]
    assert "# Phase 1 of hdrqn-v2" in (tmp_path / "phase1.md").read_text()


@pytest.mark.parametrize("algo", ["drqn", "hdrqn-v2"])
def test_one_phase_or_flat_training_has_no_phase1_report(algo, tmp_path):
    sub_only = 4 if algo == "drqn" else 0
    Trainer(_tiny(algo=algo, episodes=4, sub_only_episodes=sub_only), tmp_path, progress=False,
            tensorboard=False).run()
    assert not (tmp_path / "phase1.json").exists()
    assert (tmp_path / "options.csv").exists() == (algo != "drqn")
    assert len(_rows(tmp_path / "visits.csv")) == 4


def test_eval_reports_subgoals_with_random_subgoals(tmp_path, capsys):
    from hdrqn_ros.cli import main

    Trainer(_tiny(episodes=2, sub_only_episodes=0), tmp_path, progress=False, tensorboard=False).run()
    ckpt = str(tmp_path / "checkpoints" / "last.pt")
    assert main(["eval", "--checkpoint", ckpt, "--episodes", "4", "--meta-epsilon", "1", "--subgoals"]) == 0
    out, err = capsys.readouterr()
    result = json.loads(out)
    assert result["episodes"] == 4 and list(result["steps_at_subgoal"]) == ["blue", "green", "cyan"]
    rows = result["options"]
    assert [r["name"] for r in rows] == ["blue", "green", "cyan"] and sum(r["all_attempts"] for r in rows) >= 4
    assert "| 2 cyan | blue, green |" in err
    assert main(["eval", "--checkpoint", ckpt, "--meta-epsilon", "nan"]) == 2
    assert "--meta-epsilon must be in [0, 1]" in capsys.readouterr().err

