"""The developer scripts: `scripts/stress` tallies real pytest runs (passes, failures with their
output, retries), `scripts/goal_sightings` follows the second goal after the first; and the
`processes` marker by which `scripts/test` keeps node-starting tests one at a time."""
import json
import os
import subprocess
import sys
from importlib.machinery import SourceFileLoader
from importlib.util import module_from_spec, spec_from_loader
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from hdrqn_ros.cli import main
from hdrqn_ros.config import build_config
from hdrqn_ros.envs.domain import NO_SUBGOAL, StepBatch
from hdrqn_ros.training.checkpoint import save_checkpoint
from hdrqn_ros.training.learner import build_agent

ROOT = Path(__file__).resolve().parents[1]
_loader = SourceFileLoader("goal_sightings", str(ROOT / "scripts" / "goal_sightings"))
sightings = module_from_spec(spec_from_loader("goal_sightings", _loader))
_loader.exec_module(sightings)

SAMPLE_TESTS = '''
import os, pytest
from pathlib import Path

def test_passes():
    assert True

def test_fails():
    assert 1 == 2, "the sample failure's own message"

@pytest.mark.flaky(reruns=1)
def test_fails_first_try_only(tmp_path_factory):
    marker = Path(os.environ["SAMPLE_MARKER"])
    if not marker.exists():
        marker.write_text("tried")
        assert False, "first try"
'''


def _stress(tmp_path, *args):
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "stress"), *args], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "SAMPLE_MARKER": str(tmp_path / "marker")})


def test_stress_tallies_passes_failures_and_retries(tmp_path):
    sample = tmp_path / "test_sample.py"
    sample.write_text(SAMPLE_TESTS)
    out = tmp_path / "out"
    first = _stress(tmp_path, "--runs", "1", "--hog-elsewhere", "--out", str(out), str(sample))
    assert first.returncode == 1, first.stdout + first.stderr  # a test failed
    assert "the sample failure's own message" in first.stdout  # its own output, under the table
    assert "with a CPU hog kept elsewhere" in first.stdout
    assert "retried in run 1: " in first.stdout and "first try" in first.stdout  # the retried test's failed try
    second = _stress(tmp_path, "--runs", "2", "--no-hog", "--out", str(out), str(sample))  # continues the tally
    assert "continuing" in second.stdout and second.returncode == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 2 and summary["hog"] is False
    by_name = {test_id.split("::")[-1]: t for test_id, t in summary["tests"].items()}
    assert set(by_name) == {"test_passes", "test_fails", "test_fails_first_try_only"}
    assert (by_name["test_passes"]["passed"], by_name["test_passes"]["failed"]) == (2, 0)
    assert (by_name["test_fails"]["passed"], by_name["test_fails"]["failed"]) == (0, 2)
    retried = by_name["test_fails_first_try_only"]
    assert (retried["passed"], retried["failed"], retried["rerun"]) == (2, 0, 1)  # the retry is counted, run 1 only
    assert len(by_name["test_passes"]["seconds"]) == 2


def test_stress_shows_a_retried_tests_failed_try_when_all_pass(tmp_path):
    sample = tmp_path / "test_sample.py"
    sample.write_text(SAMPLE_TESTS)
    run = _stress(tmp_path, "--runs", "1", "--no-hog", "--out", str(tmp_path / "out"), f"{sample}::test_fails_first_try_only")
    assert run.returncode == 0, run.stdout + run.stderr
    failed_try = run.stdout.split("the failed tries ---", 1)[1]
    assert "AssertionError: first try" in failed_try and "1 passed" not in failed_try


def test_stress_refuses_bad_arguments(tmp_path):
    bad = _stress(tmp_path, "--runs", "0", "--out", str(tmp_path))
    assert bad.returncode == 2 and "--runs must be >= 1" in bad.stderr
    both = _stress(tmp_path, "--no-hog", "--hog-elsewhere")
    assert both.returncode == 2 and "not allowed with" in both.stderr


def test_a_module_that_starts_nodes_must_be_listed_to_run_one_at_a_time(tmp_path):
    (tmp_path / "test").mkdir()
    for name in ("setup.cfg", "test/conftest.py"):
        (tmp_path / name).write_text((ROOT / name).read_text())
    (tmp_path / "test" / "test_graph.py").write_text("def test_listed(domain):\n    pass\n")

    def collect():
        return subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", "-m",
                               "processes", "test"], cwd=tmp_path, capture_output=True, text=True, timeout=300)

    listed = collect()
    assert listed.returncode == 0 and "test_graph.py::test_listed" in listed.stdout, listed.stdout + listed.stderr
    (tmp_path / "test" / "test_new_nodes.py").write_text("def test_unlisted(domain):\n    pass\n")
    unlisted = collect()
    assert unlisted.returncode == 4, unlisted.stdout + unlisted.stderr  # a usage error: nothing runs
    assert "add test_new_nodes to PROCESS_MODULES" in unlisted.stdout + unlisted.stderr


