"""The controller nodes acting from an exported ONNX policy (``policy:=DIR``, issue 20 part B):
real node processes (environment, critic, meta_controller, sub_controller; no learner,
epsilon 0) choose exactly the actions the same graph chooses from the torch checkpoint the
policy was exported from, the controller processes never load torch, and a policy that
does not fit the node is refused with exit code 2."""
from __future__ import annotations

import json
import statistics
from pathlib import Path

import pytest

from hdrqn_ros.graph import NODE_MODULES
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.supervisor import ProcessSpec, Supervisor, python_command
from hdrqn_ros.training.export import export_policy

from test_graph import ENV, read_jsonl, wait_for
from test_onnx_export import _make_checkpoint

ALGO = "hdrqn-v2"
EPISODES = 6
"""Episodes per run: a few hundred lock-step steps (50 at most each)."""
CONTROLLERS = ("meta_controller", "sub_controller")
TIMING_FIELDS = ("wall_time", "action_time")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """(checkpoint, policy dir) of an hDRQNv2 agent on the 2-goal gridworld, weights moved off their start."""
    base = tmp_path_factory.mktemp("deploy")
    checkpoint = base / "run" / "checkpoints" / "last.pt"
    _make_checkpoint(checkpoint, ALGO, ENV, seed=31)
    return checkpoint, export_policy(checkpoint, base / "policy")


def _spec(node: str, *params: str) -> ProcessSpec:
    argv = python_command(NODE_MODULES[node]) + ["--ros-args", "-p", f"algo:={ALGO}", "-p", f"env:={ENV}",
                                                 "-p", "seed:=3"]
    for param in params:
        argv += ["-p", param]
    return ProcessSpec(node, argv, stack_dump_signal=STACK_DUMP_SIGNAL)


def _proc_status(pid: int) -> tuple[str, int]:
    """(/proc/PID/maps text, VmRSS in KiB) of a live process."""
    maps = Path(f"/proc/{pid}/maps").read_text()
    rss = next(int(line.split()[1]) for line in Path(f"/proc/{pid}/status").read_text().splitlines()
               if line.startswith("VmRSS:"))
    return maps, rss


def run_graph(tmp_path: Path, acting: str, epsilon: str) -> dict:
    """The graph without a learner, both controllers given ``acting`` (``policy:=DIR`` or
    ``checkpoint:=PATH``) and a fixed ``epsilon``; until the environment has run its episodes. Returns the
    environment's step rows, each controller's maps and VmRSS, and the logs."""
    step_log = tmp_path / "env_steps.jsonl"
    specs = [_spec("environment", f"max_episodes:={EPISODES}", f"step_log:={step_log}", "wait_for_learner:=false"),
             _spec("critic")] + [_spec(node, acting, f"epsilon:={epsilon}") for node in CONTROLLERS]
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    procs = {}
    try:
        wait_for(lambda: sup.returncodes["environment"] is not None, 240, f"{EPISODES} episodes", sup)
        for node in CONTROLLERS:  # still running: they wait for the next step
            procs[node] = _proc_status(sup.pids[node])
    finally:
        codes = sup.stop()
    assert codes["environment"] == 0, codes
    assert all(codes[node] == 0 for node in CONTROLLERS), codes
    logs = {spec.name: (tmp_path / "logs" / f"{spec.name}.log").read_text() for spec in specs}
    return {"rows": read_jsonl(step_log), "procs": procs, "logs": logs}


def _decision_ms(rows: list[dict]) -> float:
    """Median ms from the environment publishing a step to the action for it arriving (the
    controllers' decisions, the critic, and the DDS hops between them)."""
    gaps = [(row["action_time"] - prev["wall_time"]) * 1e3 for prev, row in zip(rows, rows[1:])
            if row["prev_key"] == prev["key"] and row["action_time"] > 0]
    return statistics.median(gaps)


