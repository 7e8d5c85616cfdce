"""Process supervisor behind ``hdrqn up``: runs a node graph as plain OS processes.

Generic: it knows only :class:`ProcessSpec` (name, argv, respawn/required policy).
Every child runs in its own session/process group, so a terminal Ctrl-C reaches
only the supervisor, which then stops each group with SIGINT -> SIGTERM -> SIGKILL
(signals hit the child *and* anything it spawned).

Bounds: state is O(number of specs) -- one current Popen, one exit code and one
restart counter per process (an exited Popen is replaced, never accumulated);
respawns are rate-limited by ``respawn_delay_s`` and only counted; log files are
appended to (one per process, growth = child output; rotate externally);
``stop()`` takes at most ``stop_timeout_s + min(1, stop_timeout_s/2) + 1`` s;
the TTY status line is truncated to the terminal width.
"""
from __future__ import annotations

import atexit
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

USAGE_EXIT = 2
"""Exit code of a process that rejected its parameters or input (never respawned)."""
_LIVE: set[subprocess.Popen] = set()  # children not yet reaped (atexit safety net)


def python_command(entry: str) -> list[str]:
    """The argv that runs ``entry`` in this Python: ``"pkg.module"`` (``python -m``) or
    ``"pkg.module:func"`` (the function's return value is the exit code)."""
    module, _, func = entry.partition(":")
    if not func:
        return [sys.executable, "-m", module]
    return [sys.executable, "-c", f"import sys; from {module} import {func} as m; sys.exit(m())"]


