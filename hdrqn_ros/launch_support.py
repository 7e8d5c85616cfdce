"""What both launch files share: package paths, the params file's shared section, and
typed launch arguments (errors name the argument). Imported by ``launch/*.launch.py``;
needs ROS 2's ``launch`` only inside the functions that take a launch context."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import yaml

from hdrqn_ros.agents.specs import ALGO_SPECS

PACKAGE = "hdrqn_ros"
ALGOS = tuple(ALGO_SPECS)
HIERARCHICAL_ALGOS = tuple(algo for algo, spec in ALGO_SPECS.items() if spec.hierarchical)
"""Agents with a meta-controller and an internal critic."""
DEFAULT_ALGO = ALGOS[0]
"""The nodes' own default ``algo`` (``hdrqn_ros.nodes.graph_parameters.ENV_PARAMETERS``)."""
NOT_RESTARTED = {0: "it finished or was stopped", 2: "a configuration error, which a restart cannot fix"}
"""Node exit codes a launch file does not restart after, and what they mean; any other exit is a crash."""
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


def restarted_node(make_node: Callable[[], object], delay_s: float) -> list:
    """Launch actions: ``make_node()`` (a ``launch_ros`` Node, made anew for each start) and,
    each time it crashes (an exit code not in :data:`NOT_RESTARTED`), a new one after
    ``delay_s``; an exit in :data:`NOT_RESTARTED` is logged and left alone."""
    from launch.actions import LogInfo, RegisterEventHandler, TimerAction
    from launch.event_handlers import OnProcessExit

    node = make_node()

    def on_exit(event, context):
        code = event.returncode
        if code in NOT_RESTARTED or context.is_shutdown:
            why = NOT_RESTARTED.get(code, "the launch is shutting down")
            return [LogInfo(msg=f"{event.process_name} exited with {code} ({why}): not restarting it")]
        return [LogInfo(msg=f"{event.process_name} exited with {code}: restarting it in {delay_s:g} s"),
                TimerAction(period=delay_s, actions=restarted_node(make_node, delay_s))]

    return [node, RegisterEventHandler(OnProcessExit(target_action=node, on_exit=on_exit))]
