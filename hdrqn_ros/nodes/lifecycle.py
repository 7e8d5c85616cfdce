"""The base of the nodes a lifecycle manager (Nav2's) can drive: ROS 2's node state machine.

- *configure* (unconfigured -> inactive): :meth:`ManagedNode.build` reads the parameters,
  loads and checks the policy or checkpoint and the tables, and creates the topics. A bad
  value fails the transition with the reason in the log; the node stays unconfigured, and
  its parameters can be corrected with ``ros2 param set`` before the next configure.
- *activate* (inactive -> active): :meth:`~ManagedNode.start`; the node acts.
- *deactivate* (active -> inactive): :meth:`~ManagedNode.stop` (a driving node publishes
  the zero command); steps that arrive are ignored, and the diagnostics say inactive.
- *cleanup* (inactive -> unconfigured): :meth:`~ManagedNode.teardown`, then every
  publisher, subscription, timer, service and client configure made is destroyed.
- *shutdown* (any -> finalized): what is up is brought down, and the process exits (code 0).

Started without ``--managed`` the process configures and activates the node itself
(:func:`hdrqn_ros.nodes.process.run_node`). Parameters are declared once, when the node is
made: the not-live ones change only while it is unconfigured.
"""
from __future__ import annotations

import traceback
from typing import Any

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from hdrqn_ros.nodes.parameters import Param, declare_parameters


class ManagedNode(LifecycleNode):
    """A lifecycle node with parameters ``parameters`` (``{name: Param}``); subclasses
    implement :meth:`build` (raise one of ``bad_input`` on a value they cannot use),
    :meth:`start`, :meth:`stop` and :meth:`teardown`, and may react to a live parameter in
    :meth:`on_live_parameter`. ``params`` holds the values read at the last configure
    (live ones kept current); ``active`` whether the node acts; ``finished`` becomes true
    at shutdown (the process exits with ``exit_code``)."""

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
        self._refuse_transitions_not_allowed()

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
        self.get_logger().info("activate: done")
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.active = False
        self.stop()
        self.get_logger().info("deactivate: done")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._bring_down()
        self.get_logger().info("cleanup: done")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._bring_down()
        self.finished = True
        self.get_logger().info("shutdown: done")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._bring_down()
        return TransitionCallbackReturn.SUCCESS

    def close(self) -> None:
        """The process stops: stop acting and release everything (the zero command goes out)."""
        self._bring_down()

    def _bring_down(self) -> None:
        if self.active:
            self.active = False
            self.stop()
        if self.configured:
            self.configured = False
            self.teardown()
            self._destroy_made()

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
        logged), where rclpy would raise out of the executor for a transition given by id."""
        service = self._service_change_state
        change_state = service.callback

        def refuse_what_is_not_allowed(request, response):
            try:
                return change_state(request, response)
            except _rclpy.RCLError as exc:
                label = self._state_machine.current_state[1]
                self.get_logger().warning(f"transition {request.transition.label or request.transition.id} refused "
                                          f"in state {label}: {exc}")
                response.success = False
                return response

        service.callback = refuse_what_is_not_allowed
