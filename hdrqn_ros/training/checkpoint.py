"""Checkpoints: tensors and plain values only, written atomically, read with
``torch.load(weights_only=True)`` (no code runs from a checkpoint file).

torch is imported where it is used, so that code without torch (a controller node acting on
an exported ONNX policy) can name :class:`CheckpointError`."""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


FORMAT = "hdrqn_ros-checkpoint"
VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, or belongs to another algorithm/domain."""


def _all_finite(state) -> bool:
    import torch

    if isinstance(state, torch.Tensor):
        return not state.is_floating_point() or bool(torch.isfinite(state).all())
    if isinstance(state, dict):
        return all(_all_finite(v) for v in state.values())
    if isinstance(state, (list, tuple)):
        return all(_all_finite(v) for v in state)
    return True


def save_checkpoint(path: str | Path, *, config: dict, agent_state: dict, progress: dict) -> None:
    """Write atomically (temp file + rename). Refuses weights with NaN/inf, so a broken
    agent never replaces the last good checkpoint."""
    if not _all_finite(agent_state):
        raise CheckpointError(f"refusing to write {path}: the weights contain NaN or infinite values")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": FORMAT, "version": VERSION, "config": json.dumps(config),
               "agent": agent_state, "progress": progress}
    import torch

    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_checkpoint(path: str | Path, map_location: str = "cpu") -> dict:
    """Returns ``{"config": dict, "agent": ..., "progress": ...}``; raises CheckpointError."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    import torch

    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # corrupted, truncated, not a torch file, or a pickle that runs code
        # torch's own message is left out: for a pickle it suggests weights_only=False, which
        # would run whatever the file holds
        raise CheckpointError(f"{path} is not a readable hdrqn_ros checkpoint: expected the weights-only torch "
                              f"file that hdrqn train writes (RUN_DIR/checkpoints/last.pt); torch could not load "
                              f"it ({type(exc).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not an hdrqn_ros checkpoint (no '{FORMAT}' marker)")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"{path} has checkpoint version {payload.get('version')}, expected {VERSION}")
    try:
        payload["config"] = json.loads(payload["config"])
    except (KeyError, TypeError, ValueError):
        raise CheckpointError(f"{path} has no readable configuration") from None
    return payload
