"""Export a checkpoint's acting networks to ONNX for torch-free deployment.

``export_policy(RUN/checkpoints/last.pt, OUT)`` writes, into ``OUT``:

* ``sub.onnx`` (every algorithm) and ``meta.onnx`` (hDRQNv1/v2, hDQN): each computes the
  online network's ``act(x, state)``, one time step, the LSTM state ``(h, c)`` as explicit
  inputs ``h``, ``c`` and outputs ``h_out``, ``c_out`` (a feed-forward network has ``x``
  -> ``q`` only); the batch axis is dynamic;
* ``policy.json``: algo, env id and options, ``num_actions``, ``num_subgoals``, image
  size, the meta input kind ("state"/"image"), which sub LSTM state feeds the hDRQNv2
  meta-controller (``meta_state``), each model's file, inputs/outputs and sha256, the
  package version and the source checkpoint's progress.

Read it back with :class:`hdrqn_ros.deploy.OnnxPolicy` (numpy + onnxruntime, no torch).
The exporter is the legacy TorchScript-based ``torch.onnx.export`` (``dynamo=False``):
it traces ``act`` as it runs, which is the acting path exactly (its Python shape checks
become constants for the traced shapes; the batch axis stays symbolic).
"""
from __future__ import annotations

import io
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

import hdrqn_ros
from hdrqn_ros.agents.algorithms import ALGO_SPECS, make_network
from hdrqn_ros.config import TrainConfig
from hdrqn_ros.deploy.onnx_policy import (POLICY_FILE, POLICY_FORMAT, POLICY_VERSION, STATE_SIZE,
                                          TensorSpec, role_io, roles_of)
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.hashing import file_sha256
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint

__all__ = ["OPSET", "ExportError", "ActStep", "export_policy", "export_network", "load_acting_networks"]

OPSET = 17
VERIFY_TOLERANCE = 1e-4
"""Largest |ONNX Runtime - torch| accepted by the check that ``export_policy`` runs on
random inputs after writing each model."""


class ExportError(ValueError):
    """A model could not be exported, or the exported model does not compute what torch does."""