def _killpg(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


@atexit.register
def _kill_leftovers() -> None:
    """Safety net: SIGKILL the process group of every child no stop() reaped."""
    for proc in list(_LIVE):
        if proc.poll() is None:
            _killpg(proc.pid, signal.SIGKILL)
        _LIVE.discard(proc)


@dataclass(frozen=True)
class ProcessSpec:
    """One supervised process (like a ROS 2 launch ``Node`` action)."""

    name: str                    # e.g. "group0/environment" (status line, log file name)
    argv: list[str]              # command to run
    respawn: bool = False        # restart after an exit while not stopping (not after exit code
    #                              2, bad parameters or input: a restart would fail the same way)
    respawn_delay_s: float = 1.0
    required: bool = False       # its (non-respawned) exit stops everything
    env: dict[str, str] | None = None  # environment variables of this process only (over the supervisor's)
    stack_dump_signal: int | None = None  # a signal on which it prints its stacks and goes on: stop()
    #                              sends it when the process outlives the SIGINT grace, so its log shows where it hung


class Supervisor:
    """Start, watch, respawn and stop a set of processes.

    ``env`` is merged over ``os.environ`` (plus ``PYTHONUNBUFFERED=1`` by default so
    logs are live). ``status`` returns an extra string for the status line.
    """

    def __init__(self, specs: Iterable[ProcessSpec], env: dict[str, str] | None = None,
                 log_dir: Path | None = None, status: Callable[[], str] | None = None,
                 stop_timeout_s: float = 5.0):
        self.specs: dict[str, ProcessSpec] = {}
        for s in specs:
            if s.name in self.specs:
                raise ValueError(f"duplicate process name {s.name!r}")
            self.specs[s.name] = s
        self.env = dict(os.environ)
        self.env.setdefault("PYTHONUNBUFFERED", "1")
        self.env.update(env or {})
        self.log_dir = Path(log_dir) if log_dir is not None else None
        self.status = status
        self.stop_timeout_s = float(stop_timeout_s)
        self.restarts: dict[str, int] = {n: 0 for n in self.specs}
        self.returncodes: dict[str, int | None] = {n: None for n in self.specs}
        self._procs: dict[str, subprocess.Popen] = {}
        self._respawn_at: dict[str, float] = {}   # name -> monotonic time of next start
        self._required_exit: tuple[str, int] | None = None
        self._signal: int | None = None
        self._started = self._stopped = False

    @property
    def pids(self) -> dict[str, int]:
        """Pids of the processes running as of the last poll()."""
        return {n: p.pid for n, p in self._procs.items() if p.returncode is None}

    def _spawn(self, name: str) -> None:
        spec, out = self.specs[name], None
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.log_path(name), "ab")  # append
            out.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} start {name}: "
                      f"{shlex.join(spec.argv)}\n".encode())
            out.flush()
        # stop() relies on SIGINT, but an inherited SIG_IGN (e.g. `hdrqn up &` in a script)
        # survives exec; a handled signal is reset to default, so swap in a no-op handler.
        swap = (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) == signal.SIG_IGN)
        if swap:
            signal.signal(signal.SIGINT, lambda *_: None)
        try:
            proc = subprocess.Popen(spec.argv, env={**self.env, **(spec.env or {})}, stdin=subprocess.DEVNULL,
                                    stdout=out, stderr=subprocess.STDOUT if out else None, start_new_session=True)
        finally:
            if swap:
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            if out is not None:
                out.close()  # the child holds its own copy of the descriptor
        self._procs[name] = proc
        self.returncodes[name] = None
        _LIVE.add(proc)

    def _reap(self, name: str, proc: subprocess.Popen) -> None:
        self.returncodes[name] = proc.returncode
        _LIVE.discard(proc)
        _killpg(proc.pid, signal.SIGKILL)  # stragglers the leader left in its group

    def start(self) -> None:
        """Start every process (each in a new session); on failure stop those started."""
        if self._started:
            return
        self._started = True
        try:
            for name in self.specs:
                self._spawn(name)
        except BaseException:
            self.stop()
            raise

    def poll(self) -> None:
        """Reap exited children, schedule/perform respawns, note a required exit."""
        now = time.monotonic()
        for name, proc in list(self._procs.items()):
            if proc.returncode is None and proc.poll() is not None:
                self._reap(name, proc)
                spec = self.specs[name]
                if self._stopped:
                    continue
                if spec.respawn and proc.returncode != USAGE_EXIT:
                    self._respawn_at[name] = now + spec.respawn_delay_s
                elif spec.respawn:
                    print(f"[supervisor] {name} exited with code {USAGE_EXIT} (bad parameters or input, see its "
                          f"log); not respawning it", file=sys.stderr)
                    if spec.required and self._required_exit is None:
                        self._required_exit = (name, proc.returncode)
                elif spec.required and self._required_exit is None:
                    self._required_exit = (name, proc.returncode)
        for name, due in list(self._respawn_at.items()):
            if now >= due and not self._stopped:
                del self._respawn_at[name]
                try:
                    self._spawn(name)
                except OSError as exc:  # e.g. EMFILE: retry later, never busy-loop
                    print(f"[supervisor] respawn of {name} failed: {exc}", file=sys.stderr)
                    self._respawn_at[name] = now + self.specs[name].respawn_delay_s
                    continue
                self.restarts[name] += 1

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        """Send ``sig`` to the process group of ``name`` (fault injection)."""
        proc = self._procs[name]
        if proc.returncode is None:
            _killpg(proc.pid, sig)

    def _alive(self) -> list[tuple[str, subprocess.Popen]]:
        return [(n, p) for n, p in self._procs.items() if p.returncode is None]

    def stop(self) -> dict[str, int | None]:
        """SIGINT all groups, wait ``stop_timeout_s``, SIGTERM, wait, SIGKILL. Idempotent."""
        if not self._stopped:
            self._stopped = True
            self._respawn_at.clear()
            grace = (self.stop_timeout_s, min(1.0, self.stop_timeout_s / 2), 1.0)
            for sig, wait in zip((signal.SIGINT, signal.SIGTERM, signal.SIGKILL), grace):
                for name, proc in self._alive():
                    if sig == signal.SIGTERM:
                        self._report_hang(name, proc)
                    _killpg(proc.pid, sig)
                deadline = time.monotonic() + wait
                while True:
                    for name, proc in self._alive():
                        if proc.poll() is not None:
                            self._reap(name, proc)
                    if not self._alive() or time.monotonic() >= deadline:
                        break
                    time.sleep(0.02)
                if not self._alive():
                    break
        return dict(self.returncodes)

    def _report_hang(self, name: str, proc: subprocess.Popen) -> None:
        """Say that ``name`` outlived the SIGINT grace and, if it can, have it print its stacks."""
        if proc.poll() is not None:
            return
        said = f"[supervisor] {name} did not stop within {self.stop_timeout_s:g} s of SIGINT"
        dump_signal = self.specs[name].stack_dump_signal
        if dump_signal is not None:
            try:
                os.kill(proc.pid, dump_signal)
            except ProcessLookupError:
                return
            said += f"; its threads' stacks are in {self.log_path(name) if self.log_dir is not None else 'its stderr'}"
        print(f"{said}; sending SIGTERM", file=sys.stderr)

    def log_path(self, name: str) -> Path:
        """The log file of process ``name`` (needs ``log_dir``)."""
        if self.log_dir is None:
            raise ValueError("this supervisor keeps no logs (no log_dir)")
        return self.log_dir / (name.replace("/", "_") + ".log")

    def log_tail(self, name: str, lines: int = 40) -> str:
        """The last ``lines`` lines of process ``name``'s log ("" before it has one)."""
        path = self.log_path(name)
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:]) if path.exists() else ""

    def status_line(self) -> str:
        """One line: how many processes are up, restarts, anything not up, then status()."""
        up, trouble = 0, []
        for name in self.specs:
            proc = self._procs.get(name)
            if name in self._respawn_at:
                trouble.append(f"{name} respawning")
            elif proc is None:
                trouble.append(f"{name} not started")
            elif proc.returncode is None:
                up += 1
            else:
                trouble.append(f"{name} exited rc={proc.returncode}")
        restarts = sum(self.restarts.values())
        line = f"[{up}/{len(self.specs)} up" + (f", {restarts} restarts" if restarts else "") + "]"
        if trouble:
            line += " " + ", ".join(trouble)
        if self.status is not None:
            try:
                line += " " + self.status()
            except Exception as exc:  # a broken status callback must not kill the graph
                line += f" status error: {exc!r}"
        return line

    def run(self, until: Callable[[], bool] | None = None, refresh_s: float = 0.5) -> int:
        """Supervise until ``until()``, a required exit, all exited, or SIGINT/SIGTERM.

        Always calls stop(). Returns 0, 1 (a required process exited with rc != 0)
        or 128+signal (130 for Ctrl-C, 143 for SIGTERM).
        """
        def on_signal(signum, _frame):
            self._signal = self._signal or signum

        old = {}
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                old[s] = signal.signal(s, on_signal)
        tty = sys.stdout.isatty()
        try:
            self.start()
            next_line = 0.0
            while True:
                self.poll()
                if (self._signal or self._required_exit or (until is not None and until())
                        or (not self._respawn_at and not self._alive())):
                    break
                now = time.monotonic()
                if now >= next_line:
                    next_line = now + (refresh_s if tty else 5.0)
                    if tty:
                        width = shutil.get_terminal_size().columns
                        sys.stdout.write("\r" + self.status_line()[: width - 1] + "\x1b[K")
                        sys.stdout.flush()
                    else:
                        print(self.status_line(), flush=True)
                time.sleep(min(refresh_s, 0.1))
        except KeyboardInterrupt:
            self._signal = self._signal or signal.SIGINT
        finally:
            if tty:
                sys.stdout.write("\n")  # keep shutdown output off the status line
            self.stop()  # our handlers stay installed so a 2nd Ctrl-C cannot cut it short
            for s, h in old.items():
                signal.signal(s, h if h is not None else signal.SIG_DFL)
        if self._signal:
            return 128 + int(self._signal)
        if self._required_exit is not None and self._required_exit[1] != 0:
            return 1
        return 0
