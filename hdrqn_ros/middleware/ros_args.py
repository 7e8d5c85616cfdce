"""ROS 2 command-line arguments and parameter files, for the backend without rclpy.

Understands what ``ros2 run`` and launch pass to a node (the rcl argument syntax):
``--ros-args -p name:=value --params-file FILE -r from:=to -r node:from:=to
-r __node:=name -r __ns:=/ns --log-level LEVEL --enclave E --``. Parameter files are the
standard ``node_name: {ros__parameters: {...}}`` YAML; keys may be ``/**``, a node name,
``/ns/node`` or a wildcard pattern; nested dictionaries become dotted parameter names.
Values use YAML syntax, as in ROS 2 (``-p rate:=5`` is an integer, ``-p rate:=5.0`` a
double, ``-p names:=[a,b]`` a string array).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import yaml

from hdrqn_ros.middleware.port import ParameterError, RosArgsError
from hdrqn_ros.yaml_files import read_mapping, safe_load

_FLAGS_WITH_VALUE = {"-p", "--param", "-r", "--remap", "--params-file", "--log-level", "-e", "--enclave"}
_FLAGS_ALONE = {"--disable-rosout-logs", "--disable-stdout-logs", "--disable-external-lib-logs",
                "--enable-rosout-logs", "--enable-stdout-logs"}


@dataclass
class RosArgs:
    """Parsed ``--ros-args``. ``params`` hold (node pattern, name, value) in the order given:
    later entries win, as in rcl."""

    params: list[tuple[str, str, Any]] = field(default_factory=list)
    remaps: list[tuple[str | None, str, str]] = field(default_factory=list)
    node_name: str | None = None
    namespace: str | None = None
    log_level: str | None = None

    def parameters_for(self, node_name: str, namespace: str) -> dict[str, Any]:
        """The parameter overrides that apply to the node ``namespace/node_name``."""
        fqn = f"{namespace.rstrip('/')}/{node_name}"
        out: dict[str, Any] = {}
        for pattern, name, value in self.params:
            if pattern == "" or _node_matches(pattern, node_name, fqn):
                out[name] = value
        return out

    def remap(self, node_name: str, resolved_topic: str, namespace: str) -> str:
        """Apply ``-r`` rules to an already resolved (fully qualified) topic name."""
        for node, src, dst in self.remaps:
            if node is not None and node != node_name:
                continue
            if resolve_name(src, namespace, node_name) == resolved_topic:
                return resolve_name(dst, namespace, node_name)
        return resolved_topic


def _node_matches(pattern: str, node_name: str, fqn: str) -> bool:
    """rcl's rule: a key names a fully qualified node (a missing leading ``/`` is implied);
    ``*`` matches one name token, ``**`` any number of namespace tokens (also none)."""
    return _pattern_regex(pattern).fullmatch(fqn) is not None


@lru_cache(maxsize=256)
def _pattern_regex(pattern: str) -> re.Pattern:
    tokens = ("/" + pattern.lstrip("/")).split("/")[1:]
    out = ""
    for tok in tokens:
        if tok == "**":
            out += "(?:/[^/]+)*"
        else:
            out += "/" + "[^/]+".join(re.escape(part) for part in tok.split("*"))
    return re.compile(out or "/")


def split_ros_args(argv: list[str]) -> tuple[list[str], RosArgs]:
    """Split a process argv into its own arguments and the parsed ``--ros-args`` sections."""
    user: list[str] = []
    ros = RosArgs()
    i, inside = 0, False
    while i < len(argv):
        arg = argv[i]
        if arg == "--ros-args":
            inside = True
        elif inside and arg == "--":
            inside = False
        elif not inside:
            user.append(arg)
        elif arg in _FLAGS_ALONE:
            pass
        elif arg in _FLAGS_WITH_VALUE:
            if i + 1 >= len(argv):
                raise RosArgsError(f"--ros-args: {arg} needs a value")
            _apply_flag(ros, arg, argv[i + 1])
            i += 1
        else:
            raise RosArgsError(f"--ros-args: unknown argument {arg!r}")
        i += 1
    return user, ros


def _apply_flag(ros: RosArgs, flag: str, value: str) -> None:
    if flag in ("-p", "--param"):
        name, sep, text = value.partition(":=")
        if not sep or not name:
            raise RosArgsError(f"--ros-args -p expects name:=value, got {value!r}")
        ros.params.append(("", name, parse_value(text)))
    elif flag in ("-r", "--remap"):
        lhs, sep, dst = value.partition(":=")
        if not sep or not lhs or not dst:
            raise RosArgsError(f"--ros-args -r expects from:=to, got {value!r}")
        node, _, src = lhs.rpartition(":")
        if src == "__node" or src == "__name":
            ros.node_name = dst
        elif src == "__ns":
            ros.namespace = dst if dst.startswith("/") else "/" + dst
        else:
            ros.remaps.append((node or None, src, dst))
    elif flag == "--params-file":
        ros.params.extend(load_params_file(value))
    elif flag == "--log-level":
        ros.log_level = value.rpartition(":")[2].upper()


def parse_value(text: str) -> Any:
    """A ``-p`` value in YAML syntax (``5`` int, ``5.0`` float, ``true``, ``[1, 2]``, text)."""
    try:
        value = safe_load(text)
    except yaml.YAMLError:
        return text
    return "" if value is None else value


def load_params_file(path: str | Path) -> list[tuple[str, str, Any]]:
    """Read a ROS 2 parameters YAML into (node pattern, name, value) entries."""
    path = Path(path)
    doc = read_mapping(path, ParameterError, "parameters file ")
    entries: list[tuple[str, str, Any]] = []
    for pattern, body in doc.items():
        _collect(path, str(pattern), body, entries)
    return entries


def _collect(path: Path, pattern: str, body: Any, entries: list) -> None:
    if not isinstance(body, dict):
        raise ParameterError(f"{path}: entry {pattern!r} must be a mapping holding 'ros__parameters'")
    if "ros__parameters" in body:
        params = body["ros__parameters"]
        if not isinstance(params, dict):
            raise ParameterError(f"{path}: {pattern}.ros__parameters must be a mapping")
        entries.extend((pattern, name, value) for name, value in _flatten(params))
        return
    for sub, inner in body.items():  # namespace nesting: {ns: {node: {ros__parameters: ...}}}
        _collect(path, f"{pattern.rstrip('/')}/{sub}" if pattern.startswith("/") else f"/{pattern}/{sub}", inner,
                 entries)


def _flatten(params: dict, prefix: str = ""):
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            yield from _flatten(value, name + ".")
        else:
            yield name, value


def resolve_name(name: str, namespace: str, node_name: str) -> str:
    """ROS 2 name resolution: ``/abs`` stays, ``~/x`` is private, ``x`` gets the namespace."""
    ns = namespace.rstrip("/")
    if name.startswith("/"):
        return name
    if name == "~" or name.startswith("~/"):
        return f"{ns}/{node_name}{name[1:]}"
    return f"{ns}/{name}"


def remap_and_resolve(ros: RosArgs, topic: str, namespace: str, node_name: str) -> str:
    """The fully qualified name of ``topic`` for a node, after ``-r`` remapping."""
    return ros.remap(node_name, resolve_name(topic, namespace, node_name), namespace)


def check_parameter_type(node: str, name: str, default: Any, value: Any) -> Any:
    """``value`` if it has the type of ``default`` (ints are accepted for doubles)."""
    if isinstance(default, bool) or isinstance(value, bool):
        ok = isinstance(value, bool) and isinstance(default, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float))
        value = float(value) if ok else value
    elif isinstance(default, list):
        ok = isinstance(value, list)
    else:
        ok = isinstance(value, type(default))
    if not ok:
        raise ParameterError(f"node {node}: parameter {name!r} must be {type(default).__name__} "
                             f"(default {default!r}), got {value!r}")
    return value


def check_overrides(node: str, defaults: dict[str, Any], overrides: dict[str, Any] | None) -> dict[str, Any]:
    """``overrides`` (parameter values given in Python, see
    :meth:`~hdrqn_ros.middleware.port.Node.declare_parameters`) type-checked against
    ``defaults``; a :class:`ParameterError` for a name without a default."""
    if not overrides:
        return {}
    if unknown := sorted(set(overrides) - set(defaults)):
        raise ParameterError(f"node {node}: no parameter {unknown[0]!r} to override; declared: {sorted(defaults)}")
    return {name: check_parameter_type(node, name, defaults[name], value) for name, value in overrides.items()}


DEFAULT_MAX_MESSAGE_BYTES = 64 * 2**20
"""Received samples larger than this are dropped with a warning (weights are ~2.5 MB)."""


INTERFACE_ENV = "HDRQN_DDS_INTERFACE"
"""The environment variable naming the network interface for DDS (the ``dds_interface`` parameter wins)."""


@dataclass(frozen=True)
class ProcessSettings:
    """What a process's middleware needs before its first node: from the ``/**`` parameters
    (``ros_domain_id``, ``dds_interface``, ``max_message_bytes``) or the environment
    (``ROS_DOMAIN_ID``, ``HDRQN_DDS_INTERFACE``). ``interface`` None: loopback only."""

    domain_id: int
    interface: str | None
    max_message_bytes: int


def process_settings(ros: RosArgs, environ: dict | None = None) -> ProcessSettings:
    """The :class:`ProcessSettings` of ``ros``; a :class:`ParameterError` naming a bad one."""
    import os

    environ = os.environ if environ is None else environ
    params = ros.parameters_for("", "/")
    domain_id = _int_setting("ros_domain_id (or $ROS_DOMAIN_ID)",
                             params.get("ros_domain_id", environ.get("ROS_DOMAIN_ID", "0") or 0))
    if not 0 <= domain_id <= 232:
        raise ParameterError(f"ROS_DOMAIN_ID must be in 0..232, got {domain_id}")
    interface = params.get("dds_interface") or environ.get(INTERFACE_ENV) or None
    if interface is not None and not isinstance(interface, str):
        raise ParameterError(f"dds_interface must be an interface name, got {interface!r}")
    max_bytes = _int_setting("max_message_bytes", params.get("max_message_bytes", DEFAULT_MAX_MESSAGE_BYTES))
    if max_bytes <= 0:
        raise ParameterError(f"max_message_bytes must be > 0, got {max_bytes}")
    return ProcessSettings(domain_id, interface, max_bytes)


def _int_setting(name: str, value) -> int:
    """``value`` as an int (a parameter or environment variable), or a ParameterError naming it."""
    try:
        if isinstance(value, (bool, float)):
            raise TypeError
        return int(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be an integer, got {value!r}") from None
