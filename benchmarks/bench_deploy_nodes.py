"""Per-decision latency of a controller node's acting code, ONNX (``policy:=``) against torch
(``checkpoint:=``): one fresh process per path and role builds its acting network with the
nodes' own :func:`hdrqn_ros.nodes.acting.make_acting_network` (a stub in place of the
rclpy node) and times the node's decision call on
:class:`~hdrqn_ros.agents.policy.HierarchicalPolicy` (N = 1): the sub-controller's
``act`` on a stacked (1, 44, 44, 6) input, the hDRQNv2 meta-controller's ``end_options`` +
``choose_subgoals``. Prints one JSON object: median and p90 ms per decision, whether torch
was imported, and VmRSS (rclpy imported, no DDS participant; the node processes' resident memory
with it is measured by ``test/test_deploy_nodes.py``).

    python benchmarks/bench_deploy_nodes.py [--decisions 2000]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = "hdrqn/GridWorld-2Goals-v0"

PROBE = r"""
import json, sys, time, types, logging
import numpy as np
from hdrqn_ros.agents.policy import HierarchicalPolicy
from hdrqn_ros.agents.specs import ALGO_SPECS, stack_subgoal
from hdrqn_ros.nodes.acting import make_acting_network

role, acting, decisions = sys.argv[1], sys.argv[2], int(sys.argv[3])
node = types.SimpleNamespace(get_logger=lambda: logging.getLogger("bench"), resolve_topic_name=lambda topic: topic,
                             create_subscription=lambda *a, **k: None)
params = {"algo": "hdrqn-v2", "env": sys.argv[4], "view": "5", "seed": 0, "epsilon": 0.0, "meta_state": "c",
          "checkpoint": "", "policy": "", "max_message_bytes": 1 << 26, **dict([acting.split(":=", 1)])}
net = make_acting_network(node, role, params, 0.0)
one = np.ones(1, bool)
policy = HierarchicalPolicy(1, net if role == "sub" else None, net if role == "meta" else None, "state")
rng = np.random.default_rng(0)
obs = rng.integers(0, 256, (44, 44, 3), dtype=np.uint8)
goal = rng.integers(0, 256, (44, 44, 3), dtype=np.uint8)
sub_end = rng.standard_normal((1, 256)).astype(np.float32)
times = []
for i in range(decisions + 200):
    start = time.perf_counter_ns()
    if role == "sub":
        policy.act(stack_subgoal(obs, goal)[None], 0.0, rng)
    else:
        policy.end_options(one, np.array([-1]), sub_end)
        policy.choose_subgoals(one, None, 0.0, rng)
    times.append(time.perf_counter_ns() - start)
    if i % 50 == 0:
        policy.start_episodes(one)
times = np.array(times[200:]) / 1e6
rss = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmRSS:"))
print(json.dumps({"median_ms": round(float(np.median(times)), 3), "p90_ms": round(float(np.percentile(times, 90)), 3),
                  "torch_imported": "torch" in sys.modules, "rss_mib": round(rss / 1024, 1)}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--decisions", type=int, default=2000)
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "test"))
    from test_onnx_export import _make_checkpoint  # an agent with every weight moved off its start

    from hdrqn_ros.training.export import export_policy

    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = Path(tmp) / "run" / "checkpoints" / "last.pt"
        _make_checkpoint(checkpoint, "hdrqn-v2", ENV, seed=31)
        policy_dir = export_policy(checkpoint, Path(tmp) / "policy")
        out = {}
        for path, acting in (("onnx", f"policy:={policy_dir}"), ("torch", f"checkpoint:={checkpoint}")):
            for role in ("sub", "meta"):
                proc = subprocess.run([sys.executable, "-c", PROBE, role, acting, str(args.decisions), ENV],
                                      cwd=ROOT, capture_output=True, text=True, timeout=600, check=True)
                out[f"{path}/{role}"] = json.loads(proc.stdout.splitlines()[-1])
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
