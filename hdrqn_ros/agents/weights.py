"""Network weights as bytes for the wire: safetensors (tensors only, never pickle)."""
from __future__ import annotations

import torch
from safetensors import SafetensorError
from safetensors.torch import load as _load
from safetensors.torch import save as _save


class WeightsError(ValueError):
    """Bytes that are not safetensors weights for the expected network."""


def encode_weights(net: torch.nn.Module) -> bytes:
    """``net``'s parameters and buffers as safetensors bytes (CPU, contiguous)."""
    return _save({k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()})


def load_weights(net: torch.nn.Module, data: bytes) -> None:
    """Load safetensors ``data`` into ``net``; every tensor name and shape must match."""
    try:
        state = _load(bytes(data))
    except (SafetensorError, ValueError, OverflowError) as exc:
        raise WeightsError(f"not safetensors weights: {exc}") from None
    expected = net.state_dict()
    if set(state) != set(expected):
        missing, extra = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
        raise WeightsError(f"weights do not fit the network (missing {missing[:3]}, unexpected {extra[:3]})")
    for name, tensor in state.items():
        if tensor.shape != expected[name].shape or tensor.dtype != expected[name].dtype:
            raise WeightsError(f"weights for {name}: {tuple(tensor.shape)} {tensor.dtype}, network expects "
                               f"{tuple(expected[name].shape)} {expected[name].dtype}")
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            raise WeightsError(f"weights for {name} hold NaN or inf")
    net.load_state_dict(state)
