"""``hdrqn experiment NAME --ray [ADDRESS]``: an experiment's runs as tasks on a Ray cluster.

:func:`run_experiment_on_ray` has the contract of :func:`hdrqn_ros.experiments.run_experiment`
(exit code per run, 0 for skipped ones; ``experiment.json``; the ``OUT/NAME`` layout that
``hdrqn plot`` reads) but runs each ``hdrqn train`` inside a Ray task with its own
resources (``num_cpus``, ``num_gpus``) and ``max_retries``: a worker process that dies
mid-run is retried, and the retry resumes from the run's last checkpoint.

Where the files go:

- ``shared=True``: every machine sees ``OUT`` (a shared filesystem); runs write into
  ``OUT/NAME`` and ``OUT/NAME.log`` directly.
- otherwise the head gathers them: the task receives the run directory's current content
  (a tar in memory: the checkpoint and metrics of an interrupted run), trains in a
  directory of the worker's machine (``$TMPDIR/hdrqn-ray/KEY``), and returns the run
  directory as a tar that the driver unpacks into ``OUT/NAME`` (regular files and
  folders only; no absolute paths, no ``..``).

Ray is started bound to loopback when no address is given, or joined at ``address``;
usage statistics are switched off (``RAY_USAGE_STATS_ENABLED=0``) wherever this module
starts or joins Ray and in the workers' environment. See docs/training.md, "Cluster".
"""
from __future__ import annotations

import argparse
import hashlib
import io
import os
import shutil
import socket
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from hdrqn_ros.extras import MissingExtra, install_command, require
from hdrqn_ros.experiments import (RUN_METRICS, Experiment, RunSpec, config_dir, default_jobs, episodes_logged,
                                   set_aside, split_finished, target_episodes, write_manifest)

INSTALL_HINT = install_command("cluster")
USAGE_STATS_ENV = "RAY_USAGE_STATS_ENABLED"
REPORT_S = 2.0
"""Seconds between a task's reports of its run's episodes to the progress board."""
TRAIN_CSVS = ("train.csv", "visits.csv", "options.csv", "eval.csv", "losses.csv")
"""Metrics tables with an ``episode`` first column (trimmed to the checkpoint on resume)."""


class ClusterError(ValueError):
    """A usage problem with ``--ray`` and its flags; the CLI prints it and exits 2."""


class RayUnavailable(ClusterError):
    """ray is not installed."""


