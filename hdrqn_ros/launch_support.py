"""What both launch files share: package paths, the params file's shared section, and
typed launch arguments (errors name the argument). Imported by ``launch/*.launch.py``;
needs ROS 2's ``launch`` only inside the functions that take a launch context."""
from __future__ import annotations

from pathlib import Path

import yaml

PACKAGE = "hdrqn_ros"
HIERARCHICAL_ALGOS = ("hdrqn-v2", "hdrqn-v1", "hdqn")
"""Agents with a meta-controller and an internal critic (``ALGO_SPECS[algo].hierarchical``)."""
ALGOS = HIERARCHICAL_ALGOS + ("drqn", "dqn")
DEFAULT_ALGO = "hdrqn-v2"
"""The nodes' own default ``algo`` (``hdrqn_ros.nodes.common.ENV_DEFAULTS``)."""
SHARED_ARGS = ("algo", "env", "view")
"""String launch arguments that, when not empty, override the ``/**`` parameter of that name."""


def share_dir() -> Path:
    """The package's share directory; the source tree when the package is not installed."""
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        return Path(get_package_share_directory(PACKAGE))
    except (PackageNotFoundError, OSError):  # OSError: no AMENT_PREFIX_PATH (no sourced workspace)
        return Path(__file__).resolve().parents[1]


def shared_file_parameters(params_file: str) -> dict:
    """The ``/**`` parameters of a ROS 2 params file (``{}`` if it has none)."""
    try:
        doc = yaml.safe_load(Path(params_file).read_text(encoding="utf-8")) or {}
    except OSError as exc:
        raise RuntimeError(f"params_file: cannot read {params_file}: {exc.strerror or exc}") from None
    section = doc.get("/**", {}) if isinstance(doc, dict) else {}
    params = section.get("ros__parameters", {}) if isinstance(section, dict) else {}
    return params if isinstance(params, dict) else {}


def arg(context, name: str) -> str:
    """A launch argument's text."""
    from launch.substitutions import LaunchConfiguration

    return LaunchConfiguration(name).perform(context).strip()


def int_arg(context, name: str, minimum: int) -> int | None:
    text = arg(context, name)
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        raise RuntimeError(f"launch argument {name} must be an integer, got {text!r}") from None
    if value < minimum:
        raise RuntimeError(f"launch argument {name} must be >= {minimum}, got {value}")
    return value


def bool_arg(context, name: str) -> bool:
    text = arg(context, name).lower()
    if text in ("true", "1", "yes", "on"):
        return True
    if text in ("false", "0", "no", "off"):
        return False
    raise RuntimeError(f"launch argument {name} must be true or false, got {text!r}")


def float_arg(context, name: str) -> float:
    text = arg(context, name)
    try:
        return float(text)
    except ValueError:
        raise RuntimeError(f"launch argument {name} must be a number, got {text!r}") from None
