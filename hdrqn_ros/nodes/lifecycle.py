"""The base of the nodes a lifecycle manager (Nav2's) can drive: ROS 2's node state machine.

- *configure* (unconfigured -> inactive): :meth:`ManagedNode.build` reads the parameters,
  loads and checks the policy or checkpoint and the tables, and creates the topics. A bad
  value fails the transition with the reason in the log; the node stays unconfigured, and
  its parameters can be corrected with ``ros2 param set`` before the next configure.
- *activate* (inactive -> active): :meth:`~ManagedNode.start`; the node acts. Activated
  through ``~/change_state`` (by a lifecycle manager), it also opens its side of a bond
  (:mod:`hdrqn_ros.nodes.bond`): heartbeats that Nav2's manager waits for.
- *deactivate* (active -> inactive): :meth:`~ManagedNode.stop` (a driving node publishes
  the zero command); steps that arrive are ignored, and the diagnostics say inactive. The
  bond is broken.
- *cleanup* (inactive -> unconfigured): :meth:`~ManagedNode.teardown`, then every
  publisher, subscription, timer, service and client configure made is destroyed.
- *shutdown* (any -> finalized): what is up is brought down, and the process exits (code 0)
  once the calls a manager makes next are answered: Nav2's asks ``~/get_state`` right after
  (:meth:`ManagedNode.may_exit`).

Started without ``--managed`` the process configures and activates the node itself
(:func:`hdrqn_ros.nodes.process.run_node`). Parameters are declared once, when the node is
made: the not-live ones change only while it is unconfigured.
"""
from __future__ import annotations

import time
import traceback
from typing import Any

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from hdrqn_ros.nodes.bond import Bond
from hdrqn_ros.nodes.parameters import Param, declare_parameters
from hdrqn_ros.nodes.ros_messages import MissingRosPackage

FINALIZED_QUIET_S = 0.25
"""After a shutdown through ``~/change_state``, once ``~/get_state`` has been answered, the
process exits when no lifecycle request came for this long."""
FINALIZED_LINGER_S = 2.0
"""The longest a finalized node stays to answer lifecycle requests (a client that never asks
``~/get_state``, such as ``ros2 lifecycle set``, waits for its process this long)."""