@pytest.mark.parametrize("epsilon", ["0.0", "0.25"], ids=["greedy", "exploring"])
def test_policy_nodes_act_as_the_checkpoint_nodes_without_torch(domain, tmp_path, exported, epsilon):
    """Greedy, and exploring (the same seeds: the same random draws on both paths, and options
    that end at subgoals, so the meta-controller reads the sub-controller's ONNX state)."""
    checkpoint, policy_dir = exported
    onnx = run_graph(tmp_path / "onnx", f"policy:={policy_dir}", epsilon)
    torch_run = run_graph(tmp_path / "torch", f"checkpoint:={checkpoint}", epsilon)

    # the same greedy decisions: the same actions on the same observations, step for step
    onnx_rows, torch_rows = onnx["rows"], torch_run["rows"]
    assert len(onnx_rows) >= 100 and max(r["episode"] for r in onnx_rows) == EPISODES - 1
    strip = [{k: v for k, v in row.items() if k not in TIMING_FIELDS} for row in onnx_rows]
    assert strip == [{k: v for k, v in row.items() if k not in TIMING_FIELDS} for row in torch_rows]
    assert len({r["action"] for r in onnx_rows}) > 1
    if epsilon != "0.0":
        assert sum(r["decision_point"] for r in onnx_rows) >= 3, "no option ended at a subgoal"

    report = {}
    for node in CONTROLLERS:
        maps, rss = onnx["procs"][node]
        assert "libtorch_cpu.so" not in maps, f"{node} loaded torch on the policy path"
        assert "onnxruntime" in maps, f"{node}: no onnxruntime in its maps"
        torch_maps, torch_rss = torch_run["procs"][node]
        assert "libtorch_cpu.so" in torch_maps  # the check sees torch where it is loaded
        assert rss < torch_rss, (node, rss, torch_rss)
        log = onnx["logs"][node]
        assert "torch imported: False" in log and "an exported policy is frozen: not subscribing" in log
        assert f"loaded {node.split('_')[0]} weights from {checkpoint}" in torch_run["logs"][node]
        report[node] = {"onnx_rss_mib": round(rss / 1024, 1), "torch_rss_mib": round(torch_rss / 1024, 1)}
    report["step_to_action_ms"] = {"onnx": round(_decision_ms(onnx_rows), 2),
                                   "torch": round(_decision_ms(torch_rows), 2)}
    report["steps"] = len(onnx_rows)
    print(f"\n[deploy nodes epsilon {epsilon}] {json.dumps(report)}")


BAD_CASES = {
    "both": ("sub_controller", ["policy:={policy}", "checkpoint:={checkpoint}"],
             "give either policy ({policy}) or checkpoint ({checkpoint}), not both"),
    "algo": ("sub_controller", ["policy:={policy}", "algo:=hdrqn-v1"],
             "does not fit this node: algo is hdrqn-v2, the node's algo is hdrqn-v1"),
    "meta_state": ("meta_controller", ["policy:={policy}", "meta_state:=h"],
                   "does not fit this node: meta_state is 'c', the node's meta_state is 'h'"),
    "sizes": ("meta_controller", ["policy:={policy}", "env:=hdrqn/FourRooms-3Goals-v0"],
              "num_actions/num_subgoals are 4/2, hdrqn/FourRooms-3Goals-v0 has 4/3"),
    "no_policy_json": ("sub_controller", ["policy:={empty}"], "{empty}/policy.json does not exist"),
}


def test_a_policy_that_does_not_fit_the_node_exits_2_naming_the_problem(domain, tmp_path, exported):
    checkpoint, policy_dir = exported
    empty = tmp_path / "not-a-policy"
    empty.mkdir()
    names = {"policy": policy_dir, "checkpoint": checkpoint, "empty": empty}
    specs = []
    for case, (node, params, _) in BAD_CASES.items():
        spec = _spec(node, *(p.format(**names) for p in params))
        specs.append(ProcessSpec(case, spec.argv, stack_dump_signal=STACK_DUMP_SIGNAL))
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    try:
        wait_for(lambda: all(code is not None for code in sup.returncodes.values()), 120, "every node to exit", sup)
    finally:
        codes = sup.stop()
    for case, (_, _, message) in BAD_CASES.items():
        log = (tmp_path / "logs" / f"{case}.log").read_text()
        assert codes[case] == 2, (case, codes[case], log[-2000:])
        assert "error: " in log and message.format(**names) in log, (case, log[-2000:])
        assert "Traceback" not in log and "libtorch" not in log
