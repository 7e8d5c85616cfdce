"""Managed (lifecycle) mode of the nodes a robot runs: ``--managed`` before ``--ros-args``.

ROS 2's node state machine, as Nav2's lifecycle manager drives it through the node's
``~/change_state`` service (rclpy backend only):

- *configure* (unconfigured -> inactive): the node object is built: parameters read, the
  policy or checkpoint and the tables loaded and checked, topics created. A bad value
  fails the transition with the reason in the log; the node stays unconfigured, and its
  parameters can be corrected with ``ros2 param set`` before the next configure.
- *activate* (inactive -> active): the node acts.
- *deactivate* (active -> inactive): a driving sub-controller publishes the zero command;
  the node stops acting (steps that arrive are ignored) and its diagnostics say inactive.
- *cleanup* (inactive -> unconfigured): everything configure made is released.
- *shutdown* (any -> finalized): released, and the process exits (code 0).

The node objects are unchanged apart from ``activate()`` / ``deactivate()`` and an
``active`` flag; configure builds one on a middleware whose ``create_node`` hands out the
managed node.
"""
from __future__ import annotations

from typing import Any, Callable

from hdrqn_ros.middleware import Middleware, Node

MANAGED_FLAG = "--managed"
"""The executable argument (before ``--ros-args``) that runs a node managed."""


class _ManagedNodeOnly:
    """What a node object's constructor gets in managed mode: ``create_node`` returns the
    managed node (whatever name it asks for; it is the node's own)."""

    def __init__(self, node: Node):
        self.node = node

    def create_node(self, name: str, namespace: str = "") -> Node:
        return self.node


class ManagedNode:
    """Hosts a node object (``build(middleware) -> object``) as a managed node named ``name``.

    ``finished`` / ``exit_code`` are what :func:`~hdrqn_ros.nodes.common.run_node` spins on:
    true after shutdown, or when the node object finished on its own."""

    def __init__(self, mw: Middleware, name: str, build: Callable[[Any], Any],
                 input_errors: tuple[type[Exception], ...]):
        """``input_errors``: the exceptions that mean bad input (a failed configure, not a crash)."""
        self.build, self.input_errors = build, input_errors
        self.node = mw.create_managed_node(name, self)
        self.built: Any = None
        self.shut_down = False
        self.node.logger.info("managed node: unconfigured (configure, then activate, through %s)",
                              self.node.resolve_topic("~/change_state"))

    @property
    def finished(self) -> bool:
        return self.shut_down or bool(getattr(self.built, "finished", False))

    @property
    def exit_code(self) -> int:
        return getattr(self.built, "exit_code", 0)

    def on_configure(self) -> str:
        try:
            built = self.build(_ManagedNodeOnly(self.node))
        except self.input_errors as exc:
            self.node.release()
            return str(exc) or type(exc).__name__
        built.active = False
        self.built = built
        return ""

    def on_activate(self) -> None:
        self.built.activate()

    def on_deactivate(self) -> None:
        self.built.deactivate()

    def on_cleanup(self) -> None:
        self.close()

    def on_shutdown(self) -> None:
        self.close()
        self.shut_down = True

    def close(self) -> None:
        """Deactivate (zero command) and release what configure made; nothing when unconfigured."""
        if self.built is None:
            return
        built, self.built = self.built, None
        if getattr(built, "active", False):
            built.deactivate()
        if hasattr(built, "close"):
            built.close()
        self.node.release()