class ManagedNode(LifecycleNode):
    """A lifecycle node with parameters ``parameters`` (``{name: Param}``); subclasses
    implement :meth:`build` (raise one of ``bad_input`` on a value they cannot use),
    :meth:`start`, :meth:`stop` and :meth:`teardown`, and may react to a live parameter in
    :meth:`on_live_parameter`. ``params`` holds the values read at the last configure
    (live ones kept current); ``active`` whether the node acts; ``finished`` becomes true
    at shutdown (the process exits with ``exit_code`` when :meth:`may_exit`); ``bond`` its
    side of the bond with the manager that activated it (``None`` when it has none)."""

    bad_input: tuple[type[Exception], ...] = (ValueError,)
    """What :meth:`build` raises for a value it cannot use: a failed configure, not an error."""

    def __init__(self, name: str, parameters: dict[str, Param], **kwargs):
        super().__init__(name, **kwargs)
        self.parameter_table = parameters
        self.configured = self.active = self.finished = False
        self.exit_code = 0
        self.configure_error = ""  # why the last configure failed
        self.params: dict[str, Any] = declare_parameters(self, parameters, apply=self._live_parameter,
                                                         configurable=lambda: not self.configured)
        self._made_before: dict[str, set] = {}
        self.bond: Bond | None = None
        self._by_manager = False  # the transition running came through ~/change_state
        self._finalized_at: float | None = None  # monotonic time of a shutdown through ~/change_state
        self._last_request = 0.0  # monotonic time of the last lifecycle service request
        self._state_asked_since_shutdown = False
        self._refuse_transitions_not_allowed()
        self._note_lifecycle_requests()

    # -- what a node implements ------------------------------------------------------------
    def build(self) -> None:
        """Make the node from ``self.params``: its core objects, topics and timers."""

    def start(self) -> None:
        """Begin acting."""

    def stop(self) -> None:
        """Stop acting (a driving node's zero command)."""

    def teardown(self) -> None:
        """Release what :meth:`build` made that is not a ROS entity (destroyed for it)."""

    def on_live_parameter(self, name: str, value: Any) -> None:
        """A live parameter changed (``params`` already holds ``value``)."""

    # -- the state machine ---------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.params = {name: self.get_parameter(name).value for name in self.parameter_table}
        self.configure_error = ""
        self._made_before = self._entities()
        try:
            self.build()
        except self.bad_input as exc:
            self.configure_error = str(exc)
            self.get_logger().error(f"configure failed, the node stays unconfigured: {exc}")
            self._destroy_made()
            return TransitionCallbackReturn.FAILURE
        except Exception:
            self.get_logger().error(f"configure failed:\n{traceback.format_exc()}")
            self._destroy_made()
            return TransitionCallbackReturn.ERROR
        self.configured = True
        self.get_logger().info("configure: done")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.start()
        self.active = True
        if self._by_manager:
            self._open_bond()
        self.get_logger().info("activate: done")
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        self.stop()
        if self.bond is not None:
            self.bond.end()
        self.get_logger().info("deactivate: done")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._bring_down()
        self.get_logger().info("cleanup: done")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._bring_down()
        self.finished = True
        if self._by_manager:
            self._finalized_at = time.monotonic()
            self.get_logger().info(f"shutdown: done; the process exits once the lifecycle requests that follow are "
                                   f"answered (at most {FINALIZED_LINGER_S:g} s)")
        else:
            self.get_logger().info("shutdown: done")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._bring_down()
        return TransitionCallbackReturn.SUCCESS

    def close(self) -> None:
        """The process stops: stop acting and release everything (the zero command goes out,
        the bond is broken)."""
        self._bring_down()

    def may_exit(self) -> bool:
        """Whether the process may end: :attr:`finished`, and after a shutdown through
        ``~/change_state`` a ``~/get_state`` answered and :data:`FINALIZED_QUIET_S` without a
        lifecycle request since, or :data:`FINALIZED_LINGER_S` passed."""
        if not self.finished or self._finalized_at is None:
            return self.finished
        now = time.monotonic()
        return (now - self._finalized_at >= FINALIZED_LINGER_S
                or (self._state_asked_since_shutdown and now - self._last_request >= FINALIZED_QUIET_S))

    def _bring_down(self) -> None:
        if self.active:
            self.active = False
            self.stop()
        if self.bond is not None:
            self.bond.close()
            self.bond = None
        if self.configured:
            self.configured = False
            self.teardown()
            self._destroy_made()

    def _open_bond(self) -> None:
        """This activation's side of the bond (the previous one's topics are released first)."""
        if self.bond is not None:
            self.bond.close()
            self.bond = None
        try:
            self.bond = Bond(self, self.get_name())
        except MissingRosPackage as exc:
            self.get_logger().warning(f"no bond heartbeat for the lifecycle manager: {exc}. A Nav2 lifecycle "
                                      "manager brings this node up only with bond_timeout: 0.0")

    def _live_parameter(self, name: str, value: Any) -> None:
        self.params[name] = value
        self.on_live_parameter(name, value)

    # -- entities configure made -------------------------------------------------------------
    _KINDS = {"publishers": "destroy_publisher", "subscriptions": "destroy_subscription",
              "timers": "destroy_timer", "services": "destroy_service", "clients": "destroy_client"}

    def _entities(self) -> dict[str, set]:
        return {kind: set(getattr(self, kind)) for kind in self._KINDS}

    def _destroy_made(self) -> None:
        """Destroy every entity made since the last configure began."""
        for kind, destroy in self._KINDS.items():
            for entity in set(getattr(self, kind)) - self._made_before.get(kind, set()):
                getattr(self, destroy)(entity)

    def _refuse_transitions_not_allowed(self) -> None:
        """A transition not allowed from the current state is refused (``success: false``,
        logged), where rclpy would raise out of the executor for a transition given by id. A
        transition asked for through the service runs with ``_by_manager`` set."""
        service = self._service_change_state
        change_state = service.callback

        def refuse_what_is_not_allowed(request, response):
            self._by_manager = True
            try:
                return change_state(request, response)
            except _rclpy.RCLError as exc:
                label = self._state_machine.current_state[1]
                self.get_logger().warning(f"transition {request.transition.label or request.transition.id} refused "
                                          f"in state {label}: {exc}")
                response.success = False
                return response
            finally:
                self._by_manager = False

        service.callback = refuse_what_is_not_allowed

    def _note_lifecycle_requests(self) -> None:
        """Each lifecycle service request stamps ``_last_request``; a ``~/get_state`` after a
        shutdown is noted (what :meth:`may_exit` waits for)."""
        services = (self._service_change_state, self._service_get_state, self._service_get_available_states,
                    self._service_get_available_transitions, self._service_get_transition_graph)
        for service in services:
            def noted(request, response, answer=service.callback, is_get_state=service is self._service_get_state):
                self._last_request = time.monotonic()
                if is_get_state and self._finalized_at is not None:
                    self._state_asked_since_shutdown = True
                return answer(request, response)

            service.callback = noted
