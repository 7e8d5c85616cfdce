"""One Q-learning controller: online and target network, Adam, episodic replay, and the
Double DQN update on bootstrapped random windows (thesis Algorithms 3 and 4).

The whole update is :meth:`Controller.update`; acting is :meth:`Controller.act`.
"""
from __future__ import annotations

import copy
from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import nn

from hdrqn_ros.agents.replay import EpisodeReplay, SequenceBatch
from hdrqn_ros.config import ControllerConfig


class TrainingDiverged(RuntimeError):
    """A loss or gradient became NaN or infinite."""


InputBuilder = Callable[[SequenceBatch], np.ndarray]
"""Turns a sampled window into the network input ``(B, n+1, ...)``."""


def meta_transition(option_extrinsic: float, terminated: bool, option_steps: int,
                    next_place: int) -> tuple[float, int, bool, int]:
    """The meta-controller's transition for an option that just ended, as replay stores it:
    ``(reward, option_steps, terminal, next_invalid)``.

    * reward: the option's summed extrinsic reward;
    * option_steps: the option's length k in primitive steps (the target discounts by
      ``gamma ** k`` with ``smdp_discount``, else by ``gamma``: :meth:`Controller.update`);
    * terminal: the episode terminated (a time limit is not terminal: it bootstraps);
    * next_invalid: ``next_place``, the subgoal whose place the next decision starts from
      (the meta-controller may not pick it), or -1 (``NO_SUBGOAL``).
    """
    return option_extrinsic, option_steps, terminated, next_place


INDEX_BUCKETS = 4
"""Steps by index in their episode for :attr:`UpdateStats.by_index`: 0, 1, 2 and 3 or later."""


class UpdateStats(NamedTuple):
    """What one :meth:`Controller.update` saw, as detached tensors on the controller's
    device (read them as floats only when needed: each read waits for the device)."""

    td_loss: torch.Tensor  # the loss minimised
    q_taken: torch.Tensor  # mean Q(s_t, a_t) of the online net over the loss steps
    target: torch.Tensor  # mean Double DQN target y_t over the loss steps
    grad_norm: torch.Tensor  # the gradients' total 2-norm before clipping
    by_index: torch.Tensor | None = None
    """(3, INDEX_BUCKETS) sums over the loss steps by their index in the episode (the
    meta-controller's option index): [count, Q(s_t, a_t), return obtained from t]; only for
    a controller made with ``track_returns``."""


