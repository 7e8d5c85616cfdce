"""Q-networks of hDRQN and its baselines (thesis tables 4.5 and 4.6).

Shapes
------
* Image inputs are ``uint8`` channels-last ``(..., 44, 44, C)``. The network scales
  them to ``[0, 1]`` (``/ 255``) and moves channels first itself. A floating-point image
  is taken as already scaled (still channels-last).
* Vector inputs (the hDRQNv2 meta-controller, which sees a sub-controller LSTM state)
  are float ``(..., F)``.
* ``forward(x, state)``: ``x`` is ``(B, T, ...)``, returns ``q`` of shape ``(B, T, n)``.
* ``act(x, state)``: ``x`` is ``(B, ...)`` (one time step), returns ``q`` of ``(B, n)``.

Recurrent state convention
--------------------------
The state is a tuple ``(h, c)`` of two ``(B, 256)`` tensors (batch first, *no* leading
``num_layers`` axis, unlike ``nn.LSTM``). ``state=None`` means zeros. Both
``forward`` and ``act`` return the state after the last step in the same convention, so
``act``'s output can be fed back into ``act`` or ``forward``. The feed-forward networks
take and return ``None`` in its place, so agents can treat both kinds alike.

Initialisation: Xavier (Glorot) uniform weights for every conv, linear and LSTM weight
matrix; all biases zero (thesis table 4.7).
"""
from __future__ import annotations


import numpy as np
import torch
from torch import Tensor, nn

from hdrqn_ros.agents.lstm_sequence import lstm_sequence
from hdrqn_ros.agents.specs import STATE_SIZE
from hdrqn_ros.envs.domain import OBS_SIZE

__all__ = [
    "FEATURES",
    "lstm_state_size",
    "LSTMState",
    "ConvTrunk",
    "MlpTrunk",
    "DuelingHead",
    "RecurrentQNetwork",
    "FeedForwardQNetwork",
    "make_image_qnet",
    "make_state_qnet",
    "xavier_init_",
]

FEATURES = 256
lstm_state_size = STATE_SIZE

LSTMState = tuple[Tensor, Tensor]


def xavier_init_(module: nn.Module) -> nn.Module:
    """Xavier-uniform weights and zero biases for every Conv2d, Linear and LSTM inside."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.LSTM):
            for name, p in m.named_parameters():
                if name.startswith("weight"):
                    nn.init.xavier_uniform_(p)
                else:
                    nn.init.zeros_(p)
    return module


def _as_tensor(x) -> Tensor:
    return x if isinstance(x, Tensor) else torch.as_tensor(np.asarray(x))


class ConvTrunk(nn.Module):
    """Four VALID 3x3 convs, strides 4, 2, 1, 1, filters 32, 32, 32, 256, ReLU after each.

    ``(N, 44, 44, C)`` uint8 -> 11x11x32 -> 5x5x32 -> 3x3x32 -> 1x1x256 -> ``(N, 256)``.
    """

    def __init__(self, in_channels: int):
        super().__init__()
        if in_channels < 1:
            raise ValueError(f"in_channels must be >= 1, got {in_channels}")
        self.in_channels = int(in_channels)
        self.input_shape = (OBS_SIZE, OBS_SIZE, self.in_channels)
        self.out_features = FEATURES
        self.convs = nn.ModuleList(
            [
                nn.Conv2d(in_channels, 32, 3, stride=4),
                nn.Conv2d(32, 32, 3, stride=2),
                nn.Conv2d(32, 32, 3, stride=1),
                nn.Conv2d(32, FEATURES, 3, stride=1),
            ]
        )
        xavier_init_(self)

    def feature_maps(self, x: Tensor) -> list:
        """Every conv layer's output, channels-first (for inspection and tests)."""
        x = self._prepare(x)
        outs = []
        for conv in self.convs[:-1]:
            x = torch.relu(conv(x))
            outs.append(x)
        # the last conv sees exactly one 3x3 window: it is one matrix product over the 288
        # values of each input (same weights; faster than a convolution call at this shape)
        last = self.convs[-1]
        x = torch.relu(torch.addmm(last.bias, x.flatten(1), last.weight.view(last.out_channels, -1).t()))
        outs.append(x.view(*x.shape, 1, 1))
        return outs

    def _prepare(self, x: Tensor) -> Tensor:
        x = _as_tensor(x)
        if x.dim() != 4 or tuple(x.shape[1:]) != self.input_shape:
            raise ValueError(
                f"ConvTrunk expects (N, {OBS_SIZE}, {OBS_SIZE}, {self.in_channels}) "
                f"channels-last images, got {tuple(x.shape)}"
            )
        if x.dtype == torch.uint8:
            x = x.to(torch.float32).mul_(1.0 / 255.0)
        else:
            x = x.to(torch.float32)
        return x.permute(0, 3, 1, 2)

    def forward(self, x: Tensor) -> Tensor:
        return self.feature_maps(x)[-1].flatten(1)