CONNECT_TIMEOUT_S = 10.0
"""How long ``--ray ADDRESS`` waits for the cluster's head to accept a connection."""


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """A :class:`ClusterError` naming ``address`` (``HOST:PORT`` or ``ray://HOST:PORT``) when
    nothing accepts a TCP connection there within ``timeout_s``: ray itself retries for
    minutes without an error. ``auto`` and an address without a port are left to ray."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not port.isdigit() or not host:
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ClusterError(f"cannot reach the Ray cluster at {address} within {timeout_s:g} s "
                           f"({type(exc).__name__}: {exc.strerror or exc}): is its head running "
                           f"(ray start --head) and the port open?") from None


class UnsafeArchive(ValueError):
    """A run archive with a member that would land outside its run directory."""


# -- starting or joining Ray -----------------------------------------------------------------
def import_ray():
    """``import ray`` with usage statistics off; :class:`RayUnavailable` when it is missing."""
    os.environ[USAGE_STATS_ENV] = "0"  # before ray is imported or initialised: nothing is reported
    try:
        require("cluster", "--ray")
    except MissingExtra as exc:
        raise RayUnavailable(str(exc)) from None
    import ray

    return ray


def start_ray(address: str | None = None, num_cpus: int | None = None) -> bool:
    """Join the Ray cluster at ``address``, or (``None``) start a local one bound to
    127.0.0.1 only with ``num_cpus`` CPUs (default: one per core). Returns whether this
    call initialised Ray (False: it already was, in this process; it is used as is)."""
    ray = import_ray()
    if ray.is_initialized():
        return False
    if address is not None:
        check_reachable(address)
        ray.init(address=address, logging_level="WARNING")
        return True
    # ray.init(_node_ip_address="127.0.0.1") alone is not loopback: ray resolves a loopback
    # node address to the machine's outbound one (services.resolve_ip_for_localhost) and
    # its servers then listen on every interface. Ray keeps a node on loopback only where
    # it does not support clusters (ray_constants.ENABLE_RAY_CLUSTER false, its default on
    # macOS/Windows); with that for the length of ray.init, the GCS, raylet, workers and
    # runtime-env agent listen on 127.0.0.1 (test/test_cluster.py checks /proc/net/tcp*).
    from ray._private import ray_constants

    saved = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(num_cpus=num_cpus or default_jobs(), include_dashboard=False, _node_ip_address="127.0.0.1",
                 logging_level="WARNING")
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = saved
    return True


def worker_env() -> dict[str, str]:
    """Environment variables of the workers' runtime env: usage statistics off and, when
    this package is imported from a source tree rather than an installed site-packages,
    that tree on ``PYTHONPATH`` (so that workers, and the ``hdrqn train`` they start, run
    the driver's code; an installed package needs nothing)."""
    env = {USAGE_STATS_ENV: "0"}
    root = Path(__file__).resolve().parents[1]
    if not any(part in ("site-packages", "dist-packages") for part in root.parts):
        env["PYTHONPATH"] = str(root)
    return env


# -- run archives ------------------------------------------------------------------------------
def pack_dir(path: Path) -> bytes:
    """The regular files and folders under ``path`` as an uncompressed tar (relative names)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for item in sorted(path.rglob("*")):
            if item.is_symlink() or not (item.is_file() or item.is_dir()):
                continue
            tar.add(item, arcname=item.relative_to(path).as_posix(), recursive=False)
    return buf.getvalue()


def unpack_dir(data: bytes, dest: Path) -> None:
    """Unpack a :func:`pack_dir` archive into ``dest``; :class:`UnsafeArchive` (and nothing
    written) when a member is not a regular file or folder, or its name is absolute or
    has a ``..`` part."""
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:") as tar:
        members = tar.getmembers()
        for m in members:
            parts = Path(m.name).parts
            if not (m.isfile() or m.isdir()) or m.name.startswith(("/", "\\")) or Path(m.name).is_absolute() \
                    or ".." in parts or not parts:
                raise UnsafeArchive(f"refusing run archive member {m.name!r} ({'file' if m.isfile() else m.type!r})")
        dest.mkdir(parents=True, exist_ok=True)
        tar.extractall(dest, members=members, filter="data")


def _replace_run_dir(data: bytes, run_dir: Path) -> None:
    """Unpack a returned run next to ``run_dir``, then swap it in (the old one is removed)."""
    incoming = run_dir.with_name(f".{run_dir.name}.incoming")
    old = run_dir.with_name(f".{run_dir.name}.old")
    for p in (incoming, old):
        shutil.rmtree(p, ignore_errors=True)
    unpack_dir(data, incoming)
    if run_dir.exists():
        run_dir.rename(old)
    incoming.rename(run_dir)
    shutil.rmtree(old, ignore_errors=True)


# -- resuming after a crash --------------------------------------------------------------------
def checkpoint_episodes(run_dir: Path) -> int | None:
    """Episodes done according to ``run_dir/checkpoints/last.pt``; None without a readable one."""
    path = run_dir / "checkpoints" / "last.pt"
    if not path.is_file():
        return None
    from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint

    try:
        return int(load_checkpoint(path)["progress"]["episodes"])
    except (CheckpointError, KeyError, TypeError, ValueError):
        return None


def trim_to_checkpoint(run_dir: Path, episodes: int) -> int:
    """Drop metrics rows of episodes after ``episodes`` (a killed run logs past its last
    checkpoint; ``--resume`` appends from the checkpoint, so without this those episodes
    would be in train.csv twice), and a torn last line. Returns the rows dropped."""
    dropped = 0
    for name in TRAIN_CSVS:
        path = run_dir / name
        if not path.is_file():
            continue
        lines = path.read_bytes().splitlines(keepends=True)
        if not lines:
            continue
        keep = [lines[0]] if lines[0].endswith(b"\n") else []
        for line in lines[1:]:
            try:
                ok = line.endswith(b"\n") and int(line.split(b",", 1)[0]) <= episodes
            except ValueError:
                ok = False
            if ok:
                keep.append(line)
        if len(keep) != len(lines):
            dropped += len(lines) - len(keep)
            tmp = path.with_name(f".{name}.tmp")
            tmp.write_bytes(b"".join(keep))
            os.replace(tmp, path)
    return dropped


# -- the task ----------------------------------------------------------------------------------
_CHILD = ("import ctypes, os, runpy, signal, sys\n"
          "ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG\n"
          "if os.getppid() != int(sys.argv[1]):\n"
          "    os._exit(137)  # the worker died before prctl\n"
          "sys.argv = ['hdrqn', *sys.argv[2:]]\n"
          "runpy.run_module('hdrqn_ros.cli', run_name='__main__', alter_sys=True)\n")
"""``hdrqn train`` that dies with the Ray worker that started it (Linux ``PR_SET_PDEATHSIG``),
so that a retried run never shares its directory with the killed attempt's process."""


def _child_argv(argv: list[str]) -> list[str]:
    if sys.platform.startswith("linux"):
        return [sys.executable, "-c", _CHILD, str(os.getpid()), *argv]
    return [sys.executable, "-m", "hdrqn_ros.cli", *argv]


def _prepare(run_dir: Path) -> tuple[bool, str]:
    """Make ``run_dir`` ready to (re)start: (resume it?, what was done, for the log). A run
    with a checkpoint has its metrics trimmed to it; one without has its metrics set
    aside (:func:`set_aside`)."""
    done = checkpoint_episodes(run_dir)
    if done is not None:
        dropped = trim_to_checkpoint(run_dir, done)
        return True, f"resuming at episode {done}" + (f" ({dropped} metrics rows after it dropped)" if dropped else "")
    if any((run_dir / name).exists() for name in RUN_METRICS):
        return False, f"starting again (no checkpoint; earlier metrics kept in {set_aside(run_dir)})"
    return False, "starting"


def _work_dir(key: str) -> Path:
    return Path(tempfile.gettempdir()) / "hdrqn-ray" / key


def _gathered_run(work: Path, payload: bytes | None) -> Path:
    """The worker's copy of a gathered run: the driver's content, unless this machine
    holds a further one (a retry on the machine of a killed attempt)."""
    run_dir = work / "run"
    incoming = work / "incoming"
    shutil.rmtree(incoming, ignore_errors=True)
    incoming.mkdir(parents=True)
    if payload:
        unpack_dir(payload, incoming)
    here, sent = checkpoint_episodes(run_dir) if run_dir.is_dir() else None, checkpoint_episodes(incoming)
    if here is not None and (sent is None or here > sent):
        shutil.rmtree(incoming)
    else:
        shutil.rmtree(run_dir, ignore_errors=True)
        incoming.rename(run_dir)
    return run_dir


def _line_start(log) -> bytes:
    """``b"\\n"`` when the log (opened ``ab+``) ends inside a line: a killed attempt's
    block-buffered output stops wherever its last buffer ended."""
    if log.seek(0, os.SEEK_END) == 0:
        return b""
    log.seek(-1, os.SEEK_END)
    return b"" if log.read(1) == b"\n" else b"\n"


def run_task(spec: RunSpec, job: dict, payload: bytes | None, board) -> dict:
    """One run in a Ray worker (``job``: see :func:`run_experiment_on_ray`). Returns
    ``{"code", "host"}`` and, when gathering, ``"tar"`` (the run directory) and ``"log"``."""
    shared = job["shared"]
    work = _work_dir(job["key"])
    work.mkdir(parents=True, exist_ok=True)
    if shared:
        out = Path(job["out"])
        run_dir, log_path = out / spec.name, out / f"{spec.name}.log"
        out.mkdir(parents=True, exist_ok=True)
    else:
        run_dir, log_path = _gathered_run(work, payload), work / "run.log"
    config = work / job["config_name"]
    config.write_text(job["config_text"], encoding="utf-8")
    argv = spec.argv(config, run_dir, job["episodes"], tuple(job["extra_sets"]))
    resume, how = _prepare(run_dir)
    if resume:
        argv.append("--resume")
    host = socket.gethostname()
    with open(log_path, "ab+") as log:
        log.write(_line_start(log) + f"[hdrqn ray] {spec.name} on {host} (worker pid {os.getpid()}): {how}\n".encode())
        log.flush()
        proc = subprocess.Popen(_child_argv(argv), stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    try:
        while True:
            board.report.remote(spec.name, episodes_logged(run_dir))
            try:
                proc.wait(timeout=job.get("report_s", REPORT_S))
                break
            except subprocess.TimeoutExpired:
                pass
    except BaseException:  # ray.cancel: KeyboardInterrupt; hdrqn train checkpoints on SIGTERM
        proc.terminate()
        try:
            proc.wait(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if shared:  # a gathered run's copy stays: a later attempt on this machine resumes from it
            shutil.rmtree(work, ignore_errors=True)
        raise
    board.report.remote(spec.name, episodes_logged(run_dir))
    result = {"code": proc.returncode, "host": host}
    if not shared:
        result["tar"] = pack_dir(run_dir)
        result["log"] = log_path.read_bytes()
    shutil.rmtree(work, ignore_errors=True)
    return result


class ProgressBoard:
    """A Ray actor: the episodes each run has logged, as its task last reported them."""

    def __init__(self):
        self.episodes: dict[str, int] = {}

    def report(self, name: str, episodes: int) -> None:
        self.episodes[name] = episodes

    def snapshot(self) -> dict[str, int]:
        return dict(self.episodes)


# -- the driver --------------------------------------------------------------------------------
def run_experiment_on_ray(exp: Experiment, runs: list[RunSpec], out: Path, episodes: int | None,
                          address: str | None = None, cpus_per_run: float = 1, gpus_per_run: float = 0,
                          extra_sets: tuple[str, ...] = (), shared: bool = False, progress: bool = True,
                          max_retries: int = 3, poll_s: float = 2.0) -> dict[str, int]:
    """Run ``runs`` as Ray tasks (``cpus_per_run`` CPUs and ``gpus_per_run`` GPUs each;
    ``--set device=cuda`` in ``extra_sets`` makes them use it) on the cluster at
    ``address``, or on a local one on loopback (``None``); ``shared``: the runs write into
    ``out`` themselves (a filesystem every machine shares), else the driver gathers them.

    As :func:`~hdrqn_ros.experiments.run_experiment`: ``out/experiment.json``, finished runs
    skipped, interrupted ones resumed, logs in ``out/NAME.log``; returns each run's exit
    code (0 for skipped ones; 1 for a run whose task failed, e.g. its worker died more
    than ``max_retries`` times). A task whose worker process dies is retried and resumes
    from the run's last checkpoint. Ctrl-C cancels the tasks (their runs checkpoint).
    A Ray already initialised in this process is used as is; one this call started is
    shut down at the end.
    """
    if not cpus_per_run > 0:
        raise ClusterError(f"--cpus-per-run must be > 0, got {cpus_per_run}")
    if not gpus_per_run >= 0:
        raise ClusterError(f"--gpus-per-run must be >= 0, got {gpus_per_run}")
    out = Path(out)
    config = config_dir() / exp.config
    write_manifest(exp, runs, out, episodes, extra_sets)
    results, pending = split_finished(runs, out, episodes)
    if not pending:
        return results
    ray = import_ray()
    target = target_episodes(config, episodes)
    started = start_ray(address)
    bar = board = None
    refs: dict = {}
    try:
        runtime_env = {"env_vars": worker_env()}
        board = ray.remote(ProgressBoard).options(num_cpus=0, runtime_env=runtime_env).remote()
        task = ray.remote(run_task).options(num_cpus=cpus_per_run, num_gpus=gpus_per_run, max_retries=max_retries,
                                            retry_exceptions=False, runtime_env=runtime_env)
        where = str(out.resolve())
        for r in pending:
            run_dir = out / r.name
            job = {"shared": shared, "out": where, "episodes": episodes, "extra_sets": list(extra_sets),
                   "config_name": config.name, "config_text": config.read_text(encoding="utf-8"),
                   "key": hashlib.sha256(f"{socket.gethostname()}:{where}/{r.name}".encode()).hexdigest()[:20]}
            payload = pack_dir(run_dir) if not shared and run_dir.is_dir() else None
            refs[task.remote(r, job, payload, board)] = r.name
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=target * len(runs), unit="ep", dynamic_ncols=True, desc=f"{exp.name} (ray)")
        reported: dict[str, int] = {}

        def show() -> None:
            nonlocal reported
            if bar is None:
                return
            try:
                reported = ray.get(board.snapshot.remote(), timeout=10)
            except Exception:  # a slow board: keep the last numbers
                pass
            running = set(refs.values())
            bar.n = sum(min(target, reported.get(r.name, 0) if r.name in running else episodes_logged(out / r.name))
                        for r in runs)
            bar.set_postfix_str(f"done {len(results)}/{len(runs)}, running or queued {len(refs)}", refresh=False)
            bar.refresh()

        show()
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=len(refs), timeout=poll_s)
            for ref in ready:
                name = refs.pop(ref)
                results[name] = _collect(ray, ref, name, out, shared, exp.name)
            show()
    except KeyboardInterrupt:
        for ref in refs:
            ray.cancel(ref)  # KeyboardInterrupt in the task: it stops hdrqn train with SIGTERM (a checkpoint)
        ray.wait(list(refs), num_returns=len(refs), timeout=120)
        raise
    finally:
        if bar is not None:
            bar.close()
        if board is not None:
            ray.kill(board)
        if started:
            ray.shutdown()
    return results


def _collect(ray, ref, name: str, out: Path, shared: bool, exp_name: str) -> int:
    """A finished task's exit code; when gathering, its run directory and log land in ``out``."""
    try:
        res = ray.get(ref)
    except ray.exceptions.RayError as exc:
        print(f"{exp_name}: run {name} failed on the cluster: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 1
    if not shared:
        with open(out / f"{name}.log", "ab") as log:
            log.write(res["log"])
        try:
            _replace_run_dir(res["tar"], out / name)
        except (UnsafeArchive, tarfile.TarError) as exc:
            print(f"{exp_name}: run {name}: the archive from {res['host']} was not unpacked: {exc}", file=sys.stderr)
            return 1
    if res["code"] != 0:
        print(f"{exp_name}: run {name} failed on {res['host']} (exit {res['code']}); see {out / name}.log",
              file=sys.stderr)
    return res["code"]


# -- the CLI's flags ---------------------------------------------------------------------------
def add_ray_arguments(parser: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]``, ``--cpus-per-run``, ``--gpus-per-run``, ``--shared-dir`` (``hdrqn experiment``)."""
    group = parser.add_argument_group(
        "Ray cluster", f"run the runs as Ray tasks ({INSTALL_HINT}; docs/training.md, \"Cluster\"); "
                       "--jobs is then unused: each run takes --cpus-per-run of the cluster's CPUs")
    group.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                       help="on the Ray cluster at ADDRESS (HEAD:6379, started with `ray start`), or without ADDRESS "
                            "on a local one listening on 127.0.0.1 only; write NAME before --ray (or --ray=ADDRESS)")
    group.add_argument("--cpus-per-run", type=float, default=None, metavar="N",
                       help="CPUs each run reserves (default 1)")
    group.add_argument("--gpus-per-run", type=float, default=None, metavar="N",
                       help="GPUs each run reserves (default 0); with --set device=cuda the run trains on it")
    group.add_argument("--shared-dir", action="store_true",
                       help="--out is on a filesystem every machine shares: runs write there directly (default: the "
                            "driver sends each run its files and gathers the run directory back)")


def ray_options(args: argparse.Namespace) -> dict:
    """``run_experiment_on_ray`` keyword arguments from :func:`add_ray_arguments`' flags;
    :class:`ClusterError` for a bad value, or a Ray flag without ``--ray``."""
    if args.ray is None:
        given = [flag for flag, value in (("--cpus-per-run", args.cpus_per_run), ("--gpus-per-run", args.gpus_per_run),
                                          ("--shared-dir", args.shared_dir or None)) if value is not None]
        if given:
            raise ClusterError(f"{', '.join(given)} only apply with --ray")
        return {}
    cpus = 1 if args.cpus_per_run is None else args.cpus_per_run
    gpus = 0 if args.gpus_per_run is None else args.gpus_per_run
    if not cpus > 0:
        raise ClusterError(f"--cpus-per-run must be > 0, got {cpus}")
    if not gpus >= 0:
        raise ClusterError(f"--gpus-per-run must be >= 0, got {gpus}")
    return {"address": None if args.ray == "local" else args.ray, "cpus_per_run": cpus, "gpus_per_run": gpus,
            "shared": args.shared_dir}
