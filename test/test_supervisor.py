"""Tests for hdrqn_ros.supervisor with real child processes (fast: ~5 s total)."""
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hdrqn_ros.supervisor import ProcessSpec, Supervisor

PY = sys.executable
SLEEP = "import signal, sys, time; signal.signal(signal.SIGINT, lambda *a: sys.exit(0)); time.sleep(60)"
READY = SLEEP.replace("time.sleep(60)", "print('ready', flush=True); time.sleep(60)")
STUBBORN = ("import signal, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
            "signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ready', flush=True); time.sleep(60)")


def spec(name, code, **kw):
    return ProcessSpec(name, [PY, "-c", code], **kw)


def gone(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def wait_ready(log_dir, *names):
    """A child signalled before its SIGINT handler is set up may miss it (then it gets
    SIGTERM after stop_timeout_s); wait for readiness so timing asserts are deterministic."""
    for n in names:
        wait_for(lambda: "ready" in (log_dir / f"{n.replace('/', '_')}.log").read_text().splitlines())


def wait_for(pred, timeout=60.0):  # generous: python start-up on a loaded machine
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.02)


@pytest.fixture
def sups():
    made = []
    yield made
    for s in made:  # never leak children, even when a test fails
        s.stop()

HANGS_ON_STOP = ("import faulthandler, signal, time\n"
                 "faulthandler.register(signal.SIGUSR1, all_threads=True)\n"
                 "signal.signal(signal.SIGINT, signal.SIG_IGN); signal.signal(signal.SIGTERM, signal.SIG_IGN)\n"
                 "def stuck_in_close():\n    time.sleep(60)\n"
                 "print('ready', flush=True); stuck_in_close()\n")


def test_stop_terminates_all(sups, tmp_path):
    sup = Supervisor([spec(f"g/p{i}", READY) for i in range(3)], log_dir=tmp_path, stop_timeout_s=60.0)
    sups.append(sup)
    sup.start()
    wait_ready(tmp_path, *sup.specs)
    pids = sup.pids
    assert len(pids) == 3
    codes = sup.stop()
    assert codes == {"g/p0": 0, "g/p1": 0, "g/p2": 0}  # exited via their SIGINT handler, not SIGTERM or SIGKILL
    assert all(gone(pid) for pid in pids.values())
    assert sup.stop() == codes  # idempotent


def test_stubborn_process_is_killed(sups, tmp_path):
    sup = Supervisor([spec("stubborn", STUBBORN)], log_dir=tmp_path, stop_timeout_s=0.5)
    sups.append(sup)
    sup.start()
    pid = sup.pids["stubborn"]
    wait_ready(tmp_path, "stubborn")
    t0 = time.monotonic()
    codes = sup.stop()
    elapsed = time.monotonic() - t0
    assert codes["stubborn"] == -signal.SIGKILL
    assert 0.5 <= elapsed < 30  # SIGKILL only after the SIGINT's timeout, and then at once
    assert gone(pid)


@pytest.mark.parametrize("dumps_stacks", [True, False])
def test_a_process_that_outlives_the_sigint_grace_is_reported(sups, tmp_path, capfd, dumps_stacks):
    """One that can print its stacks (as every node can) is asked for them before SIGTERM: its log
    shows where it hung. Any other is not sent the signal (it would die of it, unreported)."""
    sup = Supervisor([spec("node", HANGS_ON_STOP, stack_dump_signal=signal.SIGUSR1 if dumps_stacks else None)],
                     log_dir=tmp_path, stop_timeout_s=0.5)
    sups.append(sup)
    sup.start()
    wait_ready(tmp_path, "node")
    assert sup.stop() == {"node": -signal.SIGKILL}
    said = capfd.readouterr().err
    assert "[supervisor] node did not stop within 0.5 s of SIGINT" in said
    log = sup.log_tail("node")
    if dumps_stacks:
        assert f"stacks are in {tmp_path / 'node.log'}" in said
        assert 'line 5 in stuck_in_close' in log, log
    else:
        assert "stacks" not in said and "line 5 in stuck_in_close" not in log


def test_respawn_and_kill(sups):
    sup = Supervisor([spec("flaky", "import sys; sys.exit(1)", respawn=True, respawn_delay_s=0.05),
                      spec("node", SLEEP, respawn=True, respawn_delay_s=0.05)], stop_timeout_s=2.0)
    sups.append(sup)
    sup.start()

    def polled(cond):
        sup.poll()
        return cond()

    wait_for(lambda: polled(lambda: sup.restarts["flaky"] >= 1))
    old = sup.pids["node"]
    sup.kill("node")
    wait_for(lambda: polled(lambda: sup.pids.get("node") not in (None, old)))
    assert sup.restarts["node"] == 1
    assert gone(old)
    pid = sup.pids["node"]
    sup.stop()
    assert gone(pid)


def test_required_failure_stops_everything(sups):
    sup = Supervisor([spec("req", "import sys, time; time.sleep(0.2); sys.exit(3)", required=True),
                      spec("other", SLEEP)], stop_timeout_s=2.0)
    sups.append(sup)
    sup.start()
    other = sup.pids["other"]
    assert sup.run(refresh_s=0.05) == 1
    assert sup.returncodes["req"] == 3
    assert sup.returncodes["other"] is not None
    assert gone(other)


def test_run_until_returns_zero(sups):
    sup = Supervisor([spec("a", SLEEP)], status=lambda: "step=1", stop_timeout_s=2.0)
    sups.append(sup)
    t_end = time.monotonic() + 0.3
    assert sup.run(until=lambda: time.monotonic() > t_end, refresh_s=0.05) == 0
    assert "step=1" in sup.status_line() and "exited" in sup.status_line()
    assert sup.pids == {}


def test_log_files(sups, tmp_path):
    log_dir = tmp_path / "logs"
    sup = Supervisor([spec("g0/env", "print('hello env')"),
                      spec("g0/agent", "import sys; print('oops agent', file=sys.stderr)")],
                     log_dir=log_dir)
    sups.append(sup)
    assert sup.run(refresh_s=0.05) == 0  # all exited -> returns
    assert sorted(p.name for p in log_dir.iterdir()) == ["g0_agent.log", "g0_env.log"]
    assert "hello env" in (log_dir / "g0_env.log").read_text()
    assert "oops agent" in (log_dir / "g0_agent.log").read_text()


DRIVER = f"""
import json, sys
from hdrqn_ros.supervisor import ProcessSpec, Supervisor
code = {SLEEP!r}
sup = Supervisor([ProcessSpec("a", [sys.executable, "-c", code]),
                  ProcessSpec("b", [sys.executable, "-c", code])], stop_timeout_s=2.0)
sup.start()
print(json.dumps(sup.pids), flush=True)
sys.exit(sup.run(refresh_s=0.05))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_driver(sig):
    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([PY, "-c", DRIVER], stdout=subprocess.PIPE, text=True, env=env, cwd=root)
    watchdog = threading.Timer(120.0, proc.kill)
    watchdog.start()
    try:
        pids = json.loads(proc.stdout.readline())
        assert set(pids) == {"a", "b"}
        # the first status line is printed inside run(), i.e. after its handlers are installed
        line = "x"
        while line and not line.startswith("["):  # "" at EOF: the driver died, the wait below fails
            line = proc.stdout.readline()
        proc.send_signal(sig)  # Ctrl-C / `kill <pid of hdrqn up>`
        assert proc.wait(timeout=90) == 128 + sig  # 130 / 143
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()
    # the driver reaped them; if it had orphaned them they would still be alive
    assert all(gone(pid) for pid in pids.values())
