"""Replay snapshots: the replay memory of every controller in one safetensors file (tensors
and a JSON string, never pickle), written beside each checkpoint so that ``--resume``
continues with the replay the checkpoint was trained from.

Layout: episode ``i`` (0 the oldest, the next to be evicted) of controller ``role``
(``sub``, ``meta``) is stored as ``{role}/{i:06d}/frames``, ``{role}/{i:06d}/segment_starts``,
``{role}/{i:06d}/field/{name}`` and ``{role}/{i:06d}/segment/{name}``; the metadata key
``hdrqn_ros`` holds a JSON object: format and version, algo, env and env_kwargs of the run,
the snapshot's ``token``, and per role the episode count, capacities, field names, total
steps and bytes and the state of the replay's sampling generator.

Version 1 snapshots (before the discount was read at update time) stored a ``discount``
field; they load converted (:func:`_version1_fields`).

Pairing with the checkpoint: each save writes a new file ``replay-<token>.safetensors``
(temp file + rename), then the checkpoint (whose ``progress["replay"]`` names that file and
its sha256), and only then deletes the older snapshots. A crash at any point leaves the
last checkpoint beside the snapshot it names (disk holds two snapshots for a moment).
"""
from __future__ import annotations

import json
import math
import os
import tempfile
import uuid
from pathlib import Path

import numpy as np

from hdrqn_ros.agents.replay import Episode, EpisodeReplay
from hdrqn_ros.hashing import file_sha256
from hdrqn_ros.training.checkpoint import CheckpointError

FORMAT = "hdrqn_ros-replay"
VERSION = 2
META_KEY = "hdrqn_ros"
PREFIX, SUFFIX = "replay-", ".safetensors"

__all__ = ["save_replay_snapshot", "load_replay_snapshot", "remove_other_snapshots"]


def _role_tensors(role: str, replay: EpisodeReplay) -> tuple[dict[str, np.ndarray], dict]:
    tensors: dict[str, np.ndarray] = {}
    fields: list[str] = []
    segment: list[str] = []
    for i in range(len(replay)):
        ep = replay[i]
        key = f"{role}/{i:06d}"
        tensors[f"{key}/frames"] = ep.frames
        tensors[f"{key}/segment_starts"] = ep.segment_starts
        for name, arr in ep.fields.items():
            tensors[f"{key}/field/{name}"] = arr
        for name, arr in ep.segment_data.items():
            tensors[f"{key}/segment/{name}"] = arr
        if i == 0:
            fields, segment = sorted(ep.fields), sorted(ep.segment_data)
    info = {"episodes": len(replay), "capacity_episodes": replay.capacity_episodes,
            "capacity_bytes": replay.capacity_bytes, "fields": fields, "segment_data": segment,
            "num_steps": replay.num_steps, "nbytes": replay.nbytes,
            "rng": replay._rng.bit_generator.state}
    return tensors, info


def save_replay_snapshot(directory: str | Path, replays: dict[str, EpisodeReplay], run: dict) -> dict:
    """Write ``replays`` (role -> replay) to a new ``replay-<token>.safetensors`` in
    ``directory`` atomically (temp file, fsync, rename). ``run``: ``algo``, ``env``,
    ``env_kwargs``. Returns ``{"file": name, "sha256": hex, "token": token}`` for the
    checkpoint's progress."""
    from safetensors.numpy import save_file

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    tensors: dict[str, np.ndarray] = {}
    roles = {}
    for role, replay in replays.items():
        t, info = _role_tensors(role, replay)
        tensors.update(t)
        roles[role] = info
    meta = {"format": FORMAT, "version": VERSION, "token": token, **run, "roles": roles}
    name = f"{PREFIX}{token}{SUFFIX}"
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{name}.", suffix=".tmp")
    os.close(fd)
    try:
        save_file(tensors, tmp, metadata={META_KEY: json.dumps(meta)})
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        digest = file_sha256(tmp)
        os.replace(tmp, directory / name)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return {"file": name, "sha256": digest, "token": token}


def remove_other_snapshots(directory: str | Path, keep: str | None) -> None:
    """Delete the snapshots (and leftover temp files) in ``directory`` other than ``keep``."""
    for path in Path(directory).glob(f"{PREFIX}*{SUFFIX}"):
        if path.name != keep:
            path.unlink(missing_ok=True)
    for path in Path(directory).glob(f".{PREFIX}*.tmp"):
        path.unlink(missing_ok=True)