def _step(green_in_view: bool, at: int = NO_SUBGOAL, done: bool = False) -> SimpleNamespace:
    """A play() record of one environment: the view holds a green pixel or not; ``at`` a goal
    collected at this step."""
    obs = np.full((1, 44, 44, 3), 255, np.uint8)
    if green_in_view:
        obs[0, 20, 20] = sightings.GREEN
    collected = at != NO_SUBGOAL
    env = StepBatch(obs=obs, classical=np.zeros(1, np.float32), extrinsic=np.zeros(1, np.float32),
                    terminated=np.array([done and collected]), truncated=np.array([done and not collected]),
                    agent_pos=np.zeros((1, 2), np.int32), at_subgoal=np.array([at], np.int32),
                    collected=np.array([collected]), hit_obstacle=np.zeros(1, bool), life_lost=np.zeros(1, bool),
                    success=np.array([done and at == 1]))
    return SimpleNamespace(env=env)


def test_sightings_follow_the_second_goal():
    sink = sightings.Sightings(quota=3)
    episodes = [
        [_step(False), _step(True, at=0), _step(True), _step(False, at=1, done=True)],  # seen at once, taken
        [_step(False, at=0), _step(False), _step(True), _step(False, done=True)],  # seen 2 steps later, not taken
        [_step(True), _step(False, done=True)],  # blue never collected (green in view does not count)
        [_step(False, at=0), _step(False, done=True)],  # beyond the quota: not counted
    ]
    for episode in episodes:
        for record in episode:
            sink.write(record)
    got = sink.summary()
    assert got["episodes"] == 3
    assert got["blue_collected"] == round(2 / 3, 3)
    assert got["then_green_in_view"] == 1.0 and got["green_never_in_view"] == 0.0
    assert got["green_in_view_not_collected"] == 0.5
    assert got["ordered_success"] == round(1 / 3, 3)
    assert got["steps_blue_to_green_in_view_median"] == 1.0  # 0 and 2 steps


def test_goal_sightings_agree_with_eval(tmp_path, capsys):
    """On the same checkpoint, episodes and seed, the script's ordered success is `hdrqn eval`'s."""
    torch.manual_seed(3)
    cfg = build_config([], algo="drqn", seed=3)
    ckpt = tmp_path / "last.pt"
    save_checkpoint(ckpt, config=cfg.model_dump(), agent_state=build_agent(cfg).state_dict(),
                    progress={"episodes": 0, "env_steps": 0, "meta_begin": None})
    args = ["--episodes", "256", "--epsilon", "1.0", "--seed", "5"]  # one episode per environment
    script = subprocess.run([sys.executable, str(ROOT / "scripts" / "goal_sightings"), str(ckpt), *args],
                            capture_output=True, text=True, timeout=600)
    assert script.returncode == 0, script.stderr
    got = json.loads(script.stdout)
    assert main(["eval", "--checkpoint", str(ckpt), *args]) == 0
    evaluated = json.loads(capsys.readouterr().out)
    assert got["episodes"] == evaluated["episodes"] == 256
    assert got["ordered_success"] == pytest.approx(evaluated["success"], abs=1e-3)
    assert 0 < got["blue_collected"] < 1 and got["ordered_success"] > 0  # a random walk sometimes does both


def test_goal_sightings_refuse_a_non_grid_checkpoint(tmp_path):
    cfg = build_config([], algo="dqn", env="hdrqn/MontezumaRevenge-v0")
    ckpt = tmp_path / "last.pt"
    save_checkpoint(ckpt, config=cfg.model_dump(), agent_state=build_agent(cfg).state_dict(),
                    progress={"episodes": 0, "env_steps": 0, "meta_begin": None})
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / "goal_sightings"), str(ckpt)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 2 and "the sightings are for the gridworld domains" in run.stderr
    bad = subprocess.run([sys.executable, str(ROOT / "scripts" / "goal_sightings"), str(ckpt), "--epsilon", "1.5"],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "--epsilon must be in [0, 1], got 1.5" in bad.stderr
