"""Recording transitions to rosbag2 MCAP bags and reading them back (no ROS, real bags)."""
from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from hdrqn_ros.config import build_config
from hdrqn_ros.protocol import wire
from hdrqn_ros.recording.bag import TYPESTORE, BagError, BagWriter, bag_summary, read_messages
from hdrqn_ros.recording.transitions import (BagReadStats, RosbagsMessages, TransitionRecorder, bag_config,
                                             episode_summary, read_episodes)
from hdrqn_ros.training.trainer import Trainer

ENV = "hdrqn/GridWorld-2Goals-v0"


def small_config(algo: str, episodes: int = 9, **kw):
    return build_config([], algo=algo, env=ENV, episodes=episodes, num_envs=3, learning_starts=40, update_every=5,
                        eval_every=0, sub={"batch_size": 2}, meta={"batch_size": 2}, **kw)


def train_and_record(tmp_path: Path, algo: str, **bag_options):
    """Train a few episodes while recording; returns (cfg, bag path, episodes the trainer stored, trainer)."""
    cfg = small_config(algo)
    sink = TransitionRecorder(tmp_path / f"bag-{algo}", cfg, cfg.num_envs, **bag_options)
    trainer = Trainer(cfg, tmp_path / f"run-{algo}", progress=False, tensorboard=False, sink=sink)
    stored = []
    store = trainer.store

    def keep(items, counted=True):
        items = list(items)
        stored.extend((sub, meta) for _, sub, meta, _ in items)
        return store(items, counted)

    trainer.store = keep
    trainer.run()
    return cfg, sink.path, stored, trainer


def episode_bytes(sub, meta) -> tuple:
    """Every array of a (sub, meta) episode pair, as bytes (bit-exact comparison)."""
    def one(ep):
        if ep is None:
            return None
        return (ep.frames.tobytes(), ep.frames.shape, tuple((k, v.tobytes()) for k, v in sorted(ep.fields.items())),
                None if ep.segment_starts is None else ep.segment_starts.tobytes(),
                tuple((k, v.tobytes()) for k, v in sorted(ep.segment_data.items())))
    return one(sub), one(meta)


@pytest.mark.parametrize("algo", ["hdrqn-v2", "hdrqn-v1", "dqn"])
def test_round_trip_is_bit_exact(tmp_path, algo):
    cfg, bag, stored, trainer = train_and_record(tmp_path, algo)
    stats = BagReadStats()
    read = list(read_episodes([bag], cfg, trainer.agent.num_subgoals, stats))
    assert len(stored) == cfg.episodes
    # every episode the trainer stored comes back identical (frames are the observations); the
    # bag also holds the episodes that finished after the trainer had enough (fewer than N)
    missing = Counter(episode_bytes(*e) for e in stored) - Counter(episode_bytes(s, m) for _, s, m, _ in read)
    assert not missing
    assert cfg.episodes <= len(read) < cfg.episodes + cfg.num_envs
    assert stats.episodes[str(bag)] == len(read)
    assert bag_config(bag)["algo"] == algo
    groups = {g for g, *_ in read}
    assert groups == {"/group0", "/group1", "/group2"}


def test_episode_boundaries_and_returns_are_in_the_bag(tmp_path):
    cfg, bag, stored, trainer = train_and_record(tmp_path, "hdrqn-v2")
    summary = episode_summary(bag)
    assert set(summary) == {"/group0", "/group1", "/group2"}
    assert sum(g["episodes"] for g in summary.values()) >= cfg.episodes
    for g in summary.values():
        assert g["mean_steps"] == 50  # an untrained agent: every episode runs into the step limit


