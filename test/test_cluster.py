"""``hdrqn experiment --ray``: real tiny runs on a real local Ray cluster (2 CPUs, loopback only)."""
from __future__ import annotations

import argparse
import csv
import io
import json
import os
import signal
import socket
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path

import pytest

os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
ray = pytest.importorskip("ray", reason="Ray is not installed (pip install '.[cluster]')")

from hdrqn_ros import cluster  # noqa: E402
from hdrqn_ros.experiments import EXPERIMENTS, episodes_logged  # noqa: E402

EXP = EXPERIMENTS["exp3-gridworld-2goals"]
TINY = ("eval_episodes=2", "num_envs=2")
# a run of ~10 s: checkpoints every 5 episodes, updates from the third episode on
LONGER = ("num_envs=2", "eval_every=0", "checkpoint_every=5", "learning_starts=100")


def _descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rpartition(")")[2].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    found, todo = [], [root]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def _cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return [part.decode(errors="replace") for part in f.read().split(b"\0") if part]
    except OSError:
        return []


def _listening(pids: list[int]) -> dict[int, list[tuple[str, int]]]:
    """TCP LISTEN sockets (address, port) of each pid, from /proc/net/tcp{,6} and /proc/PID/fd."""
    inodes = {}
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        with open(table) as f:
            for line in f.readlines()[1:]:
                fields = line.split()
                if fields[3] != "0A":  # LISTEN
                    continue
                hexaddr, hexport = fields[1].split(":")
                raw = bytes.fromhex(hexaddr)
                if v6:
                    raw = b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4))
                    addr = socket.inet_ntop(socket.AF_INET6, raw)
                else:
                    addr = socket.inet_ntop(socket.AF_INET, raw[::-1])
                inodes[fields[9]] = (addr, int(hexport, 16))
    out = {}
    for pid in pids:
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if link.startswith("socket:[") and link[8:-1] in inodes:
                out.setdefault(pid, []).append(inodes[link[8:-1]])
    return out


@pytest.fixture(scope="module")
def ray_cluster():
    """A local cluster started the way ``--ray`` without an address starts one."""
    t0 = time.monotonic()
    assert cluster.start_ray(None, num_cpus=2)
    started = time.monotonic() - t0
    print(f"\nlocal Ray cluster started in {started:.1f} s")
    yield started
    ray_pids = _descendants(os.getpid())
    ray.shutdown()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(os.path.exists(f"/proc/{p}") and _cmdline(p) for p in ray_pids):
        time.sleep(0.2)
    left = {p: _cmdline(p)[:1] for p in ray_pids if _cmdline(p)}
    assert not left, f"Ray processes left after ray.shutdown(): {left}"


@pytest.fixture(autouse=True)
def no_worker_copies_left():
    """Workers keep a run's copy in $TMPDIR/hdrqn-ray/KEY only while it runs (or after Ctrl-C, when gathering)."""
    base = Path(tempfile.gettempdir()) / "hdrqn-ray"
    before = set(base.glob("*"))
    yield
    assert set(base.glob("*")) <= before, sorted(set(base.glob("*")) - before)


def _rows(path: Path) -> list[int]:
    with open(path) as f:
        return [int(r["episode"]) for r in csv.DictReader(f)]


