"""The learner node's own recording: every message it takes from the groups, written to a
bag as received (CDR bytes), and the bags its earlier lives wrote (``<record>``,
``<record>-restart<k>``), repaired, for a restarted learner to refill its replay from."""
from __future__ import annotations

import logging
from contextlib import suppress
from pathlib import Path
from typing import Any, Callable

from hdrqn_ros.recording.bag import BagError, repair_bag
from hdrqn_ros.recording.transitions import BagRecorder


class GraphRecorder:
    """Writes the messages the learner receives to a bag, as received: ``to_cdr(msg)``, the
    middleware's serialization. Split every ``split_mb`` MB (> 0); ``logger``: %-style."""

    def __init__(self, path: str, cfg, split_mb: float, to_cdr: Callable[[Any], bytes], logger: logging.Logger):
        target, k = Path(path), 0
        while target.exists():  # a restarted learner: keep the earlier bag, start a new one
            k += 1
            target = Path(f"{path}-restart{k}")
        self.to_cdr, self.logger = to_cdr, logger
        self.bag = BagRecorder(target, cfg, "learner node", split_bytes=int(split_mb * 2**20))
        self.failed = False
        logger.info("recording the groups' messages to %s", target)

    def add_group(self, namespace: str, topics: list[str]) -> dict[str, int]:
        return self.bag.add_group(namespace, topics)

    def sync(self) -> bool:
        """End the current chunk and hand it to the OS, so a killed learner loses none of the
        messages received so far (``hdrqn bag repair`` keeps complete chunks). False when
        recording has stopped."""
        if self.failed:
            return False
        try:
            self.bag.sync()
        except BagError as exc:
            self._stop(exc)
        return not self.failed

    def recording(self, connection: int, handler: Callable[[Any], None]) -> Callable[[Any], None]:
        """``handler``, after writing each message to the bag's ``connection``."""
        def record_then_handle(msg) -> None:
            if not self.failed:
                try:
                    self.bag.write(connection, self.to_cdr(msg))
                except BagError as exc:
                    self._stop(exc)
            handler(msg)
        return record_then_handle

    def _stop(self, exc: BagError) -> None:
        """Stop recording (disk full, permissions), keep training."""
        self.failed = True
        self.logger.error("recording stopped: %s", exc)

    def close(self) -> None:
        if not self.failed:
            with suppress(BagError):
                self.bag.close()


def earlier_recordings(record: str, logger: logging.Logger) -> list[str]:
    """The bags a learner recording to ``record`` wrote in its earlier lives (``record``,
    ``record-restart<k>``, in order), each repaired first when a kill left it unfinished."""
    bags, k = [], 0
    while Path(path := record if k == 0 else f"{record}-restart{k}").exists():
        report = repair_bag(path)
        if report.repaired:
            logger.warning("repaired %s: %d messages recovered, %d bytes dropped", path,
                           report.messages_recovered, report.bytes_dropped)
        bags.append(path)
        k += 1
    return bags
