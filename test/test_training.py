"""The training loop end to end: transitions aligned with the environment, every
algorithm trains, checkpoints resume, bad checkpoints/configs are refused."""
import hashlib

import gymnasium as gym
import numpy as np
import pytest
import torch

import hdrqn_ros  # noqa: F401
from hdrqn_ros.cli import main
from hdrqn_ros.config import ALGOS, ConfigError, build_config
from hdrqn_ros.agents.controller import TrainingDiverged
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint
from hdrqn_ros.training.episodes import EpisodeBuilder
from hdrqn_ros.training.rollout import Rollout
from hdrqn_ros.training.learner import build_agent
from hdrqn_ros.training.trainer import Trainer

ENV = "hdrqn/GridWorld-2Goals-v0"


def tiny(**overrides):
    """A few episodes on 2 environments; full-size networks, small batches."""
    base = dict(episodes=6, num_envs=2, learning_starts=0, eval_every=3, eval_episodes=2, checkpoint_every=3,
                sub={"batch_size": 2, "replay_episodes": 50}, meta={"batch_size": 2, "replay_episodes": 50})
    return build_config([], **{**base, **overrides})


def _record(algo: str, steps: int, seed: int = 7, eps: float = 0.5):
    torch.manual_seed(seed)  # the networks' initial weights
    cfg = build_config([], algo=algo)
    agent = build_agent(cfg)
    rollout = Rollout(make_batch(ENV, 2), agent, seed=seed)
    builder = EpisodeBuilder(2, agent.meta is not None)
    rng = np.random.default_rng(0)
    episodes = {0: [], 1: []}
    for _ in range(steps):
        for i, sub, meta, stats in builder.add(rollout.step(eps, eps, rng)):
            episodes[i].append((sub, meta, stats))
    return episodes


@pytest.mark.parametrize("algo", ["hdrqn-v2", "drqn"])
def test_recorded_transitions_replay_exactly_in_a_single_env(algo):
    """Every stored frame, reward, terminal flag, option boundary and subgoal image equals
    what a fresh single environment gives for the same seed and actions."""
    episodes = _record(algo, 150)
    for i, eps in episodes.items():
        assert len(eps) >= 2
        env = gym.make(ENV).unwrapped
        obs, _ = env.reset(seed=7 + i)  # batch env i is seeded seed + i
        for k, (sub, meta, stats) in enumerate(eps):
            if k:
                obs, _ = env.reset()
            starts = set(sub.segment_starts.tolist())
            seg = -1
            for t in range(sub.num_steps):
                np.testing.assert_array_equal(sub.frames[t], obs)
                if t in starts:
                    seg += 1
                    if meta is not None:
                        g = int(meta.fields["action"][seg])
                        env.set_subgoal(g)
                        np.testing.assert_array_equal(sub.segment_data["subgoal_image"][seg], env.subgoal_image(g))
                obs, classical, term, trunc, info = env.step(int(sub.fields["action"][t]))
                if meta is not None:
                    assert sub.fields["reward"][t] == info["intrinsic"]
                    assert sub.fields["terminal"][t] == (info["subgoal_reached"] or term)
                else:
                    assert sub.fields["reward"][t] == np.float32(classical)
                    assert sub.fields["terminal"][t] == term
            np.testing.assert_array_equal(sub.frames[-1], obs)
            assert term or trunc
            assert stats.success == info["success"]


def test_meta_transitions_sum_extrinsic_reward_over_each_option():
    for eps in _record("hdrqn-v2", 120).values():
        for sub, meta, stats in eps:
            assert meta.num_steps == sub.num_segments == stats.options
            assert meta.fields["reward"].sum() == pytest.approx(stats.extrinsic, abs=1e-5)
            np.testing.assert_array_equal(meta.frames[0], 0.0)  # first decision sees zeros (v2)
            assert meta.frames.shape[1:] == (256,)
            assert meta.fields["terminal"][:-1].sum() == 0


