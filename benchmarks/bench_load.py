"""Load: N actor groups -> 1 learner (default 8) on this machine, for a few minutes.

Starts the real training graph (``hdrqn up --groups N``'s processes: per group an
environment, critic, meta- and sub-controller; one learner) as rclpy nodes (Fast DDS) on the
loopback interface in its own domain, lets it train for ``--seconds`` after every group
has stepped, then stops every process and reports:

* throughput: env steps/s (from the environments' step logs), transitions assembled by
  the learner per second (its transition log), both in total and per group, and
  updates/s (the learner's ``status.json``); over the whole measured run and over its
  steady part (from ``--steady-from`` of the run on);
* latency percentiles (ms): environment publishes step ``K`` (``wall_time`` of its step
  log row) -> the learner has assembled the transition into ``K`` (``wall_time`` of its
  transition log row); the action round trip (step ``P`` published -> ``action(P)``
  arrives at the environment: critic, meta- and sub-controller); the wait from that
  action to the next step's publication (credit from the learner + stepping); all
  processes are on this machine, so ``time.time()`` is one clock;
* memory over time: RSS of every node process (``/proc/<pid>/status``), the series
  (downsampled) per node kind, the peak per kind (goal: environment and critic <= 80 MiB,
  ``light_nodes_pass``), and growth over the steady part; the replay is bounded in
  bytes (``--sub-replay-mib``, ``--meta-replay-mib``) and an estimate of when it is full
  is given, so flat memory can be judged fairly;
* alignment: every transition the learner assembled compared with the environment's step
  row of the same group and key (``prev_key, action, extrinsic, classical, terminated,
  truncated, obs, next_obs``): ``misaligned`` must be 0;
* the learner's dropped/rejected counters (``skipped``, ``lost_episodes``, ``rejected``),
  warnings in the node logs, processes that exited, CPU time per node kind and the time
  its threads were runnable but waited for a CPU (``schedstat``: is the machine the limit?).

Prints one JSON object on stdout, progress on stderr.
Usage: ``python benchmarks/bench_load.py [--groups 8] [--seconds 180] [--keep DIR]``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from hdrqn_ros.config import build_config
from hdrqn_ros.graph import graph_processes, write_params
from hdrqn_ros.protocol.wire import group_namespaces
from hdrqn_ros.supervisor import Supervisor

KINDS = ("environment", "critic", "meta_controller", "sub_controller", "learner")
LIGHT_NODE_GOAL_MIB = 80.0
"""Goal for the environment and critic processes (numpy only, no torch): peak VmRSS <= this."""
ALIGN_FIELDS = ("prev_key", "action", "extrinsic", "classical", "terminated", "truncated", "obs", "next_obs")
FRAME_BYTES = 44 * 44 * 3
"""Sub-controller replay, per ``hdrqn_ros/agents/replay.py``: a step holds one frame plus
about 10 B of fields; an episode one more frame; an option its subgoal image + int32."""
STEP_BYTES, EPISODE_BYTES, OPTION_BYTES = FRAME_BYTES + 10, FRAME_BYTES, FRAME_BYTES + 4
LOG_PATTERNS = {"inputs_never_arrived": "never arrived; skipping", "waits_for_learner": "waits for the learner",
                "no_action": "no action for step", "rejected": "rejected a message", "traceback": "Traceback",
                "resynchronising": "resynchronising"}
CLK_TCK = os.sysconf("SC_CLK_TCK")


def log(msg: str) -> None:
    print(f"[bench_load] {msg}", file=sys.stderr, flush=True)


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """utime + stime of ``pid`` (seconds)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK_TCK
    except (OSError, ValueError, IndexError):
        return None


def runqueue_wait_s(pid: int) -> float | None:
    """Seconds the threads of ``pid`` spent runnable but waiting for a CPU (``/proc/<pid>/task/*/schedstat``)."""
    total, found = 0.0, False
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return None
    for task in tasks:
        try:
            total += int((task / "schedstat").read_text().split()[1]) / 1e9
            found = True
        except (OSError, ValueError, IndexError):
            continue
    return total if found else None


def kind_of(name: str) -> str:
    return name.rsplit("/", 1)[-1]