class Controller:
    """A meta-controller or a sub-controller (or the single controller of DQN/DRQN).

    ``net`` maps ``(B, T, ...)`` inputs to Q-values ``(B, T, n_outputs)``; ``build_input``
    assembles a sampled window into that input (e.g. observation + subgoal image).
    Replay fields used (read as :class:`~hdrqn_ros.agents.replay.ReplaySamples`):
    ``action`` (int), ``reward`` (float32), ``terminal`` (bool, no bootstrap) and,
    optionally, ``next_invalid`` (int, -1 for none): a choice the next step may not take
    (the meta-controller cannot pick the subgoal it stands on), left out of the target's
    max, and ``option_steps`` (int, the option's length k in primitive steps). The discount
    is not stored: the target reads ``cfg.gamma`` at every update, raised to the power
    ``option_steps`` with ``smdp_discount`` (eq. 3.5; the meta-controller). A
    sub-controller (or flat) step stores the intrinsic (flat: classical) reward and
    ``terminal`` = :func:`~hdrqn_ros.envs.critic.sub_controller_terminal`; a meta step is
    :func:`meta_transition`.
    """

    def __init__(self, name: str, net: nn.Module, cfg: ControllerConfig, build_input: InputBuilder,
                 device: str | torch.device = "cpu", seed: int = 0, smdp_discount: bool = False,
                 track_returns: bool = False):
        self.name = name
        self.track_returns = track_returns
        self.cfg = cfg
        self.smdp_discount = smdp_discount
        self.device = torch.device(device)
        self.online = net.to(self.device)
        self.target = copy.deepcopy(net).to(self.device).requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=cfg.lr, fused=True)
        self.replay = EpisodeReplay(cfg.replay_episodes, capacity_bytes=cfg.replay_bytes, seed=seed)
        self.build_input = build_input
        self.recurrent = bool(getattr(net, "recurrent", False))
        # a feed-forward network learns from single transitions (DQN); an LSTM from windows of n,
        # or from whole segments (None: episodes for the meta-controller, options for the sub)
        self.seq_len = (None if cfg.sampling == "whole" else cfg.seq_len) if self.recurrent else 1
        self.updates = 0
        self._online_params = list(self.online.parameters())
        self._target_params = list(self.target.parameters())

    @property
    def n_outputs(self) -> int:
        return self.online.n_outputs

    def initial_state(self, batch_size: int):
        return self.online.initial_state(batch_size, self.device)

    @torch.no_grad()
    def act(self, x: np.ndarray, state):
        """One step for a batch: ``x`` (B, ...) -> (Q-values (B, n) numpy, new state)."""
        q, state = self.online.act(torch.as_tensor(x, device=self.device), state)
        return q.cpu().numpy(), state

    def update(self) -> UpdateStats:
        """Sample windows, take one Adam step on the Double DQN loss, soft-update the target.

        Loss only on each window's ``mask`` steps (windows: the last n/2; whole segments:
        all). Returns what the update saw (:class:`UpdateStats`). Raises
        :class:`TrainingDiverged` when the loss is not finite.
        """
        cfg = self.cfg
        batch = self.replay.sample_transitions(cfg.batch_size, self.seq_len, self.build_input, self.device,
                                               history=cfg.window_history,
                                               gamma=cfg.gamma if self.track_returns else None,
                                               smdp_discount=self.smdp_discount)

        # ALGO LOGIC: the Double DQN target on a window of n steps (thesis Algorithms 3, 4)
        #   y_t = r_t + d_t * (1 - terminal_t) * Q_target(s_{t+1}, argmax_a Q(s_{t+1}, a))
        # where d_t = gamma (this controller's cfg.gamma), or gamma ** k_t with smdp_discount
        # (eq. 3.5: k_t = option_steps, the option's length in primitive steps); r_t, k_t,
        # terminal_t and the invalid choice at s_{t+1} are what the replay stored for step t
        # (``meta_transition`` above and training/episodes.py); s_{t+1} = batch.obs[:, t + 1].
        # With time_limit "terminal" an episode's last step is terminal even when the step
        # limit, not the task, ended it.
        gamma = cfg.gamma
        discount = gamma ** batch.option_steps if self.smdp_discount else gamma
        terminal = batch.terminal
        if cfg.time_limit == "terminal":
            terminal = torch.maximum(terminal, batch.episode_end.float())
        q, _ = self.online(batch.obs)  # (B, n+1, A): Q(s_t, .) for every input of the window
        q_taken = q[:, :-1].gather(-1, batch.action.unsqueeze(-1)).squeeze(-1)  # Q(s_t, a_t)
        with torch.no_grad():
            q_target, _ = self.target(batch.obs)
            q_next = q[:, 1:]  # the online net picks the next action ...
            if batch.next_invalid is not None:  # ... never the invalid choice
                hit = torch.arange(q_next.shape[-1], device=self.device) == batch.next_invalid.unsqueeze(-1)
                q_next = q_next.masked_fill(hit, float("-inf"))
            next_action = q_next.argmax(-1, keepdim=True)
            next_value = q_target[:, 1:].gather(-1, next_action).squeeze(-1)  # ... the target net values it
            y = batch.reward + discount * (1 - terminal) * next_value
        per_step = (q_taken - y).pow(2) if cfg.loss == "mse" else \
            nn.functional.smooth_l1_loss(q_taken, y, reduction="none")
        loss_steps = batch.mask.sum().clamp(min=1)
        loss = (per_step * batch.mask).sum() / loss_steps
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"{self.name} loss is {loss.item()} at update {self.updates}")

        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # without grad_clip an infinite bound: the norm is measured, the gradients stay as they are
        max_norm = float("inf") if cfg.grad_clip is None else cfg.grad_clip
        grad_norm = nn.utils.clip_grad_norm_(self._online_params, max_norm, foreach=True)
        self.optimizer.step()
        self.soft_update()
        self.updates += 1
        with torch.no_grad():
            by_index = self._by_index(q_taken.detach(), batch) if self.track_returns else None
            return UpdateStats(td_loss=loss.detach(), q_taken=(q_taken * batch.mask).sum() / loss_steps,
                               target=(y * batch.mask).sum() / loss_steps, grad_norm=grad_norm, by_index=by_index)

    def _by_index(self, q_taken: torch.Tensor, batch) -> torch.Tensor:
        """:attr:`UpdateStats.by_index` of the loss steps: Q(s_t, a_t) (B, n) and the return
        obtained, summed by the step's index in its episode."""
        steps = batch.mask.shape[1]
        index = (batch.start.unsqueeze(1) + torch.arange(steps, device=self.device)).clamp(max=INDEX_BUCKETS - 1)
        mask = batch.mask
        values = torch.stack([torch.ones_like(q_taken), q_taken, batch.return_to_go])[:, mask]  # (3, loss steps)
        return torch.zeros(3, INDEX_BUCKETS, device=self.device).index_add_(1, index[mask], values)

    @torch.no_grad()
    def soft_update(self) -> None:
        """theta' <- tau * theta + (1 - tau) * theta'."""
        torch._foreach_lerp_(self._target_params, self._online_params, self.cfg.tau)

    def state_dict(self) -> dict:
        return {"online": self.online.state_dict(), "target": self.target.state_dict(),
                "optimizer": self.optimizer.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.online.load_state_dict(state["online"])
        self.target.load_state_dict(state["target"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.updates = int(state["updates"])

