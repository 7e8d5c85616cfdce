"""Where one sub- and one meta-controller update spends its time (hDRQNv2, thesis sizes).

For each controller: the median wall time of ``Controller.update()``; of replay sampling
alone (``sample_transitions``: numpy windows, stacking, copies into tensors); of the online
forward (with autograd) and the target forward (``no_grad``) alone on a sampled batch; and
a ``torch.profiler`` run of whole updates, its operators' self CPU time sorted into
backward (under autograd's engine), optimizer (Adam), gradient clipping, soft target update
and the rest (both forwards, loss, target maths, and sampling's copies into tensors).
"python and other" is the update's wall time minus everything the profiler saw (the
profiler's own cost makes its categories a little larger than the unprofiled update), one
thread. Then the floor that the matrix products set: every matrix product and convolution
one update calls (forward, target and backward: ``mm``, ``addmm``, ``bmm``, ``convolution``
and its backward, captured with their exact arguments), each timed again alone, summed
(``matmul_floor_ms``), with the update's FLOPs (``torch.utils.flop_counter``) and the
rate a large 1024^3 GEMM reaches (``large_gemm_gflops``): an update made only of these
calls at these shapes can be no faster than the floor. Prints one JSON object.

    python benchmarks/profile_updates.py [--updates 40]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
from torch.profiler import ProfilerActivity, profile
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode

from bench_training import _config, _prefill  # benchmarks/ is sys.path[0] when run as a script
from hdrqn_ros.training.learner import build_agent

MATMULS = {torch.ops.aten.mm, torch.ops.aten.addmm, torch.ops.aten.bmm, torch.ops.aten.convolution,
           torch.ops.aten.convolution_backward}
"""Operator packets (every overload, ``out=`` ones included) the matmul floor times."""


class _CaptureMatmuls(TorchDispatchMode):
    """Records every matrix product and convolution dispatched, with copies of its arguments."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func.overloadpacket in MATMULS:
            copy = lambda a: a.detach().clone() if isinstance(a, torch.Tensor) else a
            self.calls.append((func, [copy(a) for a in args], {k: copy(v) for k, v in kwargs.items()}))
        return func(*args, **kwargs)


def _large_gemm_gflops(size: int = 1024, reps: int = 20) -> float:
    a, b = torch.randn(size, size), torch.randn(size, size)
    ms = _median_ms(lambda: a @ b, reps)
    return round(2 * size ** 3 / (ms * 1e-3) / 1e9, 1)


def matmul_floor(ctrl, reps: int) -> dict:
    """The update's FLOPs, and the summed time of its matrix products and convolutions,
    each run alone (median of ``reps``) at the update's exact shapes."""
    with FlopCounterMode(display=False) as flops:
        ctrl.update()
    capture = _CaptureMatmuls()
    with capture:
        ctrl.update()
    floor = 0.0
    with torch.no_grad():
        for func, args, kwargs in capture.calls:
            floor += _median_ms(lambda: func(*args, **kwargs), reps)
    gflop = flops.get_total_flops() / 1e9
    return {"update_gflop": round(gflop, 3), "matmul_calls": len(capture.calls), "matmul_floor_ms": round(floor, 3),
            "matmul_floor_gflops": round(gflop / (floor * 1e-3), 1)}


CATEGORIES = ("backward", "optimizer", "grad_clip", "soft_update", "forward_loss_and_target_maths")


def _median_ms(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return round(statistics.median(times), 3)


def _category(event) -> str:
    names = [event.name]
    parent = event.cpu_parent
    while parent is not None:
        names.append(parent.name)
        parent = parent.cpu_parent
    joined = " ".join(names)
    if "autograd::engine::evaluate_function" in joined:
        return "backward"
    if "Optimizer.step" in joined or "_fused_adam" in joined:
        return "optimizer"
    if "_foreach_lerp" in joined:
        return "soft_update"
    if "_foreach_norm" in joined or "clip_grad" in joined:
        return "grad_clip"
    return "forward_loss_and_target_maths"


def profile_controller(ctrl, updates: int) -> dict:
    sample = lambda: ctrl.replay.sample_transitions(ctrl.cfg.batch_size, ctrl.seq_len, ctrl.build_input, ctrl.device)
    for _ in range(5):
        ctrl.update()  # warm-up: allocator, Adam state
    batch = sample()

    def online():
        ctrl.online(batch.obs)[0].sum()

    def target():
        with torch.no_grad():
            ctrl.target(batch.obs)

    out = {"update_ms": _median_ms(ctrl.update, updates), "sample_ms": _median_ms(sample, updates),
           "online_forward_ms": _median_ms(online, updates), "target_forward_ms": _median_ms(target, updates)}
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(updates):
            ctrl.update()
    totals = dict.fromkeys(CATEGORIES, 0.0)
    for event in prof.events():
        totals[_category(event)] += event.self_cpu_time_total / 1e3 / updates  # us -> ms per update
    out.update({f"{name}_ms": round(value, 3) for name, value in totals.items()})
    out["python_and_other_ms"] = round(out["update_ms"] - sum(totals.values()), 3)
    out["top_ops_ms"] = {a.key: round(a.self_cpu_time_total / 1e3 / updates, 3) for a in sorted(
        prof.key_averages(), key=lambda a: -a.self_cpu_time_total)[:8]}
    out.update(matmul_floor(ctrl, updates))
    out["achieved_gflops"] = round(out["update_gflop"] / (out["update_ms"] * 1e-3), 1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--updates", type=int, default=40)
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = _config(16)
    agent = build_agent(cfg)
    _prefill(agent, cfg)
    result = {"threads": torch.get_num_threads(), "updates": args.updates, "large_gemm_gflops": _large_gemm_gflops(),
              "sub": profile_controller(agent.sub, args.updates), "meta": profile_controller(agent.meta, args.updates)}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
