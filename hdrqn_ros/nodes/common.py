"""What every node executable shares: start-up, parameters, the spin loop, clean exit."""
from __future__ import annotations

import ctypes
import faulthandler
import os
import signal
import sys
import threading
from typing import Any, Callable

from hdrqn_ros.deploy.errors import PolicyError
from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.envs.registration import GRID_IDS, MONTEZUMA_IDS, make_batch
from hdrqn_ros.extras import MissingExtra
from hdrqn_ros.middleware import (BackendError, Middleware, Node, ParameterError, ParameterRule, RosArgsError,
                                  open_middleware)
from hdrqn_ros.middleware.ros_args import split_ros_args
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.nodes.managed import MANAGED_FLAG, ManagedNode
from hdrqn_ros.protocol.wire import MAX_ENVS

ENV_DEFAULTS = {"algo": "hdrqn-v2", "env": "hdrqn/GridWorld-2Goals-v0", "view": "5", "seed": 0}
"""Parameters every training-graph node declares (the launch files set them once for all
nodes with a ``/**`` entry)."""
ENV_RULES = {
    "algo": ParameterRule("agent: hdrqn-v2, hdrqn-v1, hdqn, drqn or dqn",
                          choices=("hdrqn-v2", "hdrqn-v1", "hdqn", "drqn", "dqn")),
    "env": ParameterRule("environment id (hdrqn envs lists them)"),
    "view": ParameterRule("gridworld view: an odd number of cells or 'full' (a string)"),
    "seed": ParameterRule("seed of the environments and of the controllers' exploration"),
    "num_envs": ParameterRule("environments the environment node steps as one batch (the same on every node of "
                              "a group)", low=1, high=64),
}
"""The rules of the shared parameters (:class:`~hdrqn_ros.middleware.ParameterRule`): read-only."""


def live_parameters(node: Node, params: dict, rules: dict[str, ParameterRule], apply=None) -> None:
    """Let ``ros2 param set`` change the ``live`` parameters of ``rules``: each accepted
    value goes into ``params`` (the node reads it at its next use), then to ``apply(name,
    value)`` for a node that keeps a derived value."""
    def accept(name: str, value) -> None:
        params[name] = value
        if apply is not None:
            apply(name, value)

    node.on_parameters_set({name: rule for name, rule in rules.items() if rule.live}, accept)


class NodeConfigError(ValueError):
    """A parameter value the node cannot work with."""


def env_kwargs(env_id: str, view: str) -> dict:
    """``make_batch`` keyword arguments from the ``view`` parameter ("3", "5", "full"...)."""
    if env_id in MONTEZUMA_IDS:
        return {}
    if env_id not in GRID_IDS:
        raise NodeConfigError(f"unknown env {env_id!r}; choose one of {sorted(GRID_IDS) + sorted(MONTEZUMA_IDS)}")
    if view == "full":
        return {"view": "full"}
    if not view.isdigit():
        raise NodeConfigError(f"view must be an odd number of cells or 'full', got {view!r}")
    return {"view": int(view)}


def check_num_envs(num_envs: int) -> int:
    """The ``num_envs`` parameter (environments one environment node steps as a batch), checked."""
    if not 1 <= num_envs <= MAX_ENVS:
        raise NodeConfigError(f"num_envs must be in 1..{MAX_ENVS}, got {num_envs}")
    return num_envs


def check_algo(algo: str) -> None:
    if algo not in ALGO_SPECS:
        raise NodeConfigError(f"unknown algo {algo!r}; choose one of {sorted(ALGO_SPECS)}")


def domain_sizes(env_id: str, view: str) -> tuple[int, int]:
    """(num_actions, num_subgoals) of the domain."""
    probe = make_batch(env_id, 1, **env_kwargs(env_id, view))
    return probe.num_actions, probe.num_subgoals


STARTUP_ERRORS = (NodeConfigError, ParameterError, RosArgsError, BackendError, PolicyError, MissingExtra,
                  FileNotFoundError)
"""What every node reports as bad input: exit code 2 (a node adds its own to :func:`run_node`,
so that a node imports only what it uses: the environment and critic stay small)."""


MIDDLEWARE_SHUTDOWN_LIMIT_S = 5.0
"""How long a stopping node waits for its middleware to shut down before it exits without it
(:func:`shut_down_within`): less than the 10 s ``ros2 launch`` allows from SIGINT to SIGKILL;
a normal teardown takes well under a second."""
LARGE_BUFFER_BYTES = 256 * 1024
"""Allocations of this size or more get memory maps of their own in a node process (see
:func:`return_large_buffers_to_the_os`)."""


