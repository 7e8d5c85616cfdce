"""Rate-limited warnings for input that is rejected again and again (a flood of bad messages).

Like rclpy's ``throttle_duration_sec``, after a short burst: the first :data:`BURST`
rejections are logged as they come (so a few different problems all show), then at most
one line per ``period_s`` seconds, each with the count so far, so a flood costs a few lines
and the count is never lost."""
from __future__ import annotations

import logging
import time

THROTTLE_PERIOD_S = 5.0
BURST = 10


class Throttle:
    """One kind of rejection (``what``, e.g. "rejected a message on /action") on ``logger``."""

    def __init__(self, logger: logging.Logger, what: str, period_s: float = THROTTLE_PERIOD_S):
        self.logger, self.what, self.period_s = logger, what, period_s
        self.count = 0
        self._last_s = -float("inf")

    def warn(self, why: object) -> None:
        """Count one rejection; log it within the burst, or if no line was logged for ``period_s``."""
        self.count += 1
        now = time.monotonic()
        if self.count <= BURST or now - self._last_s >= self.period_s:
            self._last_s = now
            self.logger.warning("%s: %s (%d so far)", self.what, why, self.count)