def test_gather_mode_runs_listens_on_loopback_skips_finished_runs_and_plots(ray_cluster, tmp_path):
    out = tmp_path / "exp"
    runs = EXP.runs([0, 1], ["dqn"])
    results = cluster.run_experiment_on_ray(EXP, runs, out, 3, extra_sets=TINY, poll_s=0.5)
    assert results == {"dqn-s0": 0, "dqn-s1": 0}
    manifest = json.loads((out / "experiment.json").read_text())
    assert [r["dir"] for r in manifest["runs"]] == ["dqn-s0", "dqn-s1"] and manifest["episodes"] == 3
    for name in results:
        assert _rows(out / name / "train.csv") == [1, 2, 3]
        assert json.loads((out / name / "summary.json").read_text())["episodes"] == 3
        assert (out / name / "checkpoints" / "last.pt").is_file() and (out / name / "config.yaml").is_file()
        log = (out / f"{name}.log").read_text()
        assert log.count("training dqn") == 1 and ": starting\n" in log and "done: 3 episodes" in log
    assert not list(out.glob(".*")), "no leftovers of the swap-in"

    # every Ray process (this driver, GCS, raylet, agents, workers) listens on loopback only
    pids = [os.getpid(), *_descendants(os.getpid())]
    sockets = _listening(pids)
    names = {pid: (_cmdline(pid) or ["?"])[0] for pid in sockets}
    found = sorted({addr for socks in sockets.values() for addr, _ in socks})
    print(f"listening: {found} from {sorted(set(names.values()))}")
    assert len(sockets) >= 3, sockets  # at least GCS, raylet and a worker
    assert set(found) <= {"127.0.0.1", "::ffff:127.0.0.1", "::1"}, (found, names)
    assert any("gcs_server" in n for n in names.values()) and any("raylet" in n for n in names.values())

    # the same call again: nothing runs (the logs and metrics are untouched)
    before = {name: ((out / name / "train.csv").stat().st_mtime_ns, (out / f"{name}.log").read_text())
              for name in results}
    assert cluster.run_experiment_on_ray(EXP, runs, out, 3, extra_sets=TINY, progress=False) == results
    assert {name: ((out / name / "train.csv").stat().st_mtime_ns, (out / f"{name}.log").read_text())
            for name in results} == before

    plot = subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", "plot", str(out)], capture_output=True,
                          text=True, timeout=120)
    assert plot.returncode == 0, plot.stderr
    assert "| dqn | 2 (2) |" in (out / "table.md").read_text()


