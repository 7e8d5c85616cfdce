"""``hdrqn experiment`` and ``hdrqn plot`` of an experiment directory, with real (tiny) runs."""
from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest

from hdrqn_ros.experiments import EXPERIMENTS, config_dir

HDRQN = [sys.executable, "-m", "hdrqn_ros.cli"]


def hdrqn(*args: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([*HDRQN, *args], capture_output=True, text=True, timeout=timeout)


def test_every_experiment_expands_to_existing_configs_and_thesis_settings():
    for exp in EXPERIMENTS.values():
        assert (config_dir() / exp.config).exists(), exp.config
        runs = exp.runs([0, 1, 2])
        assert len({r.name for r in runs}) == len(runs), f"{exp.name}: run names collide"
        assert {r.figure for r in runs} <= set(exp.figures)
    exp1 = {r.label: r.sets for r in EXPERIMENTS["exp1"].runs([0])}
    assert exp1["hdrqn-v2 nS=12"] == ("sub.seq_len=12", "meta.seq_len=1")
    assert exp1["hdrqn-v1 nM=2"] == ("sub.seq_len=8", "meta.seq_len=2")
    assert [r.view for r in EXPERIMENTS["exp2"].runs([0])] == ["3", "5", "full"] * 2
    assert [r.algo for r in EXPERIMENTS["exp3-fourrooms-3goals"].runs([0])] == \
        ["hdrqn-v2", "hdrqn-v1", "hdqn", "drqn", "dqn"]


def test_experiment_runs_resumes_and_reports(tmp_path):
    out = tmp_path / "exp"
    common = ["exp3-gridworld-2goals", "--algos", "dqn", "--seeds", "0", "1", "--jobs", "2",
              "--out", str(out), "--no-progress", "--set", "eval_episodes=2", "--set", "num_envs=2"]
    first = hdrqn("experiment", *common, "--episodes", "3")
    assert first.returncode == 0, first.stderr
    assert "2/2 runs finished" in first.stdout
    manifest = json.loads((out / "experiment.json").read_text())
    assert [r["dir"] for r in manifest["runs"]] == ["dqn-s0", "dqn-s1"]
    assert manifest["episodes"] == 3 and manifest["runs"][0]["command"][:2] == ["hdrqn", "train"]
    assert manifest["runs"][0]["command"][-6:] == ["--set", "eval_episodes=2", "--set", "num_envs=2", "--episodes", "3"]
    # the same command again: nothing to do; a bigger budget: every run resumes from its checkpoint
    again = hdrqn("experiment", *common, "--episodes", "3")
    assert again.returncode == 0 and "2/2 runs finished" in again.stdout
    assert (out / "dqn-s0.log").read_text().count("training dqn") == 1
    more = hdrqn("experiment", *common, "--episodes", "5")
    assert more.returncode == 0, more.stderr
    for run in ("dqn-s0", "dqn-s1"):
        assert json.loads((out / run / "summary.json").read_text())["episodes"] == 5
        with open(out / run / "train.csv") as f:
            assert [int(r["episode"]) for r in csv.DictReader(f)] == [1, 2, 3, 4, 5]
    plot = hdrqn("plot", str(out))
    assert plot.returncode == 0, plot.stderr
    table = (out / "table.md").read_text()
    assert "| dqn | 2 (2) |" in table
    assert (out / "exp3-gridworld-2goals_fig4_10.png").stat().st_size > 10_000


@pytest.mark.parametrize("args, message", [
    (["experiment", "exp9"], "invalid choice"),
    (["experiment", "exp1", "--jobs", "0"], "--jobs must be >= 1"),
    (["experiment", "exp1", "--episodes", "0"], "--episodes must be >= 1"),
    (["experiment", "exp1", "--set", "episodes"], "--set expects KEY=VALUE"),
    (["experiment", "exp4-montezuma", "--seeds", "x"], "invalid int value"),
    (["plot", "/nonexistent-run"], "has no train.csv"),
])
def test_bad_arguments_exit_2_with_a_message(args, message):
    run = hdrqn(*args, timeout=60)
    assert run.returncode == 2 and message in run.stderr and "Traceback" not in run.stderr
