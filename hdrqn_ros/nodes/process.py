"""One node process: ``rclpy.init``, the node, spin until it finishes or is stopped, clean exit.

What every node executable's ``main`` does through :func:`run_node`:

- DDS stays on the loopback interface unless ``$HDRQN_DDS_INTERFACE`` names another
  (:func:`~hdrqn_ros.dds.apply_rmw_network_defaults`, before ``rclpy.init``); the domain is
  ``$ROS_DOMAIN_ID``, as for any ROS 2 process.
- rclpy parses ``--ros-args`` (remaps, ``-p``, ``--params-file``, log levels) itself.
- A managed node (an ``rclpy.lifecycle.LifecycleNode``) started with ``--managed`` (before
  ``--ros-args``) waits unconfigured for a lifecycle manager; without it the process
  configures and activates it at once, as Nav2's ``autostart`` would. After its shutdown
  transition the process stays to answer the manager's next lifecycle requests (Nav2's
  asks ``~/get_state``), up to 2 s (the node's ``may_exit``).
- SIGINT (Ctrl-C, what ``ros2 launch`` sends) and SIGTERM are a normal stop: exit code the
  node's ``exit_code`` (0). Bad input (parameters, arguments, checkpoints, policies, bags, a
  ROS package that is not installed) exits 2 with one line naming it. While it runs,
  :data:`~hdrqn_ros.nodes.STACK_DUMP_SIGNAL` (SIGUSR1) prints every thread's stack.
"""
from __future__ import annotations

import ctypes
import faulthandler
import os
import signal
import sys
import threading
from typing import Callable

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from hdrqn_ros.deploy.errors import PolicyError
from hdrqn_ros.extras import MissingExtra
from hdrqn_ros.dds import INTERFACE_ENV, NetworkConfigError, apply_rmw_network_defaults
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.nodes.parameters import NodeConfigError
from hdrqn_ros.nodes.ros_messages import MissingRosPackage

MANAGED_FLAG = "--managed"
"""The executable argument (before ``--ros-args``) that leaves a managed node to a lifecycle manager."""
STARTUP_ERRORS = (NodeConfigError, NetworkConfigError, PolicyError, MissingExtra, MissingRosPackage, FileNotFoundError)
"""What every node reports as bad input: exit code 2 (a node adds its own to :func:`run_node`)."""
SPIN_STEP_S = 0.05
"""The longest the spin loop waits before it checks whether the node finished or was stopped."""
SHUTDOWN_LIMIT_S = 5.0
"""How long a stopping node waits for rclpy to shut down before it exits without it
(:func:`shut_down_within`): less than the 10 s ``ros2 launch`` allows from SIGINT to SIGKILL;
a normal teardown takes well under a second."""
LARGE_BUFFER_BYTES = 256 * 1024
"""Allocations of this size or more get memory maps of their own in a node process (see
:func:`return_large_buffers_to_the_os`)."""