class ActStep(nn.Module):
    """``net.act`` as a module with flat tensor arguments, the function that is exported:
    ``(x, h, c) -> (q, h_out, c_out)`` for an LSTM network, ``x -> q`` otherwise."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net
        self.recurrent = bool(getattr(net, "recurrent", False))

    def forward(self, x, h=None, c=None):
        if self.recurrent:
            q, (h_out, c_out) = self.net.act(x, (h, c))
            return q, h_out, c_out
        q, _ = self.net.act(x, None)
        return q


def _example_inputs(inputs: list[TensorSpec], batch: int, rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for spec in inputs:
        shape = (batch, *spec.shape[1:])
        if spec.dtype == "uint8":
            out.append(rng.integers(0, 256, size=shape, dtype=np.uint8))
        else:
            out.append(rng.standard_normal(shape).astype(np.float32))
    return out


def export_network(net: nn.Module, inputs: list[TensorSpec], outputs: list[TensorSpec], path: str | Path) -> None:
    """Write ``net.act`` to ``path`` as ONNX with the given input/output names; batch axis dynamic."""
    net = net.eval()
    example = [torch.as_tensor(a) for a in _example_inputs(inputs, 1, np.random.default_rng(0))]
    buffer = io.BytesIO()
    with warnings.catch_warnings(), torch.inference_mode(False), torch.no_grad():
        # the tracer warns that act's shape checks become constants, and that the
        # TorchScript exporter is the legacy one: both are expected here
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            torch.onnx.export(ActStep(net), tuple(example), buffer, dynamo=False, opset_version=OPSET,
                              input_names=[s.name for s in inputs], output_names=[s.name for s in outputs],
                              dynamic_axes={s.name: {0: "batch"} for s in inputs + outputs})
        except Exception as exc:
            raise ExportError(f"torch.onnx.export failed for {path}: {type(exc).__name__}: {exc}") from exc
    Path(path).write_bytes(buffer.getvalue())


def verify_network(net: nn.Module, inputs: list[TensorSpec], path: str | Path, batch: int = 2, seed: int = 0) -> float:
    """Max |ONNX Runtime - torch act| over all outputs on random inputs; ExportError above
    :data:`VERIFY_TOLERANCE`. Needs onnxruntime (the ``deploy`` extra)."""
    import onnxruntime as ort

    arrays = _example_inputs(inputs, batch, np.random.default_rng(seed))
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {s.name: a for s, a in zip(inputs, arrays)})
    with torch.inference_mode():
        want = ActStep(net)(*[torch.as_tensor(a) for a in arrays])
    want = [t.numpy() for t in (want if isinstance(want, tuple) else (want,))]
    err = max(float(np.abs(g - w).max()) for g, w in zip(got, want))
    if not err <= VERIFY_TOLERANCE:
        raise ExportError(f"{path}: ONNX Runtime differs from torch by {err:.3g} (> {VERIFY_TOLERANCE})")
    return err


def load_acting_networks(checkpoint_path: str | Path) -> tuple[TrainConfig, dict, dict[str, nn.Module], int, int]:
    """``(config, payload, {role: online network in eval mode}, num_actions, num_subgoals)``
    of a checkpoint, the networks built as the controller nodes build them."""
    payload = load_checkpoint(checkpoint_path)
    try:
        cfg = TrainConfig.model_validate(payload["config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{checkpoint_path} holds no valid training config: {str(exc).splitlines()[0]}") from None
    probe = make_batch(cfg.env, 1, **cfg.env_kwargs)
    num_actions, num_subgoals = probe.num_actions, probe.num_subgoals
    nets = {}
    for role in roles_of(cfg.algo):
        net = make_network(cfg.algo, role, num_actions, num_subgoals)
        try:
            net.load_state_dict(payload["agent"][role]["online"])
        except (KeyError, TypeError, RuntimeError) as exc:
            raise CheckpointError(f"{checkpoint_path} has no {role} network for {cfg.algo}: "
                                  f"{str(exc).splitlines()[0]}") from None
        nets[role] = net.eval()
    return cfg, payload, nets, num_actions, num_subgoals


def export_policy(checkpoint_path: str | Path, out_dir: str | Path, verify: bool = True) -> Path:
    """Export the checkpoint's acting networks and ``policy.json`` into ``out_dir``
    (created if needed; existing model files there are replaced). Returns ``out_dir``,
    the policy directory :meth:`OnnxPolicy.load` reads. ``verify``: compare ONNX Runtime with torch on random inputs.

    Raises :class:`CheckpointError` for a bad checkpoint, :class:`ExportError` when a
    model does not export or does not match torch."""
    checkpoint_path = Path(checkpoint_path)
    out = Path(out_dir)
    cfg, payload, nets, num_actions, num_subgoals = load_acting_networks(checkpoint_path)
    out.mkdir(parents=True, exist_ok=True)
    spec = ALGO_SPECS[cfg.algo]
    roles = {}
    for role, net in nets.items():
        inputs, outputs = role_io(cfg.algo, role, num_actions, num_subgoals)
        file_name = f"{role}.onnx"
        path = out / file_name
        export_network(net, inputs, outputs, path)
        entry = {"file": file_name, "sha256": file_sha256(path), "recurrent": bool(net.recurrent),
                 "inputs": [s.to_json() for s in inputs], "outputs": [s.to_json() for s in outputs]}
        if verify:
            entry["verified_max_abs_error"] = verify_network(net, inputs, path)
        roles[role] = entry
    progress = payload.get("progress") or {}
    meta = {
        "format": POLICY_FORMAT,
        "version": POLICY_VERSION,
        "package_version": hdrqn_ros.__version__,
        "algo": cfg.algo,
        "env": cfg.env,
        "env_kwargs": cfg.env_kwargs,
        "num_actions": int(num_actions),
        "num_subgoals": int(num_subgoals),
        "image_size": OBS_SIZE,
        "state_size": STATE_SIZE,
        "meta_input": spec.meta_input,
        "meta_state": cfg.meta_state,
        "opset": OPSET,
        "torch_version": torch.__version__,
        "checkpoint": {"file": checkpoint_path.name,
                       **{k: progress[k] for k in ("episodes", "env_steps") if k in progress}},
        "roles": roles,
    }
    target = out / POLICY_FILE
    fd, tmp = tempfile.mkstemp(dir=out, prefix=f".{POLICY_FILE}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(meta, f, indent=2)
            f.write("\n")
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600; the policy is meant to be copied and shared
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out