def _train_child(timeout: float = 90) -> int:
    """The pid of the one ``hdrqn train`` a Ray worker of this test's cluster is running."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for pid in _descendants(os.getpid()):
            argv = _cmdline(pid)
            if "PR_SET_PDEATHSIG" in " ".join(argv) and "train" in argv:
                return pid
        time.sleep(0.2)
    raise AssertionError("no hdrqn train process started")


@pytest.mark.parametrize("shared", [False, True], ids=["gather", "shared"])
def test_a_run_whose_worker_is_killed_is_retried_and_resumes_from_its_checkpoint(ray_cluster, tmp_path, shared):
    out = tmp_path / "exp"
    runs = EXP.runs([0], ["dqn"])
    episodes = 60
    results: dict = {}
    driver = threading.Thread(target=lambda: results.update(cluster.run_experiment_on_ray(
        EXP, runs, out, episodes, extra_sets=LONGER, shared=shared, progress=False, poll_s=0.5)))
    driver.start()
    try:
        child = _train_child()
        argv = _cmdline(child)
        run_dir = Path(argv[argv.index("--out") + 1])
        assert (run_dir == out / "dqn-s0") if shared else (run_dir.name == "run" and "hdrqn-ray" in run_dir.parts)
        deadline = time.monotonic() + 90
        while (episodes_logged(run_dir) < 12 or cluster.checkpoint_episodes(run_dir) is None) \
                and time.monotonic() < deadline:
            time.sleep(0.1)
        with open(f"/proc/{child}/stat") as f:
            worker = int(f.read().rpartition(")")[2].split()[1])
        assert _cmdline(worker)[0].startswith("ray::"), _cmdline(worker)
        killed_at = episodes_logged(run_dir)
        assert killed_at < episodes, "the run finished before the kill: make it longer"
        os.kill(worker, signal.SIGKILL)
        # the kernel delivers SIGKILL to the child once the worker's exit is done, which on a loaded
        # machine (a worker's memory to tear down, then the child's) can take seconds: wait on the event
        gone_by = time.monotonic() + 60
        while _cmdline(child) and time.monotonic() < gone_by:
            time.sleep(0.1)
        assert not _cmdline(child), "hdrqn train outlived its worker by 60 s"
    finally:
        driver.join(timeout=150)
    assert not driver.is_alive()
    assert results == {"dqn-s0": 0}
    assert _rows(out / "dqn-s0" / "train.csv") == list(range(1, episodes + 1))
    assert json.loads((out / "dqn-s0" / "summary.json").read_text())["episodes"] == episodes
    log = (out / "dqn-s0.log").read_text()
    headers = [line for line in log.splitlines() if line.startswith("[hdrqn ray]")]
    assert len(headers) == 2 and headers[0].endswith(": starting"), headers
    resumed = int(headers[1].split("resuming at episode ")[1].split()[0])
    assert 5 <= resumed <= killed_at, (headers, killed_at)
    assert log.count("training dqn") == 2 and f"done: {episodes} episodes" in log
    assert not list((out / "dqn-s0").glob("stale-*"))


def _tar(**members: bytes | str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data in members.items():
            info = tarfile.TarInfo(name.replace("__", "/"))
            if isinstance(data, str):  # a symbolic link to data
                info.type, info.linkname = tarfile.SYMTYPE, data
                tar.addfile(info)
            else:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def test_run_archives_round_trip_and_unsafe_members_are_refused(tmp_path):
    src = tmp_path / "src"
    (src / "checkpoints").mkdir(parents=True)
    (src / "train.csv").write_text("episode\n1\n")
    (src / "checkpoints" / "last.pt").write_bytes(b"\0" * 1000)
    cluster.unpack_dir(cluster.pack_dir(src), tmp_path / "dst")
    assert (tmp_path / "dst" / "train.csv").read_text() == "episode\n1\n"
    assert (tmp_path / "dst" / "checkpoints" / "last.pt").read_bytes() == b"\0" * 1000
    for bad in (_tar(ok=b"1", **{"..__evil": b"x"}), _tar(**{"/tmp__evil": b"x"}), _tar(link="/etc/passwd"),
                _tar(**{"a__..__..__evil": b"x"})):
        with pytest.raises(cluster.UnsafeArchive):
            cluster.unpack_dir(bad, tmp_path / "bad")
        assert not (tmp_path / "bad").exists() and not (tmp_path / "evil").exists()


def test_metrics_past_the_checkpoint_and_a_torn_line_are_trimmed(tmp_path):
    (tmp_path / "train.csv").write_text("episode,steps\n1,5\n2,5\n3,5\n4,5\n5,")
    (tmp_path / "options.csv").write_text("episode,start\n1,0\n1,1\n3,0\n")
    (tmp_path / "eval.csv").write_text("episode,success\n")
    assert cluster.trim_to_checkpoint(tmp_path, 2) == 4
    assert (tmp_path / "train.csv").read_text() == "episode,steps\n1,5\n2,5\n"
    assert (tmp_path / "options.csv").read_text() == "episode,start\n1,0\n1,1\n"
    assert (tmp_path / "eval.csv").read_text() == "episode,success\n"


def test_a_header_after_a_killed_attempts_torn_output_starts_its_own_line(tmp_path):
    log_path = tmp_path / "run.log"
    for content, expected in ((b"", b""), (b"episode 12 done\n", b""), (b"episode 12 do", b"\n")):
        log_path.write_bytes(content)
        with open(log_path, "ab+") as log:
            assert cluster._line_start(log) == expected, content


def test_ray_flags_and_their_errors():
    p = argparse.ArgumentParser()
    p.add_argument("name")
    cluster.add_ray_arguments(p)
    assert cluster.ray_options(p.parse_args(["exp1"])) == {}
    assert cluster.ray_options(p.parse_args(["exp1", "--ray"])) == {
        "address": None, "cpus_per_run": 1, "gpus_per_run": 0, "shared": False}
    assert cluster.ray_options(p.parse_args(["exp1", "--ray", "head:6379", "--shared-dir", "--cpus-per-run", "2",
                                             "--gpus-per-run", "1"])) == {
        "address": "head:6379", "cpus_per_run": 2, "gpus_per_run": 1, "shared": True}
    for argv, message in ((["--shared-dir"], "--shared-dir only apply with --ray"),
                          (["--ray", "--cpus-per-run", "0"], "--cpus-per-run must be > 0"),
                          (["--ray", "--gpus-per-run", "-1"], "--gpus-per-run must be >= 0")):
        with pytest.raises(cluster.ClusterError, match=message):
            cluster.ray_options(p.parse_args(["exp1", *argv]))
    assert "--shared-dir" in p.format_help() and "127.0.0.1" in p.format_help()


def test_an_unreachable_cluster_address_is_one_exit_2_line_naming_it(tmp_path):
    """Nothing listens at the address: exit 2 within the connect timeout, naming the address,
    instead of ray retrying for minutes (a closed port on loopback)."""
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{free.getsockname()[1]}"
    run = subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", "experiment", "exp1", "--ray", address, "--episodes",
                          "5", "--seeds", "0", "--out", str(tmp_path / "x")], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 2, run.stderr
    error = [line for line in run.stderr.splitlines() if "error" in line]
    assert error == [f"hdrqn experiment: error: cannot reach the Ray cluster at {address} within 10 s "
                     f"(ConnectionRefusedError: Connection refused): is its head running (ray start --head) and the "
                     f"port open?"]


def test_without_ray_the_error_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(cluster.RayUnavailable, match=r"pip install 'hdrqn_ros\[cluster\]'") as err:
        cluster.import_ray()
    assert isinstance(err.value, ValueError)  # hdrqn's main() turns ValueError into exit 2
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"


DRIVER = """
import signal, sys
from pathlib import Path
signal.signal(signal.SIGINT, signal.default_int_handler)  # also when started with SIGINT ignored (a background job)
from hdrqn_ros.cluster import run_experiment_on_ray
from hdrqn_ros.experiments import EXPERIMENTS
exp = EXPERIMENTS["exp3-gridworld-2goals"]
try:
    run_experiment_on_ray(exp, exp.runs([0], ["dqn"]), Path(sys.argv[1]), 100000, extra_sets=tuple(sys.argv[2:]),
                          shared=True, progress=False, poll_s=0.5)