def return_large_buffers_to_the_os() -> None:
    """Have glibc serve every allocation of :data:`LARGE_BUFFER_BYTES` or more (a sample of MiBs,
    oversized or not, and its copies) from a memory map of its own, unmapped when freed.

    glibc's default raises that threshold to the size of the first such buffer freed, after which
    big buffers come from the heap, and a burst of them (a flood of oversized samples) can leave
    tens of MiB in the heap for the rest of the process (docs/reliability.md). A user's
    ``MALLOC_MMAP_THRESHOLD_`` wins; off glibc this does nothing. Not for the learner: its
    per-update tensors are big and short-lived, and a fresh map for each would cost page faults."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is not None and sys.platform.startswith("linux"):
        mallopt(-3, LARGE_BUFFER_BYTES)  # -3: M_MMAP_THRESHOLD


def make_executor(context: Context):
    """rclpy's C++ ``EventsExecutor`` (a callback costs about a ninth of the single-threaded
    executor's, which rebuilds its Python wait set on every spin); the single-threaded one
    where stderr has no file descriptor (the events executor enables :mod:`faulthandler` on it)
    or rclpy has no events executor. Both run one callback at a time."""
    try:
        from rclpy.experimental import EventsExecutor
        sys.stderr.fileno()
    except (ImportError, AttributeError, ValueError, OSError):
        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


def run_node(make: Callable[..., Node], argv: list[str] | None = None,
             input_errors: tuple[type[Exception], ...] = (), large_buffers_to_os: bool = True) -> int:
    """Run the node ``make(context=...)`` builds in this process until it finishes (its
    ``may_exit()``, else its ``finished`` attribute), Ctrl-C or SIGTERM; then its ``close()``,
    then rclpy's shutdown.
    ``argv``: the process's (default ``sys.argv``); ``input_errors``: the node's own
    bad-input exceptions (exit 2, like :data:`STARTUP_ERRORS`)."""
    if large_buffers_to_os:
        return_large_buffers_to_the_os()
    argv = list(sys.argv if argv is None else argv)
    own_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    managed = MANAGED_FLAG in own_args
    stopped = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stopped.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    dumps_stacks = _print_stacks_on(STACK_DUMP_SIGNAL)
    bad_input = (*STARTUP_ERRORS, *input_errors)
    context = node = executor = None
    exit_code = 1  # until the node says otherwise: an exception is on its way out
    try:
        network = apply_rmw_network_defaults(os.environ.get(INTERFACE_ENV) or None)
        check_domain_id(os.environ.get("ROS_DOMAIN_ID", ""))
        context = Context()
        try:
            rclpy.init(args=argv, context=context, signal_handler_options=SignalHandlerOptions.NO)
        except (RuntimeError, UnicodeError) as exc:  # rcl's argument errors
            raise NodeConfigError(f"rclpy.init rejected the ROS arguments: {exc}") from None
        node = make(context=context)
        if managed and not isinstance(node, LifecycleNode):
            raise NodeConfigError(f"{node.get_name()} has no managed (lifecycle) mode: drop {MANAGED_FLAG}")
        node.get_logger().info(f"middleware rclpy {rclpy_version()}: {network}, domain {context.get_domain_id()}")
        executor = make_executor(context)
        executor.add_node(node)
        if isinstance(node, LifecycleNode) and not managed:
            _bring_up(node)
        elif isinstance(node, LifecycleNode):
            node.get_logger().info(f"managed node: unconfigured (configure, then activate, through "
                                   f"{node.resolve_service_name('~/change_state')})")
        _spin(executor, context, lambda: stopped.is_set() or _may_exit(node))
        exit_code = getattr(node, "exit_code", 0)
    except KeyboardInterrupt:
        exit_code = 130
    except bad_input as exc:
        print(f"error: {exc}", file=sys.stderr)
        exit_code = 2
    finally:
        if node is not None and hasattr(node, "close"):
            node.close()
        if context is not None:
            shut_down_within(lambda: _shutdown(context, executor, node), SHUTDOWN_LIMIT_S, exit_code)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if dumps_stacks:
            faulthandler.unregister(STACK_DUMP_SIGNAL)
    return exit_code


MAX_DOMAIN_ID = 232
"""The largest DDS domain id ROS 2 allows on Linux (its port arithmetic; ROS 2's docs)."""


def check_domain_id(text: str) -> None:
    """``$ROS_DOMAIN_ID`` ("" for unset) is an integer in 0..:data:`MAX_DOMAIN_ID`, else
    :class:`NodeConfigError` naming it (rcl would fail later with a Fast DDS port error)."""
    if text.strip() and not (text.strip().isdigit() and int(text) <= MAX_DOMAIN_ID):
        raise NodeConfigError(f"ROS_DOMAIN_ID must be an integer in 0..{MAX_DOMAIN_ID}, got {text!r}")


def _bring_up(node: LifecycleNode) -> None:
    """Configure and activate an unmanaged lifecycle node; a refused transition is bad input,
    named by the node's ``configure_error`` where it has one."""
    for transition in (node.trigger_configure, node.trigger_activate):
        if transition() != TransitionCallbackReturn.SUCCESS:
            why = getattr(node, "configure_error", "") or "the log says why"
            raise NodeConfigError(f"{node.get_fully_qualified_name()}: {transition.__name__.removeprefix('trigger_')} "
                                  f"failed: {why}")


def _may_exit(node: Node) -> bool:
    """The node's ``may_exit()`` where it has one (a managed node), else its ``finished``."""
    may_exit = getattr(node, "may_exit", None)
    return may_exit() if may_exit is not None else getattr(node, "finished", False)


def rclpy_version() -> str:
    """The installed rclpy's version ("7.1.6" for the Jazzy wheels), or "" when unknown."""
    from importlib.metadata import PackageNotFoundError, version

    for dist in ("ros-rclpy", "rclpy"):
        try:
            return version(dist)
        except PackageNotFoundError:
            continue
    return ""


def _spin(executor, context: Context, until: Callable[[], bool]) -> None:
    """Spin in steps of at most :data:`SPIN_STEP_S` until ``until()`` or the context is shut down."""
    try:
        while context.ok() and not until():
            executor.spin_once(timeout_sec=SPIN_STEP_S)
    except ExternalShutdownException:
        return


def _shutdown(context: Context, executor, node: Node | None) -> None:
    """Stop the executor, destroy the node, shut the context down, then free the executor and
    the context, whose native threads (the events executor's, the DDS participant's) end here,
    while Python runs, not in the interpreter's exit."""
    if executor is not None:
        executor.shutdown()
    if node is not None:
        node.destroy_node()
    rclpy.try_shutdown(context=context)
    context.destroy()


def shut_down_within(shutdown: Callable[[], None], limit_s: float, exit_code: int) -> None:
    """``shutdown()``, bounded: if it has not returned after ``limit_s`` (a DDS library's
    teardown that hangs), print why and every thread's stack to stderr and end the process
    with ``exit_code``. It runs after the node's ``close()``: nothing of the node's own is
    left to save, and peers see it go when its DDS lease runs out."""
    returned = threading.Event()

    def give_up() -> None:
        if returned.wait(limit_s):
            return
        print(f"warning: rclpy did not shut down within {limit_s:g} s; every thread's stack follows; exiting with "
              f"code {exit_code} without it", file=sys.stderr, flush=True)
        try:
            faulthandler.dump_traceback(all_threads=True)
        except (AttributeError, ValueError, OSError):  # stderr captured in memory
            pass
        sys.stdout.flush()
        os._exit(exit_code)

    watchdog = threading.Thread(target=give_up, name="shutdown-watchdog", daemon=True)
    watchdog.start()
    try:
        shutdown()
    finally:
        returned.set()
        # joined before the interpreter's exit: Python 3.12 ends a thread still waking up then
        # (pthread_exit), which can abort a process that has torch loaded
        watchdog.join()


def _print_stacks_on(sig: int) -> bool:
    """On ``sig`` print every thread's Python stack to stderr and go on (``kill -USR1 PID``
    shows where a node is stuck); False where stderr has no file descriptor."""
    try:
        faulthandler.register(sig, all_threads=True)
    except (AttributeError, ValueError, OSError):  # stderr captured in memory
        return False
    return True
