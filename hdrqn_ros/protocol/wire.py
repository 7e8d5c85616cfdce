"""The training graph's wire protocol: topics, message layouts, validation.

Every per-step message carries the **step key**: the simulation time of the observation
it belongs to, in nanoseconds (``key = step_index * step_period``). Images carry it as
``header.stamp``; the scalar messages (standard ``std_msgs/*MultiArray`` types) as their
first element. Layout labels name every element, so ``ros2 topic echo`` is readable.
Nodes join their inputs by key, so no message is ever paired with another step's, even
when DDS delivers different writers' samples in another order, or a node restarts.

A transition ``prev_key -> key`` is: observation(prev_key), action(prev_key), the
option's subgoal (published at the key where the option started), then env_step(key)
(what stepping did), critic(key) (intrinsic reward of that step) and observation(key).

Per step the loop is env -> critic -> sub-controller -> env; only where an option ends
does the meta-controller join in (env -> critic -> meta -> sub -> env), with hDRQNv2's
sub-controller handing its LSTM state (``sub_state``) to it at such steps.
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass

import numpy as np

from hdrqn_ros.envs.domain import StepBatch
from hdrqn_ros.protocol.arrays import as_array

# topics, relative to the group's namespace unless absolute
OBSERVATION = "observation"
SUBGOAL_IMAGES = "subgoal_images"
ENV_STEP = "env_step"
POSE = "pose"
POSES = "poses"
CRITIC = "critic"
SUBGOAL = "subgoal"
ACTION = "action"
SUB_STATE = "sub_state"
CREDIT = "learner_credit"
CLOCK = "/clock"
WEIGHTS = {"sub": "/learner/sub_weights", "meta": "/learner/meta_weights"}
STATUS = "/learner/status"

IMAGE = "sensor_msgs/msg/Image"
FLOATS = "std_msgs/msg/Float64MultiArray"
INTS = "std_msgs/msg/Int64MultiArray"
BYTES = "std_msgs/msg/UInt8MultiArray"
STRING = "std_msgs/msg/String"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POSE_ARRAY = "geometry_msgs/msg/PoseArray"
CLOCK_TYPE = "rosgraph_msgs/msg/Clock"

STEP_FIELDS = ("key", "prev_key", "env_steps", "episode", "t", "action", "extrinsic", "classical", "terminated", "truncated",
               "at_subgoal", "collected", "hit_obstacle", "life_lost", "success", "decision_point")
"""``env_step``: the env stepped ``action`` on observation ``prev_key`` and now shows
``key`` (at ``t`` = 0 a new episode begins: ``prev_key`` = 0, no action); ``env_steps``
counts the env's steps since it started (the learner's credit refers to it). ``decision_point``:
a new option may start here, and ``subgoal_images`` for ``key`` are published."""
CRITIC_FIELDS = ("key", "intrinsic", "reached", "option_done", "subgoal")
"""``critic``: the internal critic's verdict on the step into ``key`` for ``subgoal``
(option_done = 1 at an episode's first step: the meta-controller must choose)."""
SUBGOAL_FIELDS = ("key", "subgoal", "new_option")
"""``subgoal``: published by the meta-controller when an option starts (``new_option`` = 1)."""
ACTION_FIELDS = ("key", "action")
CREDIT_FIELDS = ("credit_steps", "eps_sub", "eps_meta", "acked_key", "epoch")
"""``learner_credit``: the env may take steps while its step count < ``credit_steps``;
the controllers explore with ``eps_sub``/``eps_meta``; ``acked_key`` is the last key
the learner stored; ``epoch`` changes when the learner restarts."""

STEP_DEPTH = 1000
"""Keep-last depth (samples) of the per-step protocol topics (reliable, volatile): a node off
the critical path (the meta-controller between option ends, the learner during an update) may
fall behind by many steps without losing a sample; 1000 steps of observations are about 6 MB
per reader."""


def group_namespaces(groups: int) -> list[str]:
    """The namespaces of ``groups`` environment groups: ``/`` for one, else ``/group<i>``."""
    return ["/"] if groups == 1 else [f"/group{i}" for i in range(groups)]


def group_topic(namespace: str, name: str) -> str:
    """The absolute name of a group's topic ``name`` (``/`` + name for the root namespace)."""
    return f"{namespace.rstrip('/')}/{name}"


MAX_KEY = 2**53
"""Keys are exact in float64 up to 2^53 ns (104 days of simulated time)."""


class ProtocolError(ValueError):
    """A message that does not fit the protocol (wrong size, type, range, NaN...)."""


@dataclass(frozen=True)
class Stamp:
    sec: int
    nanosec: int

    @classmethod
    def of(cls, key: int) -> "Stamp":
        return cls(int(key // 1_000_000_000), int(key % 1_000_000_000))


def key_of(stamp) -> int:
    """The step key of a ``builtin_interfaces/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


_layouts: dict = {}


def _layout(node, fields: tuple[str, ...]) -> object:
    """The (shared, never modified) layout naming ``fields``: built once per class and fields."""
    layout_cls = node.msg("std_msgs/msg/MultiArrayLayout")
    layout = _layouts.get((layout_cls, fields))
    if layout is None:
        dim = node.msg("std_msgs/msg/MultiArrayDimension")(label=",".join(fields), size=len(fields),
                                                           stride=len(fields))
        layout = _layouts[(layout_cls, fields)] = layout_cls(dim=[dim], data_offset=0)
    return layout


def make_record(node, type_name: str, fields: tuple[str, ...], values) -> object:
    """A ``*MultiArray`` message holding ``values`` in the order of ``fields``."""
    dtype = np.float64 if type_name == FLOATS else np.int64
    return node.msg(type_name)(layout=_layout(node, fields), data=node.pack(np.asarray(values, dtype=dtype)))


ENV_DIM = "env"
"""Label of the leading layout dimension of a message that holds one record per environment."""
MAX_ENVS = 64
"""Most environments one environment node steps as a batch (its ``num_envs``)."""


def _rows_layout(node, n: int, label: str, width: int) -> object:
    """The layout of ``n`` rows of ``width`` values: dimensions ``env`` (n) and ``label`` (width)."""
    layout_cls = node.msg("std_msgs/msg/MultiArrayLayout")
    layout = _layouts.get((layout_cls, label, n, width))
    if layout is None:
        dim = node.msg("std_msgs/msg/MultiArrayDimension")
        layout = _layouts[(layout_cls, label, n, width)] = layout_cls(
            dim=[dim(label=ENV_DIM, size=n, stride=n * width), dim(label=label, size=width, stride=width)],
            data_offset=0)
    return layout


def make_records(node, type_name: str, fields: tuple[str, ...], rows) -> object:
    """One record per environment: ``rows`` (N, len(fields)). For N = 1 exactly
    :func:`make_record`'s message (the single-environment wire format); for N > 1 the
    layout's dimensions are ``env`` (N) and the field names."""
    dtype = np.float64 if type_name == FLOATS else np.int64
    rows = np.asarray(rows, dtype=dtype)
    if len(rows) == 1:
        return make_record(node, type_name, fields, rows[0])
    return node.msg(type_name)(layout=_rows_layout(node, len(rows), ",".join(fields), len(fields)),
                               data=node.pack(rows.reshape(-1)))


def envs_in(msg) -> int:
    """How many environments a ``*MultiArray`` message holds: the size of its leading
    ``env`` dimension (2..:data:`MAX_ENVS`), 1 without one."""
    dims = msg.layout.dim
    if len(dims) < 2 or dims[0].label != ENV_DIM:
        return 1
    n = int(dims[0].size)
    if not 2 <= n <= MAX_ENVS:
        raise ProtocolError(f"layout dimension {ENV_DIM!r} has size {n}, expected 2..{MAX_ENVS}")
    return n


FLOAT32_MAX = float(np.finfo(np.float32).max)


def read_record(msg, fields: tuple[str, ...], dtype=np.float64, extra: bool = False) -> dict[str, float]:
    """The named values of a ``*MultiArray`` record; ``extra``: trailing values allowed
    (returned under ``"rest"``). Raises :class:`ProtocolError` on a malformed message."""
    return _record(as_array(msg.data, dtype), fields, dtype, extra)


def read_records(msg, fields: tuple[str, ...], dtype=np.float64, extra: bool = False) -> list[dict[str, float]]:
    """The records of a message with one per environment (:func:`make_records`; a message
    without an ``env`` dimension holds one), as :func:`read_record` reads each. Every
    record's ``key`` must be the same."""
    n = envs_in(msg)
    data = as_array(msg.data, dtype)
    if n == 1:
        return [_record(data, fields, dtype, extra)]
    if data.size % n:
        raise ProtocolError(f"{data.size} values do not split into {n} environments' records")
    rows = [_record(row, fields, dtype, extra) for row in data.reshape(n, -1)]
    if "key" in fields and len({row["key"] for row in rows}) > 1:
        raise ProtocolError("the environments' records carry different step keys")
    return rows


def _record(data: np.ndarray, fields: tuple[str, ...], dtype, extra: bool) -> dict[str, float]:
    num_fields = len(fields)
    if data.size < num_fields or (data.size != num_fields and not extra):
        raise ProtocolError(f"expected {num_fields} values ({','.join(fields)}), got {data.size}")
    if dtype == np.float64 and not (np.abs(data) <= FLOAT32_MAX).all():  # rewards, states become float32
        raise ProtocolError("non-finite value (NaN or inf, or beyond the float32 range)")
    out = {f: data[i].item() for i, f in enumerate(fields)}
    key = out.get("key")
    if key is not None and not (0 < key < MAX_KEY and float(key).is_integer()):
        raise ProtocolError(f"step key {key!r} is not a positive integer below 2^53")
    if extra:
        out["rest"] = data[num_fields:]
    return out


STEP_COUNTS = ("prev_key", "env_steps", "episode", "t", "action")
STEP_FLAGS = ("terminated", "truncated", "collected", "hit_obstacle", "life_lost", "success", "decision_point")
MAX_SUBGOALS = 128
"""Subgoal indices are below this (replay stores them as int8)."""


def read_steps(msg) -> list[dict[str, float]]:
    """The ``env_step`` records of a message (one per environment), each checked as
    :func:`read_step` says."""
    return [_check_step(record) for record in read_records(msg, STEP_FIELDS)]


def read_step(msg) -> dict[str, float]:
    """An ``env_step`` record whose fields are what the protocol says: :data:`STEP_COUNTS`
    integers in [0, 2^53), :data:`STEP_FLAGS` 0 or 1, ``at_subgoal`` in [-1, 128).
    Raises :class:`ProtocolError` naming the field."""
    return _check_step(read_record(msg, STEP_FIELDS))


def _check_step(record: dict[str, float]) -> dict[str, float]:
    for field in STEP_COUNTS:
        if not (0 <= record[field] < MAX_KEY and float(record[field]).is_integer()):
            raise ProtocolError(f"env_step {field} {record[field]!r} is not an integer in [0, 2^53)")
    for field in STEP_FLAGS:
        if record[field] not in (0.0, 1.0):
            raise ProtocolError(f"env_step {field} must be 0 or 1, got {record[field]!r}")
    check_index(record["at_subgoal"], MAX_SUBGOALS, "env_step at_subgoal", allow_none=True)
    return record


def _check_envs(records: list, num_envs: int | None, what: str) -> None:
    if num_envs is not None and len(records) != num_envs:
        raise ProtocolError(f"{what} holds {len(records)} environment(s)' records, expected {num_envs}")


def read_subgoals(msg, num_subgoals: int, num_envs: int | None = None) -> tuple[int, np.ndarray]:
    """(key, (N,) int64) from a ``subgoal`` message: each environment's new option's
    subgoal, -1 for environments of a batch whose option goes on (``new_option`` 0)."""
    records = read_records(msg, SUBGOAL_FIELDS, np.int64)
    _check_envs(records, num_envs, "subgoal")
    batch = len(records) > 1
    chosen = [check_index(r["subgoal"], num_subgoals, "subgoal") if r["new_option"] or not batch else -1
              for r in records]
    return int(records[0]["key"]), np.array(chosen, np.int64)


def read_actions(msg, num_actions: int, num_envs: int | None = None) -> tuple[int, np.ndarray]:
    """(key, (N,) int64) from an ``action`` message; in a batch, -1 for an environment
    that takes no action (its episode ended at this step)."""
    records = read_records(msg, ACTION_FIELDS, np.int64)
    _check_envs(records, num_envs, "action")
    allow_none = len(records) > 1
    return int(records[0]["key"]), np.array([check_index(r["action"], num_actions, "action", allow_none)
                                             for r in records], np.int64)


def make_time(node, key: int) -> object:
    """``builtin_interfaces/Time`` of a key (ns)."""
    stamp = Stamp.of(key)
    return node.msg("builtin_interfaces/msg/Time")(sec=stamp.sec, nanosec=stamp.nanosec)


def make_header(node, key: int, frame_id: str) -> object:
    return node.msg("std_msgs/msg/Header")(stamp=make_time(node, key), frame_id=frame_id)


def make_pose(node, key: int, frame_id: str, x: float, y: float) -> object:
    """``geometry_msgs/PoseStamped`` at (x, y) (grid: column, row), identity orientation."""
    return node.msg(POSE_STAMPED)(header=make_header(node, key, frame_id), pose=_pose(node, x, y))


def make_poses(node, key: int, frame_id: str, positions: list[tuple[float, float]]) -> object:
    """``geometry_msgs/PoseArray`` of a batch's agents, one (x, y) pose per environment."""
    return node.msg(POSE_ARRAY)(header=make_header(node, key, frame_id), poses=[
        _pose(node, x, y) for x, y in positions])


def _pose(node, x: float, y: float) -> object:
    return node.msg("geometry_msgs/msg/Pose")(
        position=node.msg("geometry_msgs/msg/Point")(x=x, y=y, z=0.0),
        orientation=node.msg("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0))


def make_state(node, key: int, state: np.ndarray) -> object:
    """``sub_state``: Float64MultiArray ``[key, state...]`` (the LSTM state, 256 values)."""
    dims = [node.msg("std_msgs/msg/MultiArrayDimension")(label="key", size=1, stride=1 + state.size),
            node.msg("std_msgs/msg/MultiArrayDimension")(label="state", size=state.size, stride=state.size)]
    layout = node.msg("std_msgs/msg/MultiArrayLayout")(dim=dims, data_offset=0)
    return node.msg(FLOATS)(layout=layout, data=node.pack(np.concatenate([[float(key)], state]).astype(np.float64)))


def make_states(node, key: int, states: np.ndarray) -> object:
    """``sub_state`` of N environments: (N, state) float; N = 1 is :func:`make_state`'s
    message, N > 1 has the rows ``[key, state...]`` under an ``env`` dimension."""
    if len(states) == 1:
        return make_state(node, key, states[0])
    rows = np.concatenate([np.full((len(states), 1), float(key)), states], axis=1).astype(np.float64)
    return node.msg(FLOATS)(layout=_rows_layout(node, len(rows), "key,state", rows.shape[1]),
                            data=node.pack(rows.reshape(-1)))


def read_state(msg, size: int) -> tuple[int, np.ndarray]:
    """(key, (size,) float32) from a ``sub_state`` message."""
    key, states = read_states(msg, size)
    if len(states) != 1:
        raise ProtocolError(f"sub_state holds {len(states)} environments' states, expected 1")
    return key, states[0]


def read_states(msg, size: int) -> tuple[int, np.ndarray]:
    """(key, (N, size) float32) from a ``sub_state`` message of N environments."""
    records = read_records(msg, ("key",), extra=True)
    for record in records:
        if record["rest"].size != size:
            raise ProtocolError(f"sub_state must hold {size} state values, got {record['rest'].size}")
    return int(records[0]["key"]), np.stack([r["rest"] for r in records]).astype(np.float32)


def read_images(msg, height: int, width: int, num_envs: int) -> tuple[int, np.ndarray]:
    """(key, (num_envs, height, width, 3) uint8) from an rgb8 Image of the environments'
    ``height`` x ``width`` images stacked top to bottom."""
    key, pixels = read_image(msg, height * num_envs, width)
    return key, pixels.reshape(num_envs, height, width, 3)


def make_image(node, key: int, pixels: np.ndarray, frame_id: str) -> object:
    """``sensor_msgs/Image`` rgb8 of (H, W, 3) uint8 ``pixels``, stamped with ``key``
    ((N, H, W, 3): the N images stacked top to bottom, one (N*H, W) image)."""
    pixels = pixels.reshape(-1, *pixels.shape[-2:])
    h, w, _ = pixels.shape
    header = make_header(node, key, frame_id)
    return node.msg(IMAGE)(header=header, height=h, width=w, encoding="rgb8", is_bigendian=0, step=w * 3,
                           data=node.pack(np.ascontiguousarray(pixels, np.uint8).reshape(-1)))


def read_image(msg, height: int, width: int) -> tuple[int, np.ndarray]:
    """(key, (height, width, 3) uint8) from an rgb8 Image of exactly that size."""
    if msg.encoding != "rgb8":
        raise ProtocolError(f"image encoding must be rgb8, got {msg.encoding!r}")
    if (msg.height, msg.width) != (height, width) or msg.step != width * 3:
        raise ProtocolError(f"image must be {height}x{width} (step {width * 3}), "
                            f"got {msg.height}x{msg.width} (step {msg.step})")
    data = as_array(msg.data, np.uint8)
    if data.size != height * width * 3:
        raise ProtocolError(f"image data must hold {height * width * 3} bytes, got {data.size}")
    key = key_of(msg.header.stamp)
    if not 0 < key < MAX_KEY:
        raise ProtocolError(f"image stamp {key} ns is not a valid step key")
    return key, data.reshape(height, width, 3)


def check_index(value: float, n: int, what: str, allow_none: bool = False) -> int:
    """``value`` as an int in [0, n) (or -1 when ``allow_none``)."""
    if not float(value).is_integer() or not (-1 if allow_none else 0) <= value < n:
        raise ProtocolError(f"{what} {value!r} is out of range [0, {n})")
    return int(value)



def step_outcome(step: StepBatch, i: int) -> dict:
    """The ``env_step`` fields that say what stepping environment ``i`` of ``step`` did
    (``extrinsic`` ... ``decision_point``; the caller adds the keys, counters and action)."""
    done = bool(step.terminated[i] or step.truncated[i])
    return {"extrinsic": float(step.extrinsic[i]), "classical": float(step.classical[i]),
            "terminated": bool(step.terminated[i]), "truncated": bool(step.truncated[i]),
            "at_subgoal": int(step.at_subgoal[i]), "collected": bool(step.collected[i]),
            "hit_obstacle": bool(step.hit_obstacle[i]), "life_lost": bool(step.life_lost[i]),
            "success": bool(step.success[i]),
            "decision_point": bool((step.at_subgoal[i] >= 0 or step.life_lost[i]) and not done)}


def step_batch(steps: dict | list[dict], obs: np.ndarray | None = None) -> StepBatch:
    """A :class:`StepBatch` from ``env_step`` records (one dict: one row; ``obs``: the
    rows' (44, 44, 3) observations, or none)."""
    steps = [steps] if isinstance(steps, dict) else steps
    n = len(steps)

    def col(name, dtype):
        return np.array([step[name] for step in steps], dtype)

    return StepBatch(obs=np.zeros((n, 0, 0, 3), np.uint8) if obs is None else obs.reshape(n, *obs.shape[-3:]),
                     classical=col("classical", np.float32), extrinsic=col("extrinsic", np.float32),
                     terminated=col("terminated", bool), truncated=col("truncated", bool),
                     agent_pos=np.zeros((n, 2), np.int32), at_subgoal=col("at_subgoal", np.int32),
                     collected=col("collected", bool), hit_obstacle=col("hit_obstacle", bool),
                     life_lost=col("life_lost", bool), success=col("success", bool))


def as_bytes(data) -> bytes:
    """A ``uint8[]`` field as bytes."""
    return as_array(data, np.uint8).tobytes()


def make_weights(node, payload: bytes, updates: int) -> object:
    """``std_msgs/UInt8MultiArray`` of safetensors bytes; the layout label says
    ``safetensors update=<n>`` (the learner's update count when they were taken)."""
    dim = node.msg("std_msgs/msg/MultiArrayDimension")(label=f"safetensors update={updates}", size=len(payload),
                                                       stride=len(payload))
    layout = node.msg("std_msgs/msg/MultiArrayLayout")(dim=[dim], data_offset=0)
    return node.msg(BYTES)(layout=layout, data=node.pack(np.frombuffer(payload, np.uint8)))


def read_weights_version(msg) -> int:
    """The learner update count in a weights message's layout label (0 if absent or not
    a plain decimal number of at most 18 digits)."""
    label = msg.layout.dim[0].label if len(msg.layout.dim) else ""
    _, _, n = label.partition("update=")
    return int(n) if re.fullmatch(r"[0-9]{1,18}", n) else 0


def obs_digest(obs: np.ndarray) -> str:
    """A short digest of an observation's bytes (step and transition logs)."""
    return hashlib.blake2b(np.ascontiguousarray(obs).tobytes(), digest_size=8).hexdigest()
