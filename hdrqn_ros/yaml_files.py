"""Reading YAML safely: every failure on bad text is a :class:`yaml.YAMLError`, and files
whose top level must be a mapping get errors that name the file."""
from __future__ import annotations

from pathlib import Path

import yaml


class _Loader(yaml.SafeLoader):
    """Safe loading, plus ``!!python/tuple`` read as a plain list: launch_ros writes list
    parameters that way into the params files it passes to nodes, and rcl reads them as
    sequences. Nothing else of Python's tags is accepted."""


_Loader.add_constructor("tag:yaml.org,2002:python/tuple", lambda loader, node: loader.construct_sequence(node))


def safe_load(text: str):
    """``yaml.safe_load(text)`` (and ``!!python/tuple`` as a list), raising only :class:`yaml.YAMLError`: PyYAML's constructors
    also raise ValueError (``2001-13-01``, ``!!int x``), KeyError (``!!bool maybe``),
    AttributeError (``!!timestamp x``), IndexError (``a: !!int``) and, for deep nesting,
    RecursionError."""
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError:
        raise
    except RecursionError:
        raise yaml.YAMLError("nested too deeply") from None
    except (ValueError, KeyError, AttributeError, IndexError, TypeError, OverflowError) as exc:
        raise yaml.YAMLError(f"cannot construct a value: {type(exc).__name__}: {exc}") from None


def read_mapping(path: str | Path, error: type[Exception], what: str = "", empty_ok: bool = False) -> dict:
    """The mapping in YAML file ``path``; ``error`` (e.g. ``ConfigError``) names the file and
    the problem: unreadable, not UTF-8, not YAML, or not a mapping (an empty file is ``{}``
    when ``empty_ok``). ``what`` describes the file in the unreadable case ("config ", ...)."""
    path = Path(path)
    try:
        data = safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise error(f"cannot read {what}{path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise error(f"{path} is not UTF-8 text: {exc}") from None
    except yaml.YAMLError as exc:
        raise error(f"{path} is not valid YAML: {exc}") from None
    if data is None and empty_ok:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data
