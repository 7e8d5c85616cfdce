"""Optional dependencies (the pip extras of ``setup.py``): a clear error naming the extra
and the command that installs it, instead of a ``ModuleNotFoundError`` traceback."""
from __future__ import annotations

import importlib

EXTRAS = {"deploy": ("onnxruntime", "onnx"), "cluster": ("ray",), "ros": ("rclpy",)}
"""Each extra's importable modules (what ``pip install 'hdrqn_ros[EXTRA]'`` brings)."""


class MissingExtra(ValueError):
    """An optional dependency is not installed; the message names it and its install command.
    (A ``ValueError``: the command line and the nodes report it as bad input, exit code 2.)"""


def install_command(extra: str) -> str:
    return f"pip install 'hdrqn_ros[{extra}]'"


def require(extra: str, what: str, modules: tuple[str, ...] | None = None) -> None:
    """Import ``modules`` (default: all of the extra's); :class:`MissingExtra` saying that
    ``what`` needs them, and how to install them, when one is missing."""
    for module in modules or EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise MissingExtra(f"{what} needs {module}, which is not installed ({exc}): "
                               f"{install_command(extra)}") from None