@pytest.mark.parametrize("algo", ALGOS)
def test_every_algorithm_trains_and_writes_its_run_directory(algo, tmp_path):
    cfg = tiny(algo=algo)
    summary = Trainer(cfg, tmp_path, progress=False, tensorboard=False).run()
    assert summary["episodes"] == 6
    lines = (tmp_path / "train.csv").read_text().splitlines()
    assert len(lines) == 1 + 6 and lines[0].startswith("episode,env_steps")
    assert len((tmp_path / "eval.csv").read_text().splitlines()) == 1 + 2  # at episodes 3 and 6
    agent = build_agent(cfg)
    assert agent.sub.updates == 0
    payload = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    agent.load_state_dict(payload["agent"])
    assert agent.sub.updates > 0
    assert payload["progress"]["episodes"] == 6
    assert summary["final_eval"]["episodes"] == 2


def test_each_controllers_losses_are_logged_every_few_updates(tmp_path):
    """Per controller, every ``log_every_updates`` updates: a losses.csv row of the means of
    TD loss, Q of the taken actions, target and gradient norm (the meta-controller's also by
    option index, beside the return obtained); TensorBoard's ``losses/<controller>/<stat>``;
    the latest TD loss and Q in train.csv's episode rows."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from hdrqn_ros.training.metrics import read_csv, read_losses

    trainer = Trainer(tiny(log_every_updates=4), tmp_path, progress=False, tensorboard=True)
    trainer.run()
    header = (tmp_path / "losses.csv").read_text().splitlines()[0]
    by_index = [f"{stat}_opt{i}" for stat in ("q", "return") for i in range(4)]
    assert header == ",".join(["episode,env_steps,updates,controller,td_loss,q_taken,target,grad_norm", *by_index])
    losses, train = read_losses(tmp_path / "losses.csv"), read_csv(tmp_path / "train.csv")
    assert np.isnan(np.stack([losses["sub"][c] for c in by_index])).all()  # the meta-controller's only
    first_options = np.stack([losses["meta"][c] for c in ("q_opt0", "return_opt0")])
    assert np.isfinite(first_options).all() and (losses["meta"]["return_opt0"] >= 0).all()
    for ctrl in (trainer.agent.sub, trainer.agent.meta):
        rows = {k: v for k, v in losses[ctrl.name].items() if k not in by_index}
        assert rows["updates"].tolist() == list(range(4, ctrl.updates + 1, 4)) and len(rows["updates"]) >= 3
        assert np.isfinite(np.stack(list(rows.values()))).all() and (rows["grad_norm"] >= 0).all()
        # the meta-controller's first few episodes may leave it nothing to learn (a zero loss)
        some = np.all if ctrl is trainer.agent.sub else np.any
        assert some(rows["td_loss"] > 0) and some(rows["grad_norm"] > 0)
        assert not np.array_equal(rows["q_taken"], rows["target"])
        assert np.diff(rows["env_steps"]).min() > 0 and np.diff(rows["episode"]).min() >= 0
        # train.csv: the latest row as the episode ended (empty before the first one)
        for stat in ("td_loss", "q_taken"):
            column = train[f"{ctrl.name}_{stat}"]
            assert np.isnan(column[0]) and column[-1] == rows[stat][-1]
            assert set(column[~np.isnan(column)]) <= set(rows[stat])
    tags = EventAccumulator(str(tmp_path / "tb")).Reload().Tags()["scalars"]
    stats = ("td_loss", "q_taken", "target", "grad_norm")
    assert {f"losses/{c}/{stat}" for c in ("sub", "meta") for stat in stats} <= set(tags)
    assert {"losses/meta/q_opt0", "losses/meta/return_opt0"} <= set(tags) and "losses/sub/q_opt0" not in tags
    assert "train/success" in tags and not any(tag.startswith("train/sub_") for tag in tags)


def test_update_means_average_each_controller_over_its_own_updates():
    from hdrqn_ros.agents.controller import UpdateStats
    from hdrqn_ros.training.update_means import UpdateMeans

    means = UpdateMeans(every=2)

    def stats(x):
        return UpdateStats(*(torch.tensor(float(x + i)) for i in range(4)))

    assert means.add("sub", stats(1)) is None
    assert means.add("meta", stats(10)) is None
    assert means.add("sub", stats(3)) == {"td_loss": 2.0, "q_taken": 3.0, "target": 4.0, "grad_norm": 5.0}
    assert means.add("sub", stats(5)) is None  # a new block
    assert means.add("meta", stats(20)) == {"td_loss": 15.0, "q_taken": 16.0, "target": 17.0, "grad_norm": 18.0}


def test_a_run_begun_before_the_loss_columns_keeps_its_train_csv_header(tmp_path):
    """Resuming a run whose train.csv has no loss columns appends rows under its own header."""
    from hdrqn_ros.training.metrics import TRAIN_COLUMNS, MetricsLog
    from hdrqn_ros.training.metrics import read_csv

    old = ",".join(TRAIN_COLUMNS)
    (tmp_path / "train.csv").write_text(old + "\n" + ",".join(["1"] * len(TRAIN_COLUMNS)) + "\n")
    log = MetricsLog(tmp_path, tensorboard=False, controllers=("sub", "meta"))
    log.train({**dict.fromkeys(TRAIN_COLUMNS, 2), "sub_td_loss": 0.5, "sub_q_taken": 0.1})
    log.close()
    lines = (tmp_path / "train.csv").read_text().splitlines()
    assert lines == [old, ",".join(["1"] * len(TRAIN_COLUMNS)), ",".join(["2"] * len(TRAIN_COLUMNS))]
    assert read_csv(tmp_path / "train.csv")["episode"].tolist() == [1.0, 2.0]


def test_curves_show_each_controllers_losses_when_the_run_has_them(tmp_path):
    """``hdrqn plot``'s figure gains a row of loss panels (TD loss, mean Q, gradient norm per
    controller) for a run with losses.csv; a run without one (older runs) still plots."""
    from matplotlib.image import imread

    from hdrqn_ros.training.metrics import TRAIN_COLUMNS
    from hdrqn_ros.training.plots import plot_runs

    run = tmp_path / "run"
    run.mkdir()
    rows = [",".join(str(e if c == "episode" else 1) for c in TRAIN_COLUMNS) + ("," if e < 3 else ",0.5")
            for e in range(1, 6)]
    (run / "train.csv").write_text("\n".join([",".join(TRAIN_COLUMNS + ["sub_td_loss"]), *rows]) + "\n")
    (run / "losses.csv").write_text("episode,env_steps,updates,controller,td_loss,q_taken,target,grad_norm\n"
                                    "2,100,4,sub,0.5,0.1,0.2,3\n3,110,8,sub,0.4,0.2,0.3,2\n"
                                    "3,120,4,meta,0.05,0.7,0.8,1\n4,150,12,sub,0.3,0.3,0.3,1\n")
    with_losses = imread(plot_runs([run], tmp_path / "with.png", window=2)).shape[0]
    by_index = ",".join(f"{stat}_opt{i}" for stat in ("q", "return") for i in range(4))
    (run / "losses.csv").write_text(f"episode,env_steps,updates,controller,td_loss,q_taken,target,grad_norm,{by_index}\n"
                                    "2,100,4,sub,0.5,0.1,0.2,3,,,,,,,,\n"
                                    "3,120,4,meta,0.05,0.7,0.8,1,0.9,0.5,0.2,nan,0.8,0.4,0.1,nan\n"
                                    "4,150,8,meta,0.05,0.7,0.8,1,0.9,0.5,0.2,0.1,0.8,0.4,0.1,0.0\n")
    with_values = imread(plot_runs([run], tmp_path / "values.png", window=2)).shape[0]
    (run / "losses.csv").unlink()
    without = imread(plot_runs([run], tmp_path / "without.png", window=2)).shape[0]
    assert with_losses == 3 * without // 2  # three rows of panels instead of two
    assert with_values == 2 * without  # and a fourth: the meta-controller's Q by option index


def test_resume_continues_counters_and_csv(tmp_path):
    Trainer(tiny(episodes=4), tmp_path, progress=False, tensorboard=False).run()
    first = load_checkpoint(tmp_path / "checkpoints" / "last.pt")["progress"]
    with pytest.raises(CheckpointError, match="--resume"):
        Trainer(tiny(episodes=8), tmp_path, progress=False, tensorboard=False)
    resumed = Trainer(tiny(episodes=8), tmp_path, resume=True, progress=False, tensorboard=False)
    assert resumed.changed_settings == [] and "changed" not in resumed.resumed_line()  # a bigger budget only
    resumed.run()
    second = load_checkpoint(tmp_path / "checkpoints" / "last.pt")["progress"]
    assert second["episodes"] == 8 and second["env_steps"] > first["env_steps"]
    episodes = [int(line.split(",")[0]) for line in (tmp_path / "train.csv").read_text().splitlines()[1:]]
    assert episodes == list(range(1, 9))


def test_resume_names_the_settings_changed_since_the_run_started(tmp_path):
    Trainer(tiny(episodes=2), tmp_path, progress=False, tensorboard=False).run()
    changed = tiny(episodes=4, sub={"batch_size": 2, "replay_episodes": 50, "gamma": 0.99}, flat={"gamma": 0.5})
    resumed = Trainer(changed, tmp_path, resume=True, progress=False, tensorboard=False)
    # hDRQNv2 learns with sub and meta: flat's change does not concern it, sub's does
    assert resumed.changed_settings == ["sub.gamma: 0.9 -> 0.99"]
    assert resumed.resumed_line().endswith("; settings changed since the run started: sub.gamma: 0.9 -> 0.99")


def test_checkpoint_of_another_algorithm_is_refused(tmp_path):
    Trainer(tiny(episodes=2, algo="dqn"), tmp_path, progress=False, tensorboard=False).run()
    with pytest.raises(CheckpointError, match="algo='dqn'"):
        Trainer(tiny(episodes=4, algo="hdrqn-v2"), tmp_path, resume=True, progress=False, tensorboard=False)


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", b"PK\x03\x04garbage"])
def test_corrupted_checkpoint_is_a_clear_error(tmp_path, content):
    path = tmp_path / "bad.pt"
    path.write_bytes(content)
    with pytest.raises(CheckpointError, match="bad.pt") as error:
        load_checkpoint(path)
    assert "weights_only" not in str(error.value)  # never torch's advice to load it unsafely


class _Evil:
    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('x')",))


def test_pickle_payload_in_checkpoint_is_refused(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.pt"
    torch.save({"format": "hdrqn_ros-checkpoint", "x": _Evil()}, path)
    with pytest.raises(CheckpointError):
        load_checkpoint(path)
    assert not (tmp_path / "PWNED").exists()


def test_divergence_keeps_the_last_good_checkpoint(tmp_path):
    trainer = Trainer(tiny(episodes=3), tmp_path, progress=False, tensorboard=False)
    trainer.run()
    ckpt = tmp_path / "checkpoints" / "last.pt"
    digest = hashlib.sha256(ckpt.read_bytes()).hexdigest()
    resumed = Trainer(tiny(episodes=9), tmp_path, resume=True, progress=False, tensorboard=False)
    with torch.no_grad():
        for p in resumed.agent.sub.online.parameters():
            p.fill_(float("nan"))
    with pytest.raises(TrainingDiverged):
        resumed.run()
    assert hashlib.sha256(ckpt.read_bytes()).hexdigest() == digest


def test_config_errors_name_the_key(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sub:\n  batch_sise: 4\n")
    with pytest.raises(ConfigError, match=r"sub\.batch_sise.*bad\.yaml|bad\.yaml[\s\S]*sub\.batch_sise"):
        build_config([bad])
    bad.write_text("episodes: many\n")
    with pytest.raises(ConfigError, match="episodes"):
        build_config([bad])
    with pytest.raises(ConfigError, match="unknown env"):
        build_config([], env="hdrqn/Nope-v0")


def test_partial_nested_override_keeps_other_defaults(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("meta:\n  lr: 0.0005\n")
    cfg = build_config([f])
    assert cfg.meta.lr == 0.0005 and cfg.meta.batch_size == 12 and cfg.meta.seq_len == 2


def test_cli_misuse_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["train", "--algo", "ppo", "--out", str(tmp_path)])
    assert exc.value.code == 2
    bad = tmp_path / "bad.yaml"
    bad.write_text("learning_rate: 1\n")
    assert main(["train", "--config", str(bad), "--out", str(tmp_path / "r")]) == 2
    assert "learning_rate" in capsys.readouterr().err
    assert main(["eval", "--checkpoint", str(tmp_path / "missing.pt")]) == 2
    assert main(["plot", str(tmp_path), "--out", str(tmp_path / "x.png")]) == 2
    assert main(["train", "--view", "7x7", "--out", str(tmp_path / "r2")]) == 2
    capsys.readouterr()
    for argv, usage in ((["eval", "--checkpoint", "x.pt", "--bogus"], "hdrqn eval"),
                        (["bag", "info", "bags/x", "--bogus"], "hdrqn bag info")):
        with pytest.raises(SystemExit) as exc:  # an unknown flag: the subcommand's own usage and error
            main(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.startswith(f"usage: {usage} ") and \
            err.endswith(f"{usage}: error: unrecognized arguments: --bogus\n")


def test_cli_train_eval_plot_round_trip(tmp_path, capsys):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text("num_envs: 2\nlearning_starts: 0\neval_episodes: 2\neval_every: 2\n"
                   "sub: {batch_size: 2}\nmeta: {batch_size: 2}\n")
    run = tmp_path / "run"
    assert main(["train", "--config", str(cfg), "--episodes", "2", "--out", str(run), "--no-progress"]) == 0
    assert "greedy eval: success" in capsys.readouterr().out
    assert (run / "curves.png").stat().st_size > 10_000
    assert main(["eval", "--checkpoint", str(run / "checkpoints" / "last.pt"), "--episodes", "3"]) == 0
    assert '"episodes": 3' in capsys.readouterr().out
    assert main(["eval", "--checkpoint", str(run / "checkpoints" / "last.pt"), "--episodes", "6", "--num-envs", "3"]) == 0
    assert '"episodes": 6' in capsys.readouterr().out
    assert main(["plot", str(run), str(run), "--out", str(tmp_path / "both.png")]) == 0


def test_eval_plays_exactly_the_episodes_asked_for_or_says_why_not(capsys):
    """Each environment plays as many episodes: --num-envs must divide --episodes (exit 2 naming
    the counts that would), and by default the most environments that do, up to 256, play."""
    from hdrqn_ros.training.learner import eval_envs

    assert (eval_envs(100), eval_envs(300), eval_envs(512), eval_envs(7, 7)) == (100, 150, 256, 7)
    assert main(["eval", "--checkpoint", "x.pt", "--episodes", "10", "--num-envs", "8"]) == 2
    err = capsys.readouterr().err
    assert "10 episodes do not split evenly over 8 environments" in err and "ask for 16 episodes" in err


def test_montezuma_trains_through_the_same_loop(tmp_path):
    cfg = tiny(env="hdrqn/MontezumaRevenge-v0", episodes=2, env_kwargs={"max_steps": 30}, eval_every=0,
               sub_only_episodes=1)
    summary = Trainer(cfg, tmp_path, progress=False, tensorboard=False).run()
    assert summary["episodes"] == 2 and summary["env_steps"] >= 60


def test_every_shipped_config_is_valid():
    from pathlib import Path

    files = sorted((Path(__file__).parents[1] / "config").glob("*.yaml"))
    assert len(files) >= 8
    for f in files:
        build_config([f])


def test_thesis_replay_configuration_fits_in_2_gib():
    """5000 sub episodes and 1000 meta episodes of the longest gridworld episodes (50 steps)."""
    eps = [e for runs in _record("hdrqn-v2", 200).values() for e in runs]
    sub_per_step = sum(sub.nbytes for sub, _, _ in eps) / sum(sub.num_steps for sub, _, _ in eps)
    meta_per_episode = max(meta.nbytes for _, meta, _ in eps)
    total = 5000 * 50 * sub_per_step + 1000 * meta_per_episode
    assert sub_per_step < 6 * 1024
    assert total <= 2 * 1024**3


def test_meta_never_picks_the_subgoal_it_stands_on():
    picked_own_place, decisions_at_a_place = 0, 0
    for eps in _record("hdrqn-v2", 1500, eps=1.0).values():  # a random walk reaches subgoals
        for _, meta, _ in eps:
            prev_place = meta.fields["next_invalid"][:-1]
            nxt = meta.fields["action"][1:]
            decisions_at_a_place += int((prev_place >= 0).sum())
            picked_own_place += int(((prev_place >= 0) & (nxt == prev_place)).sum())
            assert meta.fields["next_invalid"].dtype == np.int8
    assert decisions_at_a_place >= 3 and picked_own_place == 0


@pytest.mark.parametrize("argv, message", [
    (["train", "--num-envs", "100000"], "num_envs: Input should be less than or equal to 4096"),
    (["train", "--set", "eval_episodes=1000000"], "eval_episodes: Input should be less than or equal to 100000"),
    (["up", "--groups", "65"], "--groups must be in 1..64"),
    (["up", "--num-envs", "0"], "--num-envs must be in 1..64"),
    (["eval", "--checkpoint", "x.pt", "--num-envs", "5000"], "--num-envs must be in 1..4096"),
])
def test_oversized_batches_and_graphs_are_refused(argv, message, tmp_path, capsys):
    """A typo like 100000 environments is a clear error, not a machine filling its memory."""
    out = ["--out", str(tmp_path / "run")] if argv[0] != "eval" else []
    assert main([*argv, *out]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_learner_schedule_and_store(tmp_path):
    """The loop skeleton's bookkeeping: ``store`` counts a run's episodes (not recorded
    ones), ``due`` fires once per multiple of ``eval_every`` / ``checkpoint_every`` after
    ``begin``, and ``update_once`` waits for a batch of episodes and, for the
    meta-controller, for phase 2."""
    from hdrqn_ros.training.learner import Learner

    cfg = tiny(eval_every=3, checkpoint_every=2, sub_only_episodes=3, learning_starts=10**6)
    learner = Learner(cfg, tmp_path, progress=False, tensorboard=False)
    rollout = Rollout(make_batch(ENV, 2), learner.agent, seed=0)
    builder = EpisodeBuilder(2, True)
    rng = np.random.default_rng(0)
    items = []
    while len(items) < 5:
        items += builder.add(rollout.step(1.0, 1.0, rng))
    steps = sum(stats.steps for *_, stats in items[:2])
    assert learner.store(items[:2], counted=False) == (2, steps)
    assert learner.episodes == 0 and len(learner.agent.sub.replay) == len(learner.agent.meta.replay) == 2
    learner.begin()
    learner.update_once(offline=True)  # a batch of 2 episodes, but phase 1: the sub-controller only
    assert (learner.agent.sub.updates, learner.agent.meta.updates) == (1, 0)
    learner.update_once()  # online: before learning_starts, nothing learns
    assert (learner.agent.sub.updates, learner.agent.meta.updates) == (1, 0)
    fired = []
    for item in items[2:5]:
        learner.store([item])
        fired.append((learner.episodes, learner.due("eval"), learner.due("checkpoint"), learner.due("checkpoint")))
    assert fired == [(1, False, False, False), (2, False, True, False), (3, True, False, False)]
    learner.update_once(offline=True)  # phase 2 from sub_only_episodes = 3 on: both learn
    assert (learner.agent.sub.updates, learner.agent.meta.updates) == (2, 1)
    learner.log.close()