class MlpTrunk(nn.Module):
    """hDRQNv2 meta-controller feature extractor: FC200-ReLU, FC200-ReLU, FC256 (linear)."""

    def __init__(self, in_features: int = lstm_state_size):
        super().__init__()
        self.in_features = int(in_features)
        self.input_shape = (self.in_features,)
        self.out_features = FEATURES
        self.net = nn.Sequential(
            nn.Linear(in_features, 200),
            nn.ReLU(),
            nn.Linear(200, 200),
            nn.ReLU(),
            nn.Linear(200, FEATURES),
        )
        xavier_init_(self)

    def forward(self, x: Tensor) -> Tensor:
        x = _as_tensor(x)
        if x.dim() != 2 or x.shape[1] != self.in_features:
            raise ValueError(f"MlpTrunk expects (N, {self.in_features}), got {tuple(x.shape)}")
        return self.net(x.to(torch.float32))


class DuelingHead(nn.Module):
    """Split 256 features into halves: first -> advantage (n), second -> value (1).

    ``Q = V + A - mean(A)``.
    """

    def __init__(self, n_outputs: int, in_features: int = FEATURES):
        super().__init__()
        if n_outputs < 1:
            raise ValueError(f"n_outputs must be >= 1, got {n_outputs}")
        if in_features % 2:
            raise ValueError("in_features must be even")
        self.n_outputs = int(n_outputs)
        half = in_features // 2
        self.half = half
        self.advantage = nn.Linear(half, n_outputs)
        self.value = nn.Linear(half, 1)
        xavier_init_(self)

    def advantages(self, x: Tensor) -> Tensor:
        """Mean-centred advantages ``A - mean(A)``, shape ``(..., n)``."""
        a = self.advantage(x[..., : self.half])
        return a - a.mean(dim=-1, keepdim=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.value(x[..., self.half :]) + self.advantages(x)


class RecurrentQNetwork(nn.Module):
    """trunk -> LSTM(256) -> dueling head (DRQN, hDRQN meta and sub-controllers)."""

    recurrent = True

    def __init__(self, trunk: nn.Module, n_outputs: int):
        super().__init__()
        self.trunk = trunk
        self.lstm = nn.LSTM(FEATURES, lstm_state_size, batch_first=True)
        self.head = DuelingHead(n_outputs, lstm_state_size)
        self.n_outputs = int(n_outputs)
        xavier_init_(self.lstm)

    def initial_state(self, batch_size: int, device=None) -> LSTMState:
        z = torch.zeros(batch_size, lstm_state_size, device=device)
        return z, z.clone()

    def _check_state(self, state: LSTMState | None, batch: int, ref: Tensor) -> LSTMState:
        if state is None:
            return self.initial_state(batch, ref.device)
        h, c = state
        if h.shape != (batch, lstm_state_size) or c.shape != (batch, lstm_state_size):
            raise ValueError(
                f"state must be (h, c) each of shape ({batch}, {lstm_state_size}), "
                f"got {tuple(h.shape)} and {tuple(c.shape)}"
            )
        return h, c

    def forward(self, x: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState]:
        """``x`` (B, T, ...) -> ``(q (B, T, n), (h, c))`` with h, c of (B, 256).

        The LSTM runs as :func:`~hdrqn_ros.agents.lstm_sequence.lstm_sequence` (input
        projections of all T steps in one matrix product, a hand-written backward): for the
        short windows of the thesis (n <= 16) this trains faster on a CPU than ``nn.LSTM``'s
        oneDNN kernels or autograd through the unrolled steps, and it is the same function
        (``test_lstm_sequence_equals_torch_nn_lstm`` in test/test_networks.py compares
        outputs and gradients with ``nn.LSTM``, and ``act``'s batch-1 path too).
        """
        x = _as_tensor(x)
        if x.dim() < 3:
            raise ValueError(f"forward expects (B, T, ...) inputs, got {tuple(x.shape)}")
        b, t = x.shape[:2]
        feats = self.trunk(x.reshape(b * t, *x.shape[2:]))
        state = self._check_state(state, b, feats)
        lstm = self.lstm
        out, state = lstm_sequence(feats.view(b, t, -1), state, lstm.weight_ih_l0, lstm.weight_hh_l0,
                                   lstm.bias_ih_l0 + lstm.bias_hh_l0)
        return self.head(out), state

    @staticmethod
    def _gates_to_state(gates: Tensor, c: Tensor) -> LSTMState:
        i, f, g, o = gates.chunk(4, dim=1)
        c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c_new), c_new

    def cell(self, feats: Tensor, state: LSTMState) -> LSTMState:
        """One LSTM step computed with plain torch ops from ``self.lstm``'s weights.

        Avoids ``nn.LSTM``'s slow batch-1 path (oneDNN). Gate order i, f, g, o.
        """
        h, c = state
        lstm = self.lstm
        gates = torch.addmm(lstm.bias_ih_l0, feats, lstm.weight_ih_l0.t())
        gates = gates + torch.addmm(lstm.bias_hh_l0, h, lstm.weight_hh_l0.t())
        return self._gates_to_state(gates, c)

    def act(self, x: Tensor, state: LSTMState | None = None) -> tuple[Tensor, LSTMState]:
        """One step: ``x`` (B, ...) -> ``(q (B, n), (h, c))``. Wrap in ``torch.no_grad()``
        (or ``inference_mode``) when acting."""
        x = _as_tensor(x)
        feats = self.trunk(x)
        h, c = self.cell(feats, self._check_state(state, feats.shape[0], feats))
        return self.head(h), (h, c)


