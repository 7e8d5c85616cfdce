"""Reading a YAML file whose top level must be a mapping, with errors that name the file."""
from __future__ import annotations

from pathlib import Path

import yaml


def read_mapping(path: str | Path, error: type[Exception], what: str = "", empty_ok: bool = False) -> dict:
    """The mapping in YAML file ``path``; ``error`` (e.g. ``ConfigError``) names the file and
    the problem: unreadable, not YAML, or not a mapping (an empty file is ``{}`` when
    ``empty_ok``). ``what`` describes the file in the unreadable case ("config ", ...)."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise error(f"cannot read {what}{path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        raise error(f"{path} is not valid YAML: {exc}") from None
    if data is None and empty_ok:
        return {}
    if not isinstance(data, dict):
        raise error(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data
