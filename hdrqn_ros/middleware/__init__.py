"""The middleware port and its backends; :func:`open_middleware` picks one."""
from __future__ import annotations

import os

from hdrqn_ros.middleware.port import (DEFAULT_QOS, LATCHED_QOS, Middleware, Node, ParameterError, QoS,
                                       RosArgsError)

BACKEND_ENV = "HDRQN_MIDDLEWARE"
"""``auto`` (default: rclpy when importable, else Cyclone DDS), ``rclpy`` or ``cyclone``."""


def open_middleware(argv: list[str] | None = None, backend: str | None = None) -> Middleware:
    """The middleware for this process, configured from ``argv``'s ``--ros-args``."""
    backend = (backend or os.environ.get(BACKEND_ENV) or "auto").lower()
    if backend not in ("auto", "rclpy", "cyclone"):
        raise ValueError(f"{BACKEND_ENV} must be auto, rclpy or cyclone, got {backend!r}")
    if backend in ("auto", "rclpy"):
        from hdrqn_ros.middleware.rclpy_backend import RclpyMiddleware, rclpy_available

        if rclpy_available():
            return RclpyMiddleware(argv)
        if backend == "rclpy":
            raise ImportError("HDRQN_MIDDLEWARE=rclpy but rclpy cannot be imported: source a ROS 2 Jazzy setup first")
    from hdrqn_ros.middleware.cyclone import CycloneMiddleware

    return CycloneMiddleware(argv)


__all__ = ["open_middleware", "Middleware", "Node", "QoS", "DEFAULT_QOS", "LATCHED_QOS",
           "ParameterError", "RosArgsError", "BACKEND_ENV"]