def return_large_buffers_to_the_os() -> None:
    """Have glibc serve every allocation of :data:`LARGE_BUFFER_BYTES` or more (a sample of MiBs,
    oversized or not, and its copies) from a memory map of its own, unmapped when freed.

    glibc's default raises that threshold to the size of the first such buffer freed, after which
    big buffers come from the heap and a burst of them (a flood of oversized samples, taken 64 at
    a time) can leave tens of MiB in the heap for the rest of the process: test_bounds measured
    +44 MiB once under load. A user's ``MALLOC_MMAP_THRESHOLD_`` wins; off glibc this does nothing.
    Not for the learner: its per-update tensors are big and short-lived, and a fresh map for each
    would cost its page faults on every update."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is not None and sys.platform.startswith("linux"):
        mallopt(-3, LARGE_BUFFER_BYTES)  # -3: M_MMAP_THRESHOLD


def run_node(build: Callable[[Middleware], Any], argv: list[str] | None = None,
             input_errors: tuple[type[Exception], ...] = (), managed_name: str | None = None,
             large_buffers_to_os: bool = True) -> int:
    """Open the middleware, build the node object, spin until it finishes, Ctrl-C or
    SIGTERM, then clean up (the object's ``close()`` first, then the middleware).

    A node that can run managed gives its ``managed_name``: with ``--managed`` among the
    executable's arguments it starts unconfigured and lifecycle transitions build, start
    and stop it (:mod:`hdrqn_ros.nodes.managed`).

    ``large_buffers_to_os``: :func:`return_large_buffers_to_the_os` first (every node but the learner).

    SIGINT (Ctrl-C, what ``ros2 launch`` sends) and SIGTERM are a normal stop: exit code
    the object's ``exit_code`` (0). 2 for bad parameters, arguments, checkpoints, policies or bags:
    :data:`STARTUP_ERRORS` and the node's ``input_errors``. While it runs, :data:`STACK_DUMP_SIGNAL`
    (SIGUSR1) prints every thread's stack to stderr."""
    if large_buffers_to_os:
        return_large_buffers_to_the_os()
    argv = list(sys.argv if argv is None else argv)
    managed = MANAGED_FLAG in split_ros_args(argv)[0][1:]
    if managed and managed_name is None:
        print(f"error: this node has no managed (lifecycle) mode: drop {MANAGED_FLAG}", file=sys.stderr)
        return 2
    stopped = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stopped.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    dumps_stacks = _print_stacks_on(STACK_DUMP_SIGNAL)
    middleware = built = None
    exit_code = 1  # until the node says otherwise: an exception is on its way out
    try:
        middleware = open_middleware(argv)
        built = ManagedNode(middleware, managed_name, build, (*STARTUP_ERRORS, *input_errors)) if managed \
            else build(middleware)
        middleware.spin(until=lambda: stopped.is_set() or getattr(built, "finished", False))
        exit_code = getattr(built, "exit_code", 0)
    except KeyboardInterrupt:
        exit_code = 130
    except (*STARTUP_ERRORS, *input_errors) as exc:
        print(f"error: {exc}", file=sys.stderr)
        exit_code = 2
    finally:
        if built is not None and hasattr(built, "close"):
            built.close()
        if middleware is not None:
            shut_down_within(middleware, MIDDLEWARE_SHUTDOWN_LIMIT_S, exit_code)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if dumps_stacks:
            faulthandler.unregister(STACK_DUMP_SIGNAL)
    return exit_code


def shut_down_within(middleware: Middleware, limit_s: float, exit_code: int) -> None:
    """``middleware.shutdown()``, bounded: if it has not returned after ``limit_s`` (a DDS
    library's teardown that hangs), print why and every thread's stack to stderr and end the
    process with ``exit_code``. It runs after the node's ``close()``: nothing of the node's
    own is left to save, and peers see it go when its DDS lease runs out."""
    returned = threading.Event()

    def give_up() -> None:
        if returned.wait(limit_s):
            return
        print(f"warning: the {middleware.backend} middleware did not shut down within {limit_s:g} s; every "
              f"thread's stack follows; exiting with code {exit_code} without it", file=sys.stderr, flush=True)
        try:
            faulthandler.dump_traceback(all_threads=True)
        except (AttributeError, ValueError, OSError):  # stderr captured in memory
            pass
        sys.stdout.flush()
        os._exit(exit_code)

    watchdog = threading.Thread(target=give_up, name="shutdown-watchdog", daemon=True)
    watchdog.start()
    try:
        middleware.shutdown()
    finally:
        returned.set()
        # gone before the interpreter's exit: a thread still waking up then gets ended by
        # Python 3.12 (pthread_exit), which aborted a node that had torch loaded 2 times in 8
        watchdog.join()


def _print_stacks_on(sig: int) -> bool:
    """On ``sig`` print every thread's Python stack to stderr and go on (``kill -USR1 PID``
    shows where a node is stuck); False where stderr has no file descriptor."""
    try:
        faulthandler.register(sig, all_threads=True)
    except (AttributeError, ValueError, OSError):  # stderr captured in memory
        return False
    return True
