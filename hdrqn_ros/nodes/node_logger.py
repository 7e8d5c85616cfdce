"""A :class:`logging.Logger` whose records go to a node's rclpy logger (console, ``/rosout``).

The protocol layer (:mod:`hdrqn_ros.protocol`) and :class:`~hdrqn_ros.throttle.Throttle`
import no ROS and log through :mod:`logging`; a node hands them this logger.
"""
from __future__ import annotations

import logging

from rclpy.node import Node


class _RclpyHandler(logging.Handler):
    """Forwards formatted records to an rclpy (rcutils) logger."""

    def __init__(self, ros_logger) -> None:
        super().__init__(logging.DEBUG)
        self._ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        """One call site per severity: rclpy refuses a severity change at one call site."""
        try:
            text, level, ros = self.format(record), record.levelno, self._ros_logger  # format: args, tracebacks
            if level >= logging.CRITICAL:
                ros.fatal(text)
            elif level >= logging.ERROR:
                ros.error(text)
            elif level >= logging.WARNING:
                ros.warning(text)
            elif level >= logging.INFO:
                ros.info(text)
            else:
                ros.debug(text)
        except Exception:
            self.handleError(record)


def python_logger(node: Node) -> logging.Logger:
    """A logger for ``node`` outside :mod:`logging`'s registry: nodes of equal names do not
    share handlers, and records reach rcutils once, not also through the root logger."""
    logger = logging.Logger(f"hdrqn.{node.get_logger().name}", logging.DEBUG)
    logger.propagate = False
    logger.addHandler(_RclpyHandler(node.get_logger()))
    return logger