def read_status(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def read_jsonl(path: Path) -> tuple[list[dict], int]:
    """Rows of a JSON-lines file and the number of lines that did not parse (a cut last line)."""
    rows, bad = [], 0
    if not path.exists():
        return rows, bad
    with open(path) as f:
        for line in f:
            try:
                rows.append(json.loads(line))
            except ValueError:
                bad += 1
    return rows, bad


def pct(values, scale: float = 1000.0) -> dict:
    """p50/p90/p99/max/mean of ``values`` (seconds) in ms."""
    a = np.asarray(values, dtype=float) * scale
    if a.size == 0:
        return {"n": 0}
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return {"n": int(a.size), "p50": round(float(p50), 2), "p90": round(float(p90), 2), "p99": round(float(p99), 2),
            "max": round(float(a.max()), 2), "mean": round(float(a.mean()), 2)}


def _level(series: list[tuple[float, float]], at: float, width: int = 1) -> float:
    """Median of the samples nearest to time ``at`` (+- ``width`` samples)."""
    ts = np.array([t for t, _ in series])
    i = int(np.argmin(np.abs(ts - at)))
    vals = [v for _, v in series[max(0, i - width): i + width + 1]]
    return float(np.median(vals))


def growth(series: list[tuple[float, float]], start: float, end: float) -> dict:
    """RSS change between ``start`` and ``end`` (s): MiB, ratio, least-squares slope MiB/min."""
    window = [(t, v) for t, v in series if start <= t <= end]
    if len(window) < 2:
        return {"samples": len(window)}
    a, b = _level(series, start), _level(series, end)
    ts, vs = np.array([t for t, _ in window]), np.array([v for _, v in window])
    slope = float(np.polyfit(ts, vs, 1)[0]) * 60 if len(window) >= 3 else float("nan")
    return {"from_mib": round(a, 1), "to_mib": round(b, 1), "growth_mib": round(b - a, 1),
            "ratio": round(b / a, 3) if a else None, "slope_mib_per_min": round(slope, 2), "samples": len(window)}


def downsample(items: list, points: int) -> list:
    if len(items) <= points:
        return items
    idx = np.unique(np.linspace(0, len(items) - 1, points).round().astype(int))
    return [items[i] for i in idx]


def rate_in(times: np.ndarray, start: float, end: float) -> float:
    n = int(((times >= start) & (times <= end)).sum())
    return round(n / max(end - start, 1e-9), 1)


def status_rate(samples: list[tuple[float, dict]], key, start: float, end: float) -> float | None:
    """Rate of the counter ``key(status)`` between the status samples nearest ``start`` and ``end``."""
    inside = [(t, s) for t, s in samples if start - 1e-6 <= t <= end + 1e-6 and s is not None]
    if len(inside) < 2:
        return None
    (t0, s0), (t1, s1) = inside[0], inside[-1]
    return round((key(s1) - key(s0)) / max(t1 - t0, 1e-9), 2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groups", type=int, default=8)
    ap.add_argument("--seconds", type=float, default=180.0, help="measured run, from when every group has stepped")
    ap.add_argument("--algo", default="hdrqn-v2")
    ap.add_argument("--env", default="hdrqn/GridWorld-2Goals-v0")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--learning-starts", type=int, default=500, help="random env steps before updates")
    ap.add_argument("--sub-replay-mib", type=float, default=16.0, help="bound on the sub-controller replay")
    ap.add_argument("--meta-replay-mib", type=float, default=4.0, help="bound on the meta-controller replay")
    ap.add_argument("--sample-period", type=float, default=2.0, help="seconds between RSS/status samples")
    ap.add_argument("--steady-from", type=float, default=0.4, help="steady part starts at this fraction of the run")
    ap.add_argument("--startup-timeout", type=float, default=300.0, help="seconds to wait for every group to step")
    ap.add_argument("--domain-id", type=int, default=77, help="private ROS_DOMAIN_ID (DDS stays on loopback)")
    ap.add_argument("--series-points", type=int, default=30, help="memory series downsampled to this many points")
    ap.add_argument("--stop-timeout", type=float, default=60.0,
                    help="seconds the nodes get to exit after SIGINT before SIGTERM/SIGKILL (a loaded machine needs "
                         "tens of seconds to tear 33 torch-importing processes down)")
    ap.add_argument("--keep", default=None, help="keep the run (logs, step/transition logs) in this new directory")
    args = ap.parse_args()
    if args.groups < 1 or args.seconds <= 0 or not 0 <= args.steady_from < 1:
        ap.error("--groups >= 1, --seconds > 0 and 0 <= --steady-from < 1 please")

    if args.keep:
        base = Path(args.keep).resolve()
        base.mkdir(parents=True, exist_ok=False)
        tmp = None
    else:
        tmp = tempfile.mkdtemp(prefix="bench_load-")
        base = Path(tmp)
    try:
        out = run(args, base)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(out, indent=2))


def run(args, base: Path) -> dict:
    sub_bytes, meta_bytes = int(args.sub_replay_mib * 2**20), int(args.meta_replay_mib * 2**20)
    cfg = build_config([], algo=args.algo, env=args.env, seed=args.seed, episodes=10**7,
                       learning_starts=args.learning_starts, eval_every=0, checkpoint_every=10**7,
                       sub={"replay_bytes": sub_bytes}, meta={"replay_bytes": meta_bytes})
    run_dir = base / "run"
    run_dir.mkdir()
    cfg_file = run_dir / "graph-config.yaml"
    cfg_file.write_text(json.dumps(cfg.model_dump()))
    transition_log = base / "transitions.jsonl"
    params = write_params(cfg, run_dir, args.groups, cfg_file,
                          extra={"learner": {"transition_log": str(transition_log), "evaluate": False}})
    namespaces = group_namespaces(args.groups)
    step_logs = {ns: base / f"steps-{ns.strip('/') or 'root'}.jsonl" for ns in namespaces}
    specs = []
    for spec in graph_processes(cfg, params, args.groups, respawn=False):
        if kind_of(spec.name) == "environment":  # one step log per group: rows carry no namespace
            ns = next(ns for ns in namespaces if spec.argv[spec.argv.index("-r") + 1] == f"__ns:={ns}")
            spec = dataclasses.replace(spec, argv=spec.argv + ["-p", f"step_log:={step_logs[ns]}"])
        specs.append(spec)
    sup = Supervisor(specs, env={"ROS_DOMAIN_ID": str(args.domain_id)}, log_dir=run_dir / "logs",
                     stop_timeout_s=args.stop_timeout)
    status_path = run_dir / "status.json"

    samples: list[tuple[float, dict[str, float]]] = []  # (t since start, name -> RSS MiB)
    statuses: list[tuple[float, dict | None]] = []
    cpu_at: dict[str, dict[str, float]] = {}
    exits: dict[str, int] = {}
    load_start = os.getloadavg()
    t_start = time.monotonic()

    def sample() -> dict | None:
        sup.poll()
        for name, rc in sup.returncodes.items():
            if rc is not None and name not in exits:
                exits[name] = rc
                log(f"{name} exited with code {rc} (see {run_dir / 'logs'})")
        t = time.monotonic() - t_start
        rss = {name: v for name, pid in sup.pids.items() if (v := rss_mib(pid)) is not None}
        samples.append((t, rss))
        s = read_status(status_path)
        statuses.append((t, s))
        return s

    def cpu_snapshot() -> dict[str, tuple[float, float | None]]:
        return {name: (v, runqueue_wait_s(pid)) for name, pid in sup.pids.items() if (v := cpu_s(pid)) is not None}

    log(f"starting {len(specs)} processes ({args.groups} groups, {cfg.algo} on {cfg.env}) in domain "
        f"{args.domain_id}, run in {base}")
    sup.start()
    t0 = t_end = None
    try:
        # start-up: until every group has stepped (the learner counts each group's env steps)
        deadline = time.monotonic() + args.startup_timeout
        while True:
            s = sample()
            stepped = sum(1 for g in (s or {}).get("groups", {}).values() if g.get("env_steps", 0) > 0)
            if stepped == args.groups or time.monotonic() > deadline or "learner" in exits:
                break
            time.sleep(args.sample_period)
        t0, wall0 = time.monotonic() - t_start, time.time()
        cpu_at["start"] = cpu_snapshot()
        log(f"start-up took {t0:.1f} s ({stepped}/{args.groups} groups stepping); measuring {args.seconds:.0f} s")
        next_progress = t0 + 10
        while "learner" not in exits:
            now = time.monotonic() - t_start
            if now >= t0 + args.seconds:
                break
            time.sleep(min(args.sample_period, t0 + args.seconds - now))
            s = sample()
            if s and samples[-1][0] >= next_progress:
                next_progress += 10
                log(f"t={samples[-1][0] - t0:5.0f}s env_steps={sum(g['env_steps'] for g in s['groups'].values())} "
                    f"transitions={s['env_steps']} updates={s['updates']} episodes={s['episodes']} "
                    f"learner_rss={samples[-1][1].get('learner', float('nan')):.0f}MiB")
        cpu_at["end"] = cpu_snapshot()
        t_end, wall_end = time.monotonic() - t_start, time.time()
        final_status = read_status(status_path)
    finally:
        log("stopping every process")
        stop_t = time.monotonic()
        rcs = sup.stop()
        stop_s = time.monotonic() - stop_t
    load_end = os.getloadavg()
    log("analysing the logs")

    duration = t_end - t0
    steady_t = t0 + args.steady_from * duration
    steady_wall = wall0 + args.steady_from * duration

    # -- the logs --------------------------------------------------------------------------------
    env_rows: dict[str, dict[int, dict]] = {}
    bad_lines = 0
    for ns, path in step_logs.items():
        rows, bad = read_jsonl(path)
        bad_lines += bad
        env_rows[ns.rstrip("/") or "/"] = {int(r["key"]): r for r in rows}
    transitions, bad = read_jsonl(transition_log)
    bad_lines += bad

    # alignment
    misaligned, missing, duplicates, examples = 0, 0, 0, []
    seen: set[tuple[str, int]] = set()
    for tr in transitions:
        group, key = tr["group"], int(tr["key"])
        if (group, key) in seen:
            duplicates += 1
        seen.add((group, key))
        env = env_rows.get(group, {}).get(key)
        if env is None:
            missing += 1
            misaligned += 1
            continue
        bad_fields = [f for f in ALIGN_FIELDS if tr[f] != env[f]]
        if bad_fields:
            misaligned += 1
            if len(examples) < 5:
                examples.append({"group": group, "key": key, "fields": bad_fields})
    env_total = sum(len(r) for r in env_rows.values())
    # env steps without a transition: before the learner took the group's data (it starts at an episode
    # start), in flight when the graph was stopped, or gaps in between (lost data: must be 0)
    before_first = in_flight = gaps = 0
    for group, rows in env_rows.items():
        assembled = sorted(k for g, k in seen if g == group)
        first, last = (assembled[0], assembled[-1]) if assembled else (None, None)
        for key in rows:
            if (group, key) in seen:
                continue
            if first is None or key < first:
                before_first += 1
            elif key > last:
                in_flight += 1
            else:
                gaps += 1

    # latency: env publishes step K -> learner assembled the transition into K
    lat_all, lat_steady, lat_by_group = [], [], defaultdict(list)
    for tr in transitions:
        env = env_rows.get(tr["group"], {}).get(int(tr["key"]))
        if env is None or "wall_time" not in tr:
            continue
        d = tr["wall_time"] - env["wall_time"]
        lat_all.append(d)
        lat_by_group[tr["group"]].append(d)
        if steady_wall <= env["wall_time"] <= wall_end:
            lat_steady.append(d)
    # action round trip (step P published -> action(P) at the environment), credit wait + step, step cycle
    rtt, wait, cycle, rtt_steady, credit_wait = [], [], [], [], 0.0
    for rows in env_rows.values():
        for r in rows.values():
            prev = rows.get(int(r["prev_key"]))
            wait.append(r["wall_time"] - r["action_time"])
            if prev is None:  # the previous step was an episode's first (t = 0): not in the step log
                continue
            rtt.append(r["action_time"] - prev["wall_time"])
            cycle.append(r["wall_time"] - prev["wall_time"])
            credit_wait += r["wall_time"] - r["action_time"]
            if steady_wall <= prev["wall_time"] <= wall_end:
                rtt_steady.append(r["action_time"] - prev["wall_time"])

    # throughput
    groups_out = {}
    env_times_all, tr_times_all = [], []
    tr_by_group = defaultdict(list)
    for tr in transitions:
        tr_by_group[tr["group"]].append(tr["wall_time"])
    for group, rows in env_rows.items():
        et = np.array([r["wall_time"] for r in rows.values()])
        tt = np.array(tr_by_group.get(group, []))
        env_times_all.append(et)
        tr_times_all.append(tt)
        groups_out[group] = {"env_steps_per_s": rate_in(et, wall0, wall_end),
                             "env_steps_per_s_steady": rate_in(et, steady_wall, wall_end),
                             "transitions_per_s": rate_in(tt, wall0, wall_end),
                             "env_steps_logged": int(et.size), "transitions": int(tt.size),
                             "latency_ms_p50": pct(lat_by_group.get(group, [])).get("p50")}
    env_times = np.concatenate(env_times_all) if env_times_all else np.array([])
    tr_times = np.concatenate(tr_times_all) if tr_times_all else np.array([])
    in_window = [(t, s) for t, s in statuses if s is not None]
    throughput = {
        "env_steps_per_s": rate_in(env_times, wall0, wall_end),
        "env_steps_per_s_steady": rate_in(env_times, steady_wall, wall_end),
        "transitions_per_s": rate_in(tr_times, wall0, wall_end),
        "transitions_per_s_steady": rate_in(tr_times, steady_wall, wall_end),
        "updates_per_s": status_rate(in_window, lambda s: s["updates"], t0, t_end),
        "updates_per_s_steady": status_rate(in_window, lambda s: s["updates"], steady_t, t_end),
        "episodes_per_s": status_rate(in_window, lambda s: s["episodes"], t0, t_end),
        "per_group": groups_out,
    }
    per_group_rates = [g["env_steps_per_s"] for g in groups_out.values()]
    throughput["per_group_env_steps_per_s_min_max"] = [min(per_group_rates), max(per_group_rates)] \
        if per_group_rates else None

    # memory
    names = sorted({n for _, rss in samples for n in rss})
    by_name = {n: [(t, rss[n]) for t, rss in samples if n in rss] for n in names}
    total_series = [(t, sum(rss.values())) for t, rss in samples if rss]
    series = []
    for t, rss in downsample(samples, args.series_points):
        point = {"t_s": round(t - t0, 1)}
        for kind in KINDS:
            vals = [v for n, v in rss.items() if kind_of(n) == kind]
            if kind == "learner":
                point["learner_mib"] = round(vals[0], 1) if vals else None
            elif vals:
                point[f"{kind}_max_mib"] = round(max(vals), 1)
        point["all_nodes_mib"] = round(sum(rss.values()), 1)
        series.append(point)
    peak = {kind: round(max((v for n, s in by_name.items() if kind_of(n) == kind for _, v in s), default=0.0), 1)
            for kind in KINDS}
    growth_out = {"window_s": [round(steady_t - t0, 1), round(t_end - t0, 1)],
                  "learner": growth(by_name.get("learner", []), steady_t, t_end),
                  "all_nodes": growth(total_series, steady_t, t_end)}
    for kind in KINDS[:-1]:
        per = {n: growth(s, steady_t, t_end) for n, s in by_name.items() if kind_of(n) == kind}
        per = {n: g for n, g in per.items() if "growth_mib" in g}
        if per:
            worst = max(per, key=lambda n: per[n]["growth_mib"])
            growth_out[f"{kind}_worst"] = {"process": worst, **per[worst]}

    # replay fill (estimate from the finished episodes in the transition log)
    replay_full_at, replay_est, episodes_done = None, 0, 0
    open_eps: dict[str, list] = defaultdict(list)
    for tr in sorted(transitions, key=lambda r: r["wall_time"]):
        ep = open_eps[tr["group"]]
        ep.append(tr["subgoal"])
        if tr["terminated"] or tr["truncated"]:
            options = 1 + sum(1 for a, b in zip(ep, ep[1:]) if a != b)
            replay_est += len(ep) * STEP_BYTES + EPISODE_BYTES + options * OPTION_BYTES
            episodes_done += 1
            open_eps[tr["group"]] = []
            if replay_full_at is None and replay_est >= sub_bytes:
                replay_full_at = tr["wall_time"] - wall0
    memory = {
        "sampled_every_s": args.sample_period,
        "replay": {"sub_replay_bytes_bound": sub_bytes, "meta_replay_bytes_bound": meta_bytes,
                   "sub_replay_episodes_bound": cfg.sub.replay_episodes,
                   "meta_replay_episodes_bound": cfg.meta.replay_episodes,
                   "episodes_finished": episodes_done,
                   "sub_replay_bytes_offered_estimate": replay_est,
                   "sub_replay_full_at_s_estimate": None if replay_full_at is None else round(replay_full_at, 1),
                   "note": "replay may grow up to its bound; the estimate counts the frames, fields and subgoal "
                           "images of the finished episodes the learner received (hdrqn_ros/agents/replay.py)"},
        "growth_steady": growth_out,
        "peak_mib_by_kind": peak,
        "light_nodes_goal_mib": LIGHT_NODE_GOAL_MIB,
        "light_nodes_pass": all(peak.get(k, 0.0) <= LIGHT_NODE_GOAL_MIB for k in ("environment", "critic")),
        "series": series,
    }

    # counters, warnings, CPU
    fs = final_status or {}
    gstats = fs.get("groups", {})
    counters = {k: sum(g.get(k, 0) for g in gstats.values()) for k in ("skipped", "lost_episodes", "rejected")}
    at_t0 = next((st for t, st in statuses if st is not None and t >= t0 - 1e-6), None) or {}
    counters_after_startup = {k: v - sum(g.get(k, 0) for g in at_t0.get("groups", {}).values())
                              for k, v in counters.items()}
    warnings: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for path in sorted((run_dir / "logs").glob("*.log")):
        kind = kind_of(path.stem.replace("_", "/", 1)) if path.stem != "learner" else "learner"
        text = path.read_text(errors="replace")
        for label, pattern in LOG_PATTERNS.items():
            if (n := len(re.findall(re.escape(pattern), text))):
                warnings[label][kind] += n
    cpu, waited = defaultdict(float), defaultdict(float)
    for name, (end_cpu, end_wait) in cpu_at.get("end", {}).items():
        if name in cpu_at.get("start", {}):
            start_cpu, start_wait = cpu_at["start"][name]
            cpu[kind_of(name)] += end_cpu - start_cpu
            if end_wait is not None and start_wait is not None:
                waited[kind_of(name)] += end_wait - start_wait
    wall = max(duration, 1e-9)

    return {
        "benchmark": "load: groups -> 1 learner over rclpy / Fast DDS (loopback)",
        "machine_cores": os.cpu_count(),
        "loadavg_1min_start_end": [round(load_start[0], 2), round(load_end[0], 2)],
        "config": {"algo": cfg.algo, "env": cfg.env, "view": cfg.env_kwargs.get("view", 5), "seed": cfg.seed,
                   "groups": args.groups, "processes": len(specs), "learning_starts": cfg.learning_starts,
                   "update_every": cfg.update_every, "sub_batch": [cfg.sub.batch_size, cfg.sub.seq_len],
                   "meta_batch": [cfg.meta.batch_size, cfg.meta.seq_len], "credit_window": 20,
                   "max_owed_updates": 2, "domain_id": args.domain_id, "respawn": False},
        "startup_s": round(t0, 1),
        "duration_s": round(duration, 1),
        "steady_from_s": round(steady_t - t0, 1),
        "groups": args.groups,
        "throughput": throughput,
        "latency_ms": {
            "env_publish_to_learner_transition": pct(lat_all),
            "env_publish_to_learner_transition_steady": pct(lat_steady),
            "action_round_trip": pct(rtt),
            "action_round_trip_steady": pct(rtt_steady),
            "action_to_next_step_publish": pct(wait),
            "step_cycle": pct(cycle),
            "env_time_share_waiting_for_credit": round(credit_wait / float(np.sum(cycle)), 3) if cycle else None,
        },
        "memory": memory,
        "alignment": {"transitions_checked": len(transitions), "misaligned": misaligned,
                      "missing_env_row": missing, "duplicates": duplicates, "fields": list(ALIGN_FIELDS),
                      "examples": examples, "env_steps_logged": env_total,
                      "env_steps_not_assembled": {"before_learner_took_group": before_first,
                                                  "in_flight_at_stop": in_flight, "gaps_mid_run": gaps},
                      "unparsable_log_lines": bad_lines},
        "learner_status": {"final": {k: fs.get(k) for k in ("episodes", "env_steps", "updates", "eps_sub",
                                                              "eps_meta", "success_last100")},
                           "dropped_rejected": counters,
                           "dropped_rejected_after_startup": counters_after_startup,
                           "per_group": {g: {k: v.get(k) for k in ("env_steps", "transitions", "skipped",
                                                                   "lost_episodes", "rejected")}
                                         for g, v in gstats.items()}},
        "log_warnings": {k: dict(v) for k, v in warnings.items()},
        "cpu_share_of_one_core_by_kind": {k: round(v / wall, 3) for k, v in sorted(cpu.items())},
        "runqueue_wait_s_per_s_by_kind": {k: round(v / wall, 3) for k, v in sorted(waited.items())},
        "process_exits_during_run": exits,
        "stop_s": round(stop_s, 1),
        "stop_returncodes_nonzero": {n: rc for n, rc in rcs.items() if rc not in (0, None)},
    }


if __name__ == "__main__":
    main()