def _version1_fields(role: str, fields: dict[str, np.ndarray], meta_gamma: float,
                     smdp_discount: bool) -> dict[str, np.ndarray]:
    """A version 1 episode's fields in today's layout. The sub-controller's ``discount``
    (its gamma) goes. The meta-controller's ``discount`` (``meta_gamma ** k`` with
    ``smdp_discount``, else ``meta_gamma``) becomes ``option_steps`` k =
    ``round(log(discount) / log(meta_gamma))``: exact for options stored with that gamma.
    Where the discount did not depend on k (no ``smdp_discount``, or gamma 0 or 1) k is not
    recoverable and loads as 1; the update reads k only with ``smdp_discount``."""
    fields = dict(fields)
    discount = fields.pop("discount")
    if role == "meta":
        if smdp_discount and 0.0 < meta_gamma < 1.0:
            steps = np.rint(np.log(discount.astype(np.float64)) / math.log(meta_gamma)).clip(min=1)
        else:
            steps = np.ones(discount.shape)
        fields["option_steps"] = steps.astype(np.int32)
    return fields


def load_replay_snapshot(path: str | Path, replays: dict[str, EpisodeReplay], expected: dict, run: dict,
                         written_with: dict) -> None:
    """Fill the empty ``replays`` from snapshot ``path`` exactly (same episodes, same order,
    same sampling generator state). ``expected``: the checkpoint's record of it (``sha256``,
    ``token``); ``run``: this run's ``algo``, ``env``, ``env_kwargs``; ``written_with``: the
    checkpoint's config (its ``meta.gamma`` and ``smdp_discount`` convert a version 1
    snapshot, :func:`_version1_fields`). Raises
    :class:`CheckpointError` naming ``path`` for a missing, corrupted, truncated or
    foreign snapshot; the replays are left empty then (never partly filled)."""
    from safetensors import SafetensorError, safe_open
    from safetensors.numpy import load_file

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"replay snapshot {path} named by the checkpoint does not exist (resume with "
                              f"--set save_replay=false to continue with an empty replay)")
    if file_sha256(path) != expected.get("sha256"):
        raise CheckpointError(f"replay snapshot {path} does not match its checkpoint (sha256 differs: "
                              f"corrupted, truncated or replaced)")
    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = json.loads((f.metadata() or {})[META_KEY])
        tensors = load_file(str(path))
    except (SafetensorError, OSError, KeyError, TypeError, ValueError) as exc:
        raise CheckpointError(f"{path} is not a readable replay snapshot ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") not in (1, VERSION):
        raise CheckpointError(f"{path} is not a version 1 or {VERSION} hdrqn_ros replay snapshot")
    if meta.get("token") != expected.get("token"):
        raise CheckpointError(f"replay snapshot {path} belongs to another checkpoint")
    for key in ("algo", "env", "env_kwargs"):
        if meta.get(key) != run.get(key):
            raise CheckpointError(f"replay snapshot {path} was written with {key}={meta.get(key)!r}, "
                                  f"not {run.get(key)!r}")
    roles = meta.get("roles", {})
    if set(roles) != set(replays):
        raise CheckpointError(f"replay snapshot {path} holds the replays {sorted(roles)}, this agent has "
                              f"{sorted(replays)}")
    try:
        for role, replay in replays.items():
            info = roles[role]
            if len(replay):
                raise CheckpointError(f"cannot restore {path} into a non-empty {role} replay")
            for i in range(int(info["episodes"])):
                key = f"{role}/{i:06d}"
                fields = {n: tensors.pop(f"{key}/field/{n}") for n in info["fields"]}
                if meta["version"] == 1:
                    fields = _version1_fields(role, fields, written_with["meta"]["gamma"],
                                              written_with.get("smdp_discount", False))
                replay.add(Episode(frames=tensors.pop(f"{key}/frames"), fields=fields,
                                   segment_starts=tensors.pop(f"{key}/segment_starts"),
                                   segment_data={n: tensors.pop(f"{key}/segment/{n}") for n in info["segment_data"]}))
            if (len(replay), replay.num_steps) != (info["episodes"], info["num_steps"]):
                raise CheckpointError(f"replay snapshot {path}: the {role} replay does not fit this run's replay "
                                      f"capacity ({len(replay)} of {info['episodes']} episodes kept)")
            replay._rng.bit_generator.state = info["rng"]
        if tensors:
            raise CheckpointError(f"replay snapshot {path} holds unexpected tensors, e.g. {sorted(tensors)[:3]}")
    except CheckpointError:
        for replay in replays.values():
            replay.clear()
        raise
    except (KeyError, TypeError, ValueError) as exc:
        for replay in replays.values():
            replay.clear()
        raise CheckpointError(f"replay snapshot {path} is inconsistent ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
