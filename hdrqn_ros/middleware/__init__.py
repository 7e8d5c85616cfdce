"""The middleware port and its backends; :func:`open_middleware` picks one."""
from __future__ import annotations

import os

from hdrqn_ros.middleware.port import (DEFAULT_QOS, LATCHED_QOS, BackendError, Middleware, Node, ParameterError,
                                       ParameterRule, QoS, RosArgsError)

BACKEND_ENV = "HDRQN_MIDDLEWARE"
"""``auto`` (default: rclpy when importable, else Cyclone DDS), ``rclpy`` or ``cyclone``."""
BACKENDS = ("auto", "rclpy", "cyclone")


def chosen_backend(backend: str | None = None) -> str:
    """``rclpy`` or ``cyclone``: ``backend`` (else ``$HDRQN_MIDDLEWARE``, else ``auto``) resolved;
    a :class:`BackendError` naming what to install when rclpy is asked for and missing."""
    from hdrqn_ros.middleware.rclpy_backend import RCLPY_INSTALL_HINT, rclpy_available, rclpy_import_error

    requested = (backend or os.environ.get(BACKEND_ENV) or "auto").strip().lower()
    if requested not in BACKENDS:
        raise BackendError(f"middleware must be one of {', '.join(BACKENDS)} (--middleware or ${BACKEND_ENV}), "
                           f"got {requested!r}")
    if requested == "cyclone" or (requested == "auto" and not rclpy_available()):
        return "cyclone"
    if not rclpy_available():
        raise BackendError(f"middleware rclpy was asked for, but rclpy cannot be imported ({rclpy_import_error()}); "
                           f"install it: {RCLPY_INSTALL_HINT}")
    return "rclpy"


def open_middleware(argv: list[str] | None = None, backend: str | None = None) -> Middleware:
    """The middleware for this process (:func:`chosen_backend`), configured from ``argv``'s ``--ros-args``."""
    if chosen_backend(backend) == "rclpy":
        from hdrqn_ros.middleware.rclpy_backend import RclpyMiddleware

        return RclpyMiddleware(argv)
    from hdrqn_ros.middleware.cyclone import CycloneMiddleware

    return CycloneMiddleware(argv)


__all__ = ["open_middleware", "chosen_backend", "Middleware", "Node", "QoS", "DEFAULT_QOS", "LATCHED_QOS",
           "BackendError", "ParameterError", "ParameterRule", "RosArgsError", "BACKEND_ENV", "BACKENDS"]
