"""Replay snapshots: ``--resume`` continues with the replay the checkpoint was trained from
(issue 18 item 7); SIGKILL never pairs a checkpoint with another replay; a bad snapshot is
a clear error; ``save_replay: false`` writes none."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from hdrqn_ros.config import build_config
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint
from hdrqn_ros.training.learner import Learner
from hdrqn_ros.training.trainer import Trainer


def tiny(**overrides):
    base = dict(episodes=4, num_envs=2, learning_starts=20, eval_every=0, eval_episodes=2, checkpoint_every=2,
                sub={"batch_size": 2, "replay_episodes": 3}, meta={"batch_size": 2, "replay_episodes": 50})
    return build_config([], **{**base, **overrides})


def assert_same_replay(a, b):
    assert (len(a), a.num_steps, a.nbytes, a.capacity_episodes) == (len(b), b.num_steps, b.nbytes, b.capacity_episodes)
    assert a._rng.bit_generator.state == b._rng.bit_generator.state
    for i in range(len(a)):
        x, y = a[i], b[i]
        assert x.frames.dtype == y.frames.dtype and np.array_equal(x.frames, y.frames)
        assert np.array_equal(x.segment_starts, y.segment_starts)
        for mine, theirs in ((x.fields, y.fields), (x.segment_data, y.segment_data)):
            assert sorted(mine) == sorted(theirs)
            for k in mine:
                assert mine[k].dtype == theirs[k].dtype and np.array_equal(mine[k], theirs[k]), k


def snapshots(run_dir):
    return sorted((run_dir / "checkpoints").glob("replay-*.safetensors"))


def test_resume_restores_both_replays_exactly(tmp_path):
    cfg = tiny()
    trainer = Trainer(cfg, tmp_path, progress=False, tensorboard=False)
    trainer.run()
    saved = trainer.replays()
    assert set(saved) == {"sub", "meta"} and len(saved["sub"]) == 3  # the ring is full: evictions happened
    (snap,) = snapshots(tmp_path)  # the older snapshots are gone
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["progress"]["replay"]["file"] == snap.name
    resumed = Learner(tiny(episodes=8), tmp_path, resume=True, progress=False, tensorboard=False)
    assert resumed.replay_restored
    for role in ("sub", "meta"):
        assert_same_replay(saved[role], resumed.replays()[role])
    # later evictions happen as they would have: the oldest episode goes first
    second = resumed.replays()["sub"][1]
    resumed.replays()["sub"].add(saved["sub"][0])
    assert resumed.replays()["sub"][0] is second


def test_flat_agent_replay_is_restored(tmp_path):
    Trainer(tiny(algo="drqn", episodes=2), tmp_path, progress=False, tensorboard=False).run()
    resumed = Learner(tiny(algo="drqn", episodes=4), tmp_path, resume=True, progress=False, tensorboard=False)
    assert set(resumed.replays()) == {"sub"} and len(resumed.replays()["sub"]) == 2


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage"])
def test_damaged_snapshot_is_a_clear_error_naming_the_file(tmp_path, damage):
    Trainer(tiny(episodes=2), tmp_path, progress=False, tensorboard=False).run()
    (snap,) = snapshots(tmp_path)
    data = bytearray(snap.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "flip":
        data[-10] ^= 0xFF
    else:
        data = bytearray(b"not a snapshot")
    snap.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=snap.name):
        Learner(tiny(episodes=4), tmp_path, resume=True, progress=False, tensorboard=False)


def test_snapshot_of_another_shape_or_checkpoint_is_refused(tmp_path):
    Trainer(tiny(episodes=2), tmp_path / "a", progress=False, tensorboard=False).run()
    Trainer(tiny(episodes=2, seed=1), tmp_path / "b", progress=False, tensorboard=False).run()
    (a,), (b,) = snapshots(tmp_path / "a"), snapshots(tmp_path / "b")
    a.write_bytes(b.read_bytes())  # another run's replay under this checkpoint's name
    with pytest.raises(CheckpointError, match=a.name):
        Learner(tiny(episodes=4), tmp_path / "a", resume=True, progress=False, tensorboard=False)
    # same file, same digest, but resumed with another view (another frame shape)
    with pytest.raises(CheckpointError, match=b.name):
        Learner(tiny(episodes=4, env_kwargs={"view": 3}), tmp_path / "b", resume=True, progress=False,
                tensorboard=False)


def _rewrite_as_version1(run_dir, sub_gamma, meta_gamma, smdp_discount):
    """Rewrite the run's snapshot in version 1's layout (a ``discount`` field, as episodes were
    stored before the update read gamma: sub gamma; meta gamma, or gamma**k with
    ``smdp_discount``; no ``option_steps``) and point its checkpoint at it."""
    from safetensors import safe_open
    from safetensors.numpy import load_file, save_file

    from hdrqn_ros.hashing import file_sha256
    from hdrqn_ros.training.checkpoint import save_checkpoint

    (snap,) = snapshots(run_dir)
    with safe_open(str(snap), framework="numpy") as f:
        meta = json.loads(f.metadata()["hdrqn_ros"])
    tensors = load_file(str(snap))
    for key in [k for k in tensors if k.endswith("/field/action")]:
        role, prefix = key.split("/")[0], key[: -len("action")]
        if role == "sub":
            tensors[prefix + "discount"] = np.full(len(tensors[key]), sub_gamma, np.float32)
        else:
            k = tensors.pop(prefix + "option_steps")
            tensors[prefix + "discount"] = (meta_gamma ** k if smdp_discount else np.full(len(k), meta_gamma)
                                            ).astype(np.float32)
    meta["version"] = 1
    for info in meta["roles"].values():
        info["fields"] = sorted({*info["fields"], "discount"} - {"option_steps"})
    save_file(tensors, str(snap), metadata={"hdrqn_ros": json.dumps(meta)})
    ckpt = run_dir / "checkpoints" / "last.pt"
    payload = load_checkpoint(ckpt)
    payload["progress"]["replay"]["sha256"] = file_sha256(snap)
    save_checkpoint(ckpt, config=payload["config"], agent_state=payload["agent"], progress=payload["progress"])


@pytest.mark.parametrize("smdp_discount", [True, False])
def test_a_version1_snapshot_with_stored_discounts_loads_converted(tmp_path, smdp_discount):
    """A snapshot written before the discount was read at update time still resumes: the
    sub-controller's discount column is dropped, the meta-controller's becomes the options'
    lengths, exactly (round(log(discount) / log(gamma)) with ``smdp_discount``), or 1 where
    the discount never depended on them."""
    cfg = tiny(smdp_discount=smdp_discount)
    trainer = Trainer(cfg, tmp_path, progress=False, tensorboard=False)
    trainer.run()
    saved = trainer.replays()
    steps = np.concatenate([saved["meta"][i].fields["option_steps"] for i in range(len(saved["meta"]))])
    assert steps.max() > 1  # options of several steps: a conversion to 1 would show
    _rewrite_as_version1(tmp_path, cfg.sub.gamma, cfg.meta.gamma, smdp_discount)
    resumed = Learner(tiny(episodes=8, smdp_discount=smdp_discount), tmp_path, resume=True, progress=False,
                      tensorboard=False)
    assert resumed.replay_restored
    assert_same_replay(saved["sub"], resumed.replays()["sub"])
    if smdp_discount:
        assert_same_replay(saved["meta"], resumed.replays()["meta"])
    else:
        for i in range(len(saved["meta"])):
            ours = resumed.replays()["meta"][i].fields
            assert ours["option_steps"].dtype == np.int32 and (ours["option_steps"] == 1).all()
    updates = resumed.agent.meta.updates
    resumed.update_once(offline=True)  # the restored replays train
    assert resumed.agent.meta.updates == updates + 1


def test_save_replay_false_writes_no_snapshot_and_resumes_empty(tmp_path):
    Trainer(tiny(episodes=2, save_replay=False), tmp_path, progress=False, tensorboard=False).run()
    assert snapshots(tmp_path) == []
    assert "replay" not in load_checkpoint(tmp_path / "checkpoints" / "last.pt")["progress"]
    resumed = Learner(tiny(episodes=4), tmp_path, resume=True, progress=False, tensorboard=False)
    assert not resumed.replay_restored and all(len(r) == 0 for r in resumed.replays().values())
    assert resumed.resumed_line().endswith("at episode 2 (%d env steps); no replay snapshot: the replay refills "
                                           "before updates resume; settings changed since the run started: "
                                           "save_replay: False -> True" % resumed.env_steps)


def _episodes_logged(run_dir) -> int:
    try:
        return max(0, len((run_dir / "train.csv").read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def test_sigkilled_run_resumes_with_the_replay_of_its_last_checkpoint(tmp_path):
    run_dir = tmp_path / "run"
    common = ["--no-progress", "--set", "num_envs=2", "--set", "eval_every=0", "--set", "learning_starts=50",
              "--set", "sub.batch_size=2", "--set", "meta.batch_size=2", "--set", "checkpoint_every=2"]
    argv = [sys.executable, "-m", "hdrqn_ros.cli", "train", "--algo", "hdrqn-v2", "--episodes", "100000",
            "--out", str(run_dir), *common]
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    ckpt = run_dir / "checkpoints" / "last.pt"
    try:
        deadline = time.monotonic() + 120
        while not ckpt.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        assert ckpt.exists(), proc.stderr.read() if proc.poll() is not None else "no checkpoint in 120 s"
        first = _episodes_logged(run_dir)
        while _episodes_logged(run_dir) < first + 3 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.1)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    progress = load_checkpoint(ckpt)["progress"]
    snap = run_dir / "checkpoints" / progress["replay"]["file"]
    from safetensors import safe_open

    with safe_open(str(snap), framework="numpy") as f:
        held = {r: info["episodes"] for r, info in json.loads(f.metadata()["hdrqn_ros"])["roles"].items()}
    assert held["sub"] == progress["episodes"] >= 2 and held["meta"] == progress["episodes"]
    cfg = build_config([], algo="hdrqn-v2", num_envs=2, eval_every=0, learning_starts=50, checkpoint_every=2,
                       episodes=progress["episodes"] + 2, sub={"batch_size": 2}, meta={"batch_size": 2})
    resumed = Learner(cfg, run_dir, resume=True, progress=False, tensorboard=False)
    assert {r: len(x) for r, x in resumed.replays().items()} == held
    resumed.log.close()
    more = subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", "train", "--algo", "hdrqn-v2", "--episodes",
                           str(progress["episodes"] + 2), "--out", str(run_dir), "--resume", *common],
                          capture_output=True, text=True, timeout=300)
    assert more.returncode == 0, more.stderr
    assert (f"at episode {progress['episodes']} ({progress['env_steps']} env steps); replay restored "
            f"(sub {held['sub']} episodes, meta {held['meta']} episodes)") in more.stderr
    final = load_checkpoint(ckpt)["progress"]
    assert final["episodes"] == progress["episodes"] + 2
    assert len(snapshots(run_dir)) == 1
