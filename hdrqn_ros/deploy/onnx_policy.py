"""Acting from an exported policy directory with ONNX Runtime: numpy in, numpy out, no torch.

A policy directory (written by :func:`hdrqn_ros.training.export.export_policy`, or
``hdrqn export``) holds ``policy.json`` and one ONNX model per controller: ``meta.onnx``
and ``sub.onnx`` for the hierarchical algorithms, ``sub.onnx`` alone for DQN and DRQN.
Each model computes what the torch network's ``act(x, state)`` computes, one time step:

* recurrent (LSTM) controllers: inputs ``x`` (B, ...), ``h`` (B, 256), ``c`` (B, 256);
  outputs ``q`` (B, n), ``h_out``, ``c_out`` (B, 256), the LSTM state after the step;
* feed-forward controllers (DQN, hDQN): input ``x``, output ``q``.

``x`` is a uint8 channels-last image (B, 44, 44, C) (the model scales it to [0, 1]), or,
for the hDRQNv2 meta-controller, the float32 (B, 256) sub-controller LSTM state (its
``c`` or ``h``, ``policy.json``'s ``meta_state``) at the end of the previous option.

This module imports only the standard library, numpy and onnxruntime (and the
``hdrqn_ros`` package root, which imports no torch), so a robot needs no torch to act.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from hdrqn_ros.deploy.errors import PolicyError
from hdrqn_ros.agents.specs import ALGO_SPECS, STATE_SIZE, stack_subgoal
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.hashing import file_sha256

__all__ = ["POLICY_FILE", "POLICY_FORMAT", "POLICY_VERSION", "STATE_SIZE", "ALGOS", "PolicyError",
           "TensorSpec", "role_io", "stack_subgoal", "OnnxPolicy"]

POLICY_FILE = "policy.json"
POLICY_FORMAT = "hdrqn_ros-policy"
POLICY_VERSION = 1
ALGOS: dict[str, dict] = {algo: {"hierarchical": spec.hierarchical, "recurrent": spec.recurrent,
                               "meta_input": spec.meta_input} for algo, spec in ALGO_SPECS.items()}
""":data:`hdrqn_ros.agents.specs.ALGO_SPECS` as plain dicts."""

LSTMState = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class TensorSpec:
    """One model input or output: ``shape[0]`` is the batch axis (``None``: any size)."""

    name: str
    shape: tuple
    dtype: str  # numpy dtype name: "uint8" or "float32"

    def to_json(self) -> dict:
        return {"name": self.name, "shape": list(self.shape), "dtype": self.dtype}

    @classmethod
    def from_json(cls, data: dict) -> "TensorSpec":
        return cls(str(data["name"]), tuple(data["shape"]), str(data["dtype"]))


def _recurrent(algo: str, role: str) -> bool:
    spec = ALGOS[algo]
    # the hDRQNv2 meta-controller is an LSTM network whatever the sub-controller is
    return spec["recurrent"] or (role == "meta" and spec["meta_input"] == "state")


def role_io(algo: str, role: str, num_actions: int, num_subgoals: int) -> tuple[list[TensorSpec], list[TensorSpec]]:
    """The inputs and outputs the ``role`` model of ``algo`` must have (thesis tables 4.5, 4.6)."""
    if algo not in ALGOS:
        raise PolicyError(f"unknown algo {algo!r}; choose one of {sorted(ALGOS)}")
    spec = ALGOS[algo]
    if role == "sub":
        x = TensorSpec("x", (None, OBS_SIZE, OBS_SIZE, 6 if spec["hierarchical"] else 3), "uint8")
        n = num_actions
    elif role == "meta" and spec["hierarchical"]:
        if spec["meta_input"] == "state":
            x = TensorSpec("x", (None, STATE_SIZE), "float32")
        else:
            x = TensorSpec("x", (None, OBS_SIZE, OBS_SIZE, 3), "uint8")
        n = num_subgoals
    else:
        raise PolicyError(f"{algo} has no {role!r} controller")
    inputs, outputs = [x], [TensorSpec("q", (None, int(n)), "float32")]
    if _recurrent(algo, role):
        inputs += [TensorSpec(k, (None, STATE_SIZE), "float32") for k in ("h", "c")]
        outputs += [TensorSpec(k, (None, STATE_SIZE), "float32") for k in ("h_out", "c_out")]
    return inputs, outputs


def roles_of(algo: str) -> tuple[str, ...]:
    return ("meta", "sub") if ALGOS[algo]["hierarchical"] else ("sub",)


_ORT_TYPES = {"tensor(uint8)": "uint8", "tensor(float)": "float32"}


def _session_options() -> ort.SessionOptions:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1  # one decision of these small networks: threads only cost
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # errors only
    return opts


def _check_session_io(path: Path, kind: str, actual, expected: list[TensorSpec]) -> None:
    """``actual``: onnxruntime NodeArg list; raise PolicyError naming ``path`` on a mismatch."""
    names = [a.name for a in actual]
    if names != [e.name for e in expected]:
        raise PolicyError(f"{path}: {kind} are {names}, expected {[e.name for e in expected]}")
    for arg, spec in zip(actual, expected):
        dtype = _ORT_TYPES.get(arg.type, arg.type)
        if dtype != spec.dtype:
            raise PolicyError(f"{path}: {kind[:-1]} {arg.name!r} has type {dtype}, expected {spec.dtype}")
        shape = list(arg.shape)
        ok = len(shape) == len(spec.shape) and all(
            (want is None and (not isinstance(got, int) or got == 1)) or got == want
            for got, want in zip(shape, spec.shape))
        if not ok:
            want = ["batch" if w is None else w for w in spec.shape]
            raise PolicyError(f"{path}: {kind[:-1]} {arg.name!r} has shape {shape}, expected {want}")


class _RoleModel:
    """One controller's ONNX session and its declared inputs/outputs."""

    def __init__(self, role: str, path: Path, inputs: list[TensorSpec], outputs: list[TensorSpec]):
        self.role, self.path = role, path
        self.inputs, self.outputs = inputs, outputs
        self.recurrent = len(inputs) == 3
        self.x_spec = inputs[0]
        try:
            self.session = ort.InferenceSession(str(path), sess_options=_session_options(),
                                                providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad models
            raise PolicyError(f"{path}: not a loadable ONNX model ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
        _check_session_io(path, "inputs", self.session.get_inputs(), inputs)
        _check_session_io(path, "outputs", self.session.get_outputs(), outputs)
        self.batch_fixed = isinstance(self.session.get_inputs()[0].shape[0], int)
        self.output_names = [o.name for o in outputs]


class OnnxPolicy:
    """The controllers of an exported policy, acting with ONNX Runtime (1 thread, sequential).

    ``q, state = policy.act(role, x, state)`` is the torch network's ``act`` in numpy:
    ``x`` (B, ...) with the batch axis, ``state`` ``(h, c)`` of two float32 (B, 256) arrays
    or ``None`` (zeros) for an LSTM controller, ``None`` for a feed-forward one; returns
    ``q`` float32 (B, n) and the new state (``None`` for a feed-forward controller).
    """

    def __init__(self, directory: Path, meta: dict, models: dict[str, _RoleModel]):
        self.directory = directory
        self.meta_data = meta
        self.models = models
        self.algo: str = meta["algo"]
        self.env: str = meta.get("env", "")
        self.env_kwargs: dict = dict(meta.get("env_kwargs") or {})
        self.num_actions: int = int(meta["num_actions"])
        self.num_subgoals: int = int(meta["num_subgoals"])
        self.meta_input: str | None = meta.get("meta_input")
        self.meta_state: str = meta.get("meta_state", "c")
        self.hierarchical: bool = ALGOS[self.algo]["hierarchical"]

    @property
    def roles(self) -> tuple[str, ...]:
        return tuple(self.models)

    # ---- loading -------------------------------------------------------------------
    @classmethod
    def load(cls, policy_dir: str | Path) -> "OnnxPolicy":
        """Read ``policy_dir/policy.json`` and its models; raises :class:`PolicyError`."""
        directory = Path(policy_dir)
        meta_path = directory / POLICY_FILE
        if not directory.is_dir():
            raise PolicyError(f"policy directory {directory} does not exist")
        if not meta_path.is_file():
            raise PolicyError(f"{meta_path} does not exist: {directory} is not an exported policy "
                              f"(write one with `hdrqn export --checkpoint RUN/checkpoints/last.pt --out {directory}`)")
        try:
            meta = json.loads(meta_path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise PolicyError(f"{meta_path} is not readable JSON ({type(exc).__name__}: {exc})") from None
        models = {role: cls._load_role(directory, meta_path, meta, role) for role in cls._check_meta(meta_path, meta)}
        return cls(directory, meta, models)

    @staticmethod
    def _check_meta(meta_path: Path, meta) -> tuple[str, ...]:
        if not isinstance(meta, dict) or meta.get("format") != POLICY_FORMAT:
            raise PolicyError(f"{meta_path} is not an hdrqn_ros policy (no format {POLICY_FORMAT!r})")
        if meta.get("version") != POLICY_VERSION:
            raise PolicyError(f"{meta_path} has policy version {meta.get('version')!r}, expected {POLICY_VERSION}")
        algo = meta.get("algo")
        if algo not in ALGOS:
            raise PolicyError(f"{meta_path}: unknown algo {algo!r}; expected one of {sorted(ALGOS)}")
        for key in ("num_actions", "num_subgoals"):
            value = meta.get(key)
            if not isinstance(value, int) or isinstance(value, bool) or value < (1 if key == "num_actions" else 0):
                raise PolicyError(f"{meta_path}: {key} must be a positive integer, got {value!r}")
        if meta.get("image_size", OBS_SIZE) != OBS_SIZE:
            raise PolicyError(f"{meta_path}: image_size is {meta.get('image_size')!r}, expected {OBS_SIZE}")
        if meta.get("meta_input") != ALGOS[algo]["meta_input"]:
            raise PolicyError(f"{meta_path}: meta_input is {meta.get('meta_input')!r}, but {algo} has "
                              f"{ALGOS[algo]['meta_input']!r}")
        if meta.get("meta_state", "c") not in ("c", "h"):
            raise PolicyError(f"{meta_path}: meta_state must be 'c' or 'h', got {meta.get('meta_state')!r}")
        roles = roles_of(algo)
        declared = meta.get("roles")
        if not isinstance(declared, dict) or sorted(declared) != sorted(roles):
            got = sorted(declared) if isinstance(declared, dict) else declared
            raise PolicyError(f"{meta_path}: roles are {got!r}, but {algo} has {list(roles)}")
        return roles

    @staticmethod
    def _load_role(directory: Path, meta_path: Path, meta: dict, role: str) -> _RoleModel:
        entry = meta["roles"][role]
        inputs, outputs = role_io(meta["algo"], role, meta["num_actions"], meta["num_subgoals"])
        try:
            declared_in = [TensorSpec.from_json(d) for d in entry["inputs"]]
            declared_out = [TensorSpec.from_json(d) for d in entry["outputs"]]
            file_name, digest = str(entry["file"]), str(entry["sha256"])
        except (KeyError, TypeError, ValueError) as exc:
            raise PolicyError(f"{meta_path}: role {role!r} entry is incomplete ({type(exc).__name__}: {exc})") from None
        for kind, declared, expected in (("inputs", declared_in, inputs), ("outputs", declared_out, outputs)):
            if declared != expected:
                raise PolicyError(f"{meta_path}: {role} {kind} {[d.to_json() for d in declared]} do not fit "
                                  f"{meta['algo']}, expected {[e.to_json() for e in expected]}")
        path = directory / file_name
        if Path(file_name).name != file_name:
            raise PolicyError(f"{meta_path}: {role} file {file_name!r} must be a plain file name in {directory}")
        if not path.is_file():
            raise PolicyError(f"{path} does not exist (the {role} model named in {meta_path})")
        actual = file_sha256(path)
        if actual != digest:
            raise PolicyError(f"{path}: sha256 {actual} does not match {digest} in {meta_path} "
                              f"(the file was changed after export)")
        return _RoleModel(role, path, inputs, outputs)

    # ---- acting --------------------------------------------------------------------
    def _model(self, role: str) -> _RoleModel:
        try:
            return self.models[role]
        except KeyError:
            raise ValueError(f"{self.algo} has no {role!r} controller; roles: {list(self.models)}") from None

    def recurrent(self, role: str) -> bool:
        return self._model(role).recurrent

    def input_spec(self, role: str) -> TensorSpec:
        """``x``'s spec of ``role`` (shape with ``None`` for the batch axis, dtype)."""
        return self._model(role).x_spec

    def initial_state(self, role: str, batch_size: int = 1) -> LSTMState | None:
        """Zeros ``(h, c)`` of (batch_size, 256) float32, or ``None`` for a feed-forward controller."""
        if not self._model(role).recurrent:
            return None
        return np.zeros((batch_size, STATE_SIZE), np.float32), np.zeros((batch_size, STATE_SIZE), np.float32)

    def act(self, role: str, x: np.ndarray, state: LSTMState | None = None) -> tuple[np.ndarray, LSTMState | None]:
        """One step: ``x`` (B, ...) -> ``(q (B, n) float32, new state)``."""
        model = self._model(role)
        spec = model.x_spec
        x = np.asarray(x)
        if x.ndim != len(spec.shape) or x.shape[1:] != spec.shape[1:]:
            raise ValueError(f"{role} input must be (B, {', '.join(map(str, spec.shape[1:]))}), got {x.shape}")
        if spec.dtype == "uint8":
            if x.dtype != np.uint8:
                raise ValueError(f"{role} input must be a uint8 image, got {x.dtype}")
        else:
            x = x.astype(np.float32, copy=False)
        batch = x.shape[0]
        if model.batch_fixed and batch != 1:
            raise ValueError(f"{model.path} was exported for batch 1, got a batch of {batch}")
        feeds = {"x": np.ascontiguousarray(x)}
        if model.recurrent:
            h, c = self.initial_state(role, batch) if state is None else state
            h = np.ascontiguousarray(h, dtype=np.float32)
            c = np.ascontiguousarray(c, dtype=np.float32)
            if h.shape != (batch, STATE_SIZE) or c.shape != (batch, STATE_SIZE):
                raise ValueError(f"state must be (h, c) each of shape ({batch}, {STATE_SIZE}), "
                                 f"got {h.shape} and {c.shape}")
            feeds["h"], feeds["c"] = h, c
            q, h_out, c_out = model.session.run(model.output_names, feeds)
            return q, (h_out, c_out)
        elif state is not None:
            raise ValueError(f"the {role} controller of {self.algo} is feed-forward: its state is None")
        (q,) = model.session.run(model.output_names, feeds)
        return q, None

    def sub_input(self, obs: np.ndarray, subgoal_image: np.ndarray | None = None) -> np.ndarray:
        """(B, 44, 44, 3) observations -> the sub-controller's (B, 44, 44, 3 or 6) input."""
        return stack_subgoal(obs, subgoal_image) if self.hierarchical else obs

    def meta_input_from_sub_state(self, sub_state: LSTMState) -> np.ndarray:
        """hDRQNv2: the meta input (B, 256) from the sub-controller's state at an option's end."""
        return sub_state[1 if self.meta_state == "c" else 0]

    def __repr__(self) -> str:
        return f"OnnxPolicy({str(self.directory)!r}, algo={self.algo!r}, roles={list(self.models)})"
