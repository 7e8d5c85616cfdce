"""Deployment cost of a controller: per-decision latency at batch 1 and resident memory,
torch (what a controller node does with ``checkpoint:=``, ``TorchActingNetwork.act``) against the exported
ONNX policy (``hdrqn_ros.deploy.OnnxPolicy``, no torch).

Prints one JSON object. Goals: ONNX <= 0.2 ms per decision and <= 100 MiB resident memory
(VmRSS) for a process that loads the policy and acts (issue 20); torch <= 0.5 ms per
decision (issue 19).

* latency: ``--decisions`` timed decisions per role and path after ``--warmup``, each
  timed alone (``perf_counter_ns``): input to array/tensor, ``act`` with the carried LSTM
  state, Q-values to numpy, argmax; torch under ``inference_mode`` with 1 thread (as the
  nodes set it), ONNX Runtime with 1 intra-op thread, sequential. The paths alternate in
  rounds A B B A so a change in the machine's load hits both alike; medians over all.
* memory: a fresh subprocess per path loads the controllers of the policy (ONNX) or the
  checkpoint (torch networks, as ``ActingNetwork`` builds them), acts 200 times per role,
  then reads its VmRSS and VmHWM from /proc/self/status.

    python benchmarks/bench_deploy.py [--algo hdrqn-v2] [--checkpoint RUN/checkpoints/last.pt]
                                      [--decisions 2000] [--warmup 200]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import hdrqn_ros
from hdrqn_ros.config import build_config
from hdrqn_ros.deploy import OnnxPolicy
from hdrqn_ros.training.checkpoint import save_checkpoint
from hdrqn_ros.training.export import export_policy, load_acting_networks
from hdrqn_ros.training.learner import build_agent

LATENCY_GOAL_MS = 0.2
TORCH_LATENCY_GOAL_MS = 0.5
"""The torch path's goal (issue 19): one sub-controller decision at batch 1 <= 0.5 ms."""
RSS_GOAL_MIB = 100.0
ROOT = Path(__file__).resolve().parents[1]

MEMORY_PROBE = r"""
import json, sys
import numpy as np
kind, source = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(0)
if kind == "onnx":
    from hdrqn_ros.deploy import OnnxPolicy
    policy = OnnxPolicy.load(source)
    for role in policy.roles:
        spec, state = policy.input_spec(role), policy.initial_state(role)
        x = rng.integers(0, 256, (1, *spec.shape[1:]), dtype=np.uint8) if spec.dtype == "uint8" else \
            rng.standard_normal((1, *spec.shape[1:])).astype(np.float32)
        for _ in range(200):
            q, state = policy.act(role, x, state)
            int(q.argmax())
elif kind == "torch":
    import torch
    torch.set_num_threads(1)
    from hdrqn_ros.training.export import load_acting_networks
    _, _, nets, _, _ = load_acting_networks(source)
    for role, net in nets.items():
        shape = net.trunk.input_shape
        x = rng.integers(0, 256, shape, dtype=np.uint8) if len(shape) == 3 else \
            rng.standard_normal(shape).astype(np.float32)
        state = net.initial_state(1)
        for _ in range(200):
            with torch.inference_mode():
                q, state = net.act(torch.tensor(x[None]), state)
            int(q.numpy().argmax())
status = dict(line.split(":", 1) for line in open("/proc/self/status") if ":" in line)
print(json.dumps({"vmrss_mib": int(status["VmRSS"].split()[0]) / 1024, "vmhwm_mib": int(status["VmHWM"].split()[0]) / 1024,
                  "torch_imported": "torch" in sys.modules}))
"""


