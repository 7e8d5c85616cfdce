"""What a robot step waits for (``robot_environment``): a wait that lasts is reported.

A step, or an episode's start, that cannot be taken yet says why (:meth:`StepWaits.wait`);
a wait that has lasted ``WAIT_REPORTED_S`` is logged (WARN, again every
``WAIT_REPEATED_S``) and is the node's ``/diagnostics`` WARN (:meth:`StepWaits.lasting`);
the next step clears it. Wall seconds (``time.monotonic``): a simulated clock may stand still.
"""
from __future__ import annotations

import time

WAIT_REPORTED_S, WAIT_REPEATED_S = 2.0, 10.0
"""A wait is reported once it lasts this long (diagnostics WARN, log), and logged again this often."""


class StepWaits:
    """The current wait of a robot step and of its pose; ``logger``: the node's (``warning``)."""

    def __init__(self, logger):
        self.logger = logger
        self.since: float | None = None  # wall time the current wait began
        self.logged, self.reason = 0.0, ""
        self.pose_since: float | None = None  # wall time the next step began to wait for its pose

    def wait(self, why: str) -> None:
        """Report a wait that lasts (after ``WAIT_REPORTED_S``, then every ``WAIT_REPEATED_S``), not a momentary one."""
        now = time.monotonic()
        self.reason = why
        if self.since is None:
            self.since = now
        elif now - self.since >= WAIT_REPORTED_S and now - self.logged >= WAIT_REPEATED_S:
            self.logged = now
            self.logger.warning(f"waiting {now - self.since:.0f} s {why}")

    def clear(self) -> None:
        """No wait now (a new wait starts its clock again)."""
        self.since = None

    def new_step(self) -> None:
        """A step was taken: no wait, and the next step's pose wait has not begun."""
        self.since = self.pose_since = None

    def pose_waited_s(self) -> float:
        """Wall seconds the next step has waited for its pose (its clock starts at the first call)."""
        if self.pose_since is None:
            self.pose_since = time.monotonic()
        return time.monotonic() - self.pose_since

    def lasting(self) -> str:
        """``"waiting N s <why>"`` for a wait over ``WAIT_REPORTED_S``, else ``""``."""
        waited = 0.0 if self.since is None else time.monotonic() - self.since
        return f"waiting {waited:.0f} s {self.reason}" if waited > WAIT_REPORTED_S else ""