except KeyboardInterrupt:
    sys.exit(130)
"""


def test_ctrl_c_cancels_the_tasks_their_runs_checkpoint_and_no_ray_process_is_left(tmp_path):
    """A driver of its own (``--ray`` without an address: it starts and stops a local cluster)."""
    out = tmp_path / "exp"
    env = {**os.environ, "PYTHONPATH": str(Path(cluster.__file__).resolve().parents[1])}
    proc = subprocess.Popen([sys.executable, "-c", DRIVER, str(out), *LONGER], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    try:
        run_dir = out / "dqn-s0"
        deadline = time.monotonic() + 300  # a local Ray cluster starts slowly on a loaded machine
        while (episodes_logged(run_dir) < 8 or cluster.checkpoint_episodes(run_dir) is None) \
                and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        spawned = _descendants(proc.pid)
        assert any("raylet" in " ".join(_cmdline(p)) for p in spawned)
        proc.send_signal(signal.SIGINT)
        output, _ = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, output
    saved = cluster.checkpoint_episodes(run_dir)
    assert saved is not None and saved >= episodes_logged(run_dir) >= 8, (saved, episodes_logged(run_dir))
    log = (out / "dqn-s0.log").read_text()
    assert "interrupted" in log, log  # hdrqn train stopped by SIGTERM, with a checkpoint
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline and any(_cmdline(p) for p in spawned):
        time.sleep(0.2)
    assert not [_cmdline(p)[:1] for p in spawned if _cmdline(p)], "processes left by the driver's cluster"
