"""When a robot's episodes run: one per ``start_episode`` request, or back to back with
``autostart``; ``stop_episode`` ends the running one at its next step (truncated) and
starts none until the next ``start_episode``. The robot environment node's
``~/start_episode`` and ``~/stop_episode`` services answer with these. No ROS.
"""
from __future__ import annotations


class EpisodeRequests:
    """The episode requests of one robot; ``auto``: episodes back to back (``autostart``)."""

    def __init__(self, autostart: bool):
        self.start_requested = False  # one episode asked for, not started yet
        self.stop_requested = False  # the running episode to end at its next step
        self.auto = bool(autostart)

    @property
    def wanted(self) -> bool:
        """Whether an episode should start once none runs and the inputs are ready."""
        return self.start_requested or self.auto

    def start(self, autostart: bool, running: bool, finished: bool, episode: int) -> tuple[bool, str]:
        """A ``start_episode`` request (``episode``: the latest episode's number, -1 before the
        first): ``(accepted, why)``; with ``autostart`` episodes run back to back again."""
        if finished or running:
            return False, "finished: max_episodes reached" if finished else \
                f"episode {episode} is running: start_episode starts one when none runs"
        self.start_requested, self.stop_requested, self.auto = True, False, bool(autostart)
        return True, f"episode {episode + 1} starts when the inputs are fresh" + \
            (" (autostart: then back to back)" if self.auto else "")

    def stop(self, running: bool, episode: int) -> tuple[bool, str]:
        """A ``stop_episode`` request: ``(True, what happens)``."""
        self.start_requested, self.auto, self.stop_requested = False, False, running
        return True, f"episode {episode} ends at the next step" if running else "no episode running"

    def started(self) -> None:
        self.start_requested = False

    def ended(self) -> None:
        """The running episode ended or was abandoned."""
        self.stop_requested = False