def memory_of(kind: str, source: Path) -> dict:
    proc = subprocess.run([sys.executable, "-c", MEMORY_PROBE, kind, str(source)], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    if proc.returncode:
        raise RuntimeError(f"{kind} memory probe failed: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.splitlines()[-1])


def _input(shape: tuple, rng: np.random.Generator) -> np.ndarray:
    """One decision's input, no batch axis: a uint8 image or a float32 LSTM state."""
    if len(shape) == 3:
        return rng.integers(0, 256, shape, dtype=np.uint8)
    return rng.standard_normal(shape).astype(np.float32)


def torch_decider(net):
    state = [net.initial_state(1)]

    def decide(x: np.ndarray) -> int:
        with torch.inference_mode():  # as TorchActingNetwork.act
            q, state[0] = net.act(torch.tensor(x[None]), state[0])
        return int(q.numpy().argmax())
    return decide


def onnx_decider(policy: OnnxPolicy, role: str):
    state = [policy.initial_state(role)]

    def decide(x: np.ndarray) -> int:
        q, state[0] = policy.act(role, x[None], state[0])
        return int(q.argmax())
    return decide


def time_decisions(decide, inputs: list[np.ndarray], count: int) -> list[int]:
    out = []
    clock = time.perf_counter_ns
    for k in range(count):
        x = inputs[k % len(inputs)]
        t0 = clock()
        decide(x)
        out.append(clock() - t0)
    return out


def latency(nets: dict, policy: OnnxPolicy, decisions: int, warmup: int) -> dict:
    rng = np.random.default_rng(0)
    result = {}
    for role, net in nets.items():
        inputs = [_input(net.trunk.input_shape, rng) for _ in range(64)]
        paths = {"torch": torch_decider(net), "onnx": onnx_decider(policy, role)}
        for decide in paths.values():
            time_decisions(decide, inputs, warmup)
        samples = {name: [] for name in paths}
        quarter = -(-decisions // 4)
        for name in ("torch", "onnx", "onnx", "torch"):  # rounds A B B A
            samples[name] += time_decisions(paths[name], inputs, 2 * quarter)
        for name, ns in samples.items():
            ms = np.asarray(ns) / 1e6
            result[f"{role}_{name}_ms"] = {"median": round(float(np.median(ms)), 4),
                                           "p90": round(float(np.percentile(ms, 90)), 4), "n": len(ms)}
        result[f"{role}_speedup"] = round(result[f"{role}_torch_ms"]["median"] / result[f"{role}_onnx_ms"]["median"], 2)
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--algo", default="hdrqn-v2")
    ap.add_argument("--checkpoint", help="a run's checkpoint (default: a fresh agent's, saved to a temp dir)")
    ap.add_argument("--decisions", type=int, default=2000)
    ap.add_argument("--warmup", type=int, default=200)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="bench_deploy_") as tmp:
        ckpt = Path(args.checkpoint) if args.checkpoint else Path(tmp) / "run" / "checkpoints" / "last.pt"
        if not args.checkpoint:
            torch.manual_seed(0)
            cfg = build_config([], algo=args.algo)
            save_checkpoint(ckpt, config=cfg.model_dump(), agent_state=build_agent(cfg).state_dict(), progress={})
        policy_dir = export_policy(ckpt, Path(tmp) / "policy")
        cfg, _, nets, _, _ = load_acting_networks(ckpt)
        policy = OnnxPolicy.load(policy_dir)
        lat = latency(nets, policy, args.decisions, args.warmup)
        memory = {"onnx": memory_of("onnx", policy_dir), "torch": memory_of("torch", ckpt)}
    worst_onnx = max(v["median"] for k, v in lat.items() if k.endswith("_onnx_ms"))
    worst_torch = max(v["median"] for k, v in lat.items() if k.endswith("_torch_ms"))
    onnx_rss = memory["onnx"]["vmrss_mib"]
    report = {
        "algo": cfg.algo,
        "env": cfg.env,
        "roles": list(nets),
        "latency": lat,
        "memory_mib": {kind: {k: round(v, 1) if isinstance(v, float) else v for k, v in m.items()}
                       for kind, m in memory.items()},
        "rss_ratio_torch_over_onnx": round(memory["torch"]["vmrss_mib"] / onnx_rss, 2),
        "goals": {
            "latency_goal_ms": LATENCY_GOAL_MS,
            "onnx_worst_role_median_ms": worst_onnx,
            "latency_ratio_to_goal": round(worst_onnx / LATENCY_GOAL_MS, 2),
            "latency_met": worst_onnx <= LATENCY_GOAL_MS,
            "torch_latency_goal_ms": TORCH_LATENCY_GOAL_MS,
            "torch_worst_role_median_ms": worst_torch,
            "torch_latency_met": worst_torch <= TORCH_LATENCY_GOAL_MS,
            "rss_goal_mib": RSS_GOAL_MIB,
            "onnx_rss_mib": round(onnx_rss, 1),
            "rss_ratio_to_goal": round(onnx_rss / RSS_GOAL_MIB, 2),
            "rss_met": onnx_rss <= RSS_GOAL_MIB,
        },
        "versions": {"hdrqn_ros": hdrqn_ros.__version__, "torch": torch.__version__,
                     "onnxruntime": __import__("onnxruntime").__version__, "python": platform.python_version()},
        "machine": {"cpus": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2),
                    "processor": platform.processor() or platform.machine()},
    }
    print(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