class FeedForwardQNetwork(nn.Module):
    """trunk -> Linear(256, 256)-ReLU -> dueling head (DQN and hDQN baselines).

    Same call signatures as :class:`RecurrentQNetwork`; the state is always ``None``.
    """

    recurrent = False

    def __init__(self, trunk: nn.Module, n_outputs: int):
        super().__init__()
        self.trunk = trunk
        self.fc = nn.Linear(FEATURES, FEATURES)
        self.head = DuelingHead(n_outputs, FEATURES)
        self.n_outputs = int(n_outputs)
        xavier_init_(self.fc)

    def initial_state(self, batch_size: int, device=None) -> None:
        return None

    def forward(self, x: Tensor, state: None = None) -> tuple[Tensor, None]:
        """``x`` (B, T, ...) -> ``(q (B, T, n), None)``."""
        x = _as_tensor(x)
        if x.dim() < 3:
            raise ValueError(f"forward expects (B, T, ...) inputs, got {tuple(x.shape)}")
        b, t = x.shape[:2]
        q = self.head(torch.relu(self.fc(self.trunk(x.reshape(b * t, *x.shape[2:])))))
        return q.view(b, t, self.n_outputs), None

    def act(self, x: Tensor, state: None = None) -> tuple[Tensor, None]:
        """``x`` (B, ...) -> ``(q (B, n), None)``."""
        return self.head(torch.relu(self.fc(self.trunk(_as_tensor(x))))), None


def make_image_qnet(in_channels: int, n_outputs: int, recurrent: bool = True) -> nn.Module:
    """Conv-trunk Q-network on 44x44xC uint8 images.

    hDRQNv1 meta: ``make_image_qnet(3, n_subgoals)``; sub-controller (observation and
    subgoal image stacked): ``make_image_qnet(6, n_actions)``; DRQN: ``(3, n_actions)``;
    DQN / hDQN: ``recurrent=False``.
    """
    trunk = ConvTrunk(in_channels)
    cls = RecurrentQNetwork if recurrent else FeedForwardQNetwork
    return cls(trunk, n_outputs)


def make_state_qnet(
    in_features: int = lstm_state_size, n_outputs: int = 2, recurrent: bool = True
) -> nn.Module:
    """hDRQNv2 meta-controller: MLP 256->200->200->256, LSTM 256, dueling head."""
    trunk = MlpTrunk(in_features)
    cls = RecurrentQNetwork if recurrent else FeedForwardQNetwork
    return cls(trunk, n_outputs)