def test_a_recording_is_read_by_mcap_with_ros2_decoding(tmp_path):
    _, bag, _, _ = train_and_record(tmp_path, "hdrqn-v2")
    decoded = 0
    for file in sorted(bag.glob("*.mcap")):
        with file.open("rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for schema, channel, message, ros_msg in reader.iter_decoded_messages():
                assert schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
                if channel.topic.endswith("/observation"):
                    assert (ros_msg.height, ros_msg.width, ros_msg.encoding) == (44, 44, "rgb8")
                decoded += 1
    assert decoded == bag_summary(bag)["message_count"] > 0


def test_split_recording_reads_back_the_same(tmp_path):
    cfg, bag, stored, trainer = train_and_record(tmp_path, "hdrqn-v2", split_bytes=64 * 1024)
    assert len(list(bag.glob("*.mcap"))) > 1
    read = list(read_episodes([bag], cfg, trainer.agent.num_subgoals))
    assert {episode_bytes(*e) for e in stored} <= {episode_bytes(s, m) for _, s, m, _ in read}


def test_a_killed_recording_is_repaired_and_read_up_to_its_last_chunk(tmp_path):
    cfg, bag, stored, trainer = train_and_record(tmp_path, "hdrqn-v2")
    full = Counter(episode_bytes(s, m) for _, s, m, _ in read_episodes([bag], cfg, trainer.agent.num_subgoals))
    file = next(bag.glob("*.mcap"))
    data = file.read_bytes()
    file.write_bytes(data[: int(len(data) * 0.6)])  # what a kill -9 leaves: no summary, a cut chunk
    (bag / "metadata.yaml").unlink()
    run = subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", "bag", "repair", str(bag)], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    salvaged = Counter(episode_bytes(s, m) for _, s, m, _ in read_episodes([bag], cfg, trainer.agent.num_subgoals))
    assert 0 < sum(salvaged.values()) < sum(full.values())
    assert not salvaged - full  # the recovered prefix holds only what was recorded, unchanged


def hdrqn(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def test_cli_records_then_trains_offline(tmp_path):
    bag, run = tmp_path / "bag", tmp_path / "offline"
    rec = hdrqn("train", "--episodes", "6", "--num-envs", "2", "--out", tmp_path / "run", "--record", bag,
                "--eval-every", "0", "--no-progress", "--set", "learning_starts=50", "--set", "sub.batch_size=2",
                "--set", "meta.batch_size=2")
    assert rec.returncode == 0, rec.stderr
    assert "recorded" in rec.stderr and bag.is_dir()
    info = hdrqn("bag", "info", bag)
    assert info.returncode == 0 and "/group1/env_step" in info.stdout
    off = hdrqn("train", "--from-bag", bag, "--out", run, "--updates", "20", "--set", "eval_episodes=4",
                "--no-progress")
    assert off.returncode == 0, off.stderr
    assert "config from the bag's recorded config" in off.stderr
    assert "done: 20 updates on" in off.stdout
    assert (run / "checkpoints" / "last.pt").exists() and (run / "summary.json").exists()
    again = hdrqn("train", "--episodes", "6", "--out", tmp_path / "run2", "--record", bag, "--no-progress")
    assert again.returncode == 2 and "already exists" in again.stderr  # never overwrites a recording


def write_bag(path: Path, topics: dict[str, str], messages: list[tuple[str, object]]) -> Path:
    with BagWriter(path) as w:
        for topic, type_name in topics.items():
            w.add_topic(topic, type_name)
        for i, (topic, msg) in enumerate(messages):
            w.write(topic, 1_000 + i, TYPESTORE.serialize_cdr(msg, topics[topic]))
    return path


def test_a_re_published_step_is_counted_once(tmp_path):
    """An environment re-publishes a step nobody answered in time: ``bag info`` counts it
    once, not as an episode cut short."""
    def step(key: int, t: int, end: bool = False):
        values = dict.fromkeys(wire.STEP_FIELDS, 0.0)
        values.update(key=key, t=t, terminated=float(end), success=float(end), classical=float(end))
        return wire.make_record(RosbagsMessages, wire.FLOATS, wire.STEP_FIELDS, [values[f] for f in wire.STEP_FIELDS])

    steps = [step(1, 0), step(1, 0), step(2, 1), step(3, 2, end=True), step(4, 0), step(5, 1), step(5, 1),
             step(6, 2, end=True)]
    bag = write_bag(tmp_path / "bag", {"/env_step": wire.FLOATS}, [("/env_step", m) for m in steps])
    assert episode_summary(bag)["/"] == {"num_envs": 1, "episodes": 2, "incomplete": 0, "mean_return": 1.0,
                                         "success_rate": 1.0, "mean_steps": 2.0}


def test_bad_bags_exit_2_naming_file_and_problem(tmp_path):
    not_a_bag = tmp_path / "notabag"
    not_a_bag.mkdir()
    (not_a_bag / "notes.txt").write_text("hello")
    r = hdrqn("train", "--from-bag", not_a_bag, "--out", tmp_path / "r1")
    assert r.returncode == 2 and str(not_a_bag) in r.stderr and "Traceback" not in r.stderr

    # a bag, but not of transitions
    String = TYPESTORE.types["std_msgs/msg/String"]
    other = write_bag(tmp_path / "chatter", {"/chatter": "std_msgs/msg/String"}, [("/chatter", String(data="hi"))])
    r = hdrqn("train", "--from-bag", other, "--out", tmp_path / "r2")
    assert r.returncode == 2 and "no env_step topic" in r.stderr and str(other) in r.stderr

    # unknown message types in the metadata
    meta = other / "metadata.yaml"
    meta.write_text(meta.read_text().replace("std_msgs/msg/String", "my_pkg/msg/Secret"))
    r = hdrqn("train", "--from-bag", other, "--out", tmp_path / "r3")
    assert r.returncode == 2 and "my_pkg/msg/Secret" in r.stderr and str(other) in r.stderr

    # missing topics: an hDRQNv1 recording has no sub_state, which hDRQNv2 needs
    cfg, bag, _, _ = train_and_record(tmp_path, "hdrqn-v1")
    r = hdrqn("train", "--from-bag", bag, "--algo", "hdrqn-v2", "--out", tmp_path / "r4")
    assert r.returncode == 2 and "sub_state is missing" in r.stderr and str(bag) in r.stderr

    # mismatched image sizes: a two-goal recording read as the three-goal domain
    r = hdrqn("train", "--from-bag", bag, "--env", "hdrqn/GridWorld-3Goals-v0", "--out", tmp_path / "r5")
    assert r.returncode == 2 and "subgoal_images" in r.stderr and "image must be 132x44" in r.stderr

    # fewer episodes than a batch: no update could run, so it is an error, not "done: 0 updates"
    r = hdrqn("train", "--from-bag", bag, "--set", "sub.batch_size=1000", "--set", "meta.batch_size=1000",
              "--out", tmp_path / "r6")
    assert r.returncode == 2 and "no controller can update" in r.stderr and "batch_size 1000" in r.stderr, r.stderr
    r = hdrqn("train", "--from-bag", bag, "--set", "meta.batch_size=1000", "--updates", "2", "--eval-every", "0",
              "--out", tmp_path / "r7")
    assert r.returncode == 0 and "warning: the meta controller's replay holds" in r.stderr, r.stderr
    for out in ("r1", "r2", "r3", "r4", "r5", "r6"):
        assert not (tmp_path / out / "checkpoints").exists()


def test_observation_of_another_size_is_an_error(tmp_path):
    cfg = small_config("dqn")
    Image, Header, Time = (TYPESTORE.types[t] for t in ("sensor_msgs/msg/Image", "std_msgs/msg/Header",
                                                        "builtin_interfaces/msg/Time"))
    m = RosbagsMessages()
    step = wire.make_record(m, wire.FLOATS, wire.STEP_FIELDS, [10_000_000, 0, 0, 0, 0] + [0] * 11)
    image = Image(header=Header(stamp=Time(sec=0, nanosec=10_000_000), frame_id="x"), height=84, width=84,
                  encoding="rgb8", is_bigendian=0, step=84 * 3, data=np.zeros(84 * 84 * 3, np.uint8))
    bag = write_bag(tmp_path / "big", {"/env_step": wire.FLOATS, "/observation": wire.IMAGE, "/action": wire.INTS},
                    [("/env_step", step), ("/observation", image)])
    with pytest.raises(BagError, match=r"big: topic /observation: image must be 44x44"):
        list(read_episodes([bag], cfg, 2))


def test_graph_style_bag_with_foreign_topics(tmp_path):
    """What ``ros2 bag record -s mcap`` of a running graph holds: the group topics under
    their namespace plus topics we do not need (/clock, /rosout...); it trains the same."""
    cfg, bag, stored, trainer = train_and_record(tmp_path, "hdrqn-v2")
    copy = tmp_path / "graph-bag"
    with BagWriter(copy) as w:
        keep = {}
        for topic, type_name, t, cdr in read_messages(bag):
            if not topic.startswith("/group1/"):
                continue
            name = topic.replace("/group1", "/robot")
            if name not in keep:
                keep[name] = w.add_topic(name, type_name)
            w.write(keep[name], t, cdr)
        w.add_topic("/rosout", "rcl_interfaces/msg/Log")
        w.add_topic("/clock", "rosgraph_msgs/msg/Clock")
        Clock, Time = TYPESTORE.types["rosgraph_msgs/msg/Clock"], TYPESTORE.types["builtin_interfaces/msg/Time"]
        w.write("/clock", t + 1, TYPESTORE.serialize_cdr(Clock(clock=Time(sec=1, nanosec=0)), "rosgraph_msgs/msg/Clock"))
    read = list(read_episodes([copy], cfg, trainer.agent.num_subgoals))
    original = [e for e in read_episodes([bag], cfg, trainer.agent.num_subgoals) if e[0] == "/group1"]
    assert [g for g, *_ in read] == ["/robot"] * len(original)
    assert [episode_bytes(s, m) for _, s, m, _ in read] == [episode_bytes(s, m) for _, s, m, _ in original]


@pytest.fixture
def small_disk(tmp_path):
    """A 400 KiB tmpfs (root only; skipped where mounting is not allowed)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()

    def mount(*options):
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", ",".join(("size=400k",) + options), "tmpfs", str(mnt)],
                           capture_output=True, text=True)
        if r.returncode:
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
        return mnt
    yield mount
    subprocess.run(["umount", str(mnt)], capture_output=True)


def test_disk_full_while_recording_stops_cleanly_and_keeps_everything(tmp_path, small_disk):
    disk, run = small_disk(), tmp_path / "run"
    r = hdrqn("train", "--episodes", "400", "--num-envs", "4", "--out", run, "--record", disk / "bag",
              "--record-split-mb", "0.3", "--eval-every", "0", "--no-progress", "--set", "learning_starts=100",
              "--set", "sub.batch_size=2", "--set", "meta.batch_size=2")
    assert r.returncode == 2, r.stderr
    assert "No space left on device" in r.stderr and str(disk / "bag") in r.stderr and "Traceback" not in r.stderr
    assert (run / "checkpoints" / "last.pt").exists()  # what was trained is kept
    kept = tmp_path / "kept"
    subprocess.run(["cp", "-r", str(disk / "bag"), str(kept)], check=True)
    assert hdrqn("bag", "repair", kept).returncode == 0
    cfg = small_config("hdrqn-v2")
    assert list(read_episodes([kept], cfg, 2))  # the finished files stay readable


def test_read_only_disk_is_a_clear_error(tmp_path, small_disk):
    disk = small_disk("ro")
    r = hdrqn("train", "--episodes", "2", "--out", tmp_path / "run", "--record", disk / "bag", "--no-progress")
    assert r.returncode == 2 and str(disk / "bag") in r.stderr and "Read-only file system" in r.stderr
    assert "Traceback" not in r.stderr


SAMPLE = Path(__file__).resolve().parents[1] / "bags" / "hdrqn-v2_gridworld-2goals"


def test_offline_training_from_the_sample_bag_improves_the_greedy_policy(tmp_path):
    """Full-size hDRQNv2 networks, trained only from the sample bag (a trained agent's
    episodes at epsilon 0.3), then evaluated greedily in the environment."""
    from hdrqn_ros.training.offline import OfflineTrainer

    cfg = build_config([], base=bag_config(SAMPLE), eval_episodes=50)
    trainer = OfflineTrainer(cfg, tmp_path / "offline", progress=False, tensorboard=False)
    assert trainer.fill(read_episodes([SAMPLE], cfg, trainer.agent.num_subgoals)) >= 300
    summary = trainer.run(updates=900, evaluations=1)
    before, after = summary["before_eval"], summary["final_eval"]
    # untrained: no goal collected and -0.24 per episode; after: goals collected, return up
    assert after["extrinsic"] > before["extrinsic"]
    assert after["reward"] > before["reward"] + 0.15, (before, after)
