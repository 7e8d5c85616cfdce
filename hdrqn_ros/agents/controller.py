"""One Q-learning controller: online and target network, Adam, episodic replay, and the
Double DQN update on bootstrapped random windows (thesis Algorithms 3 and 4).

The whole update is :meth:`Controller.update`; acting is :meth:`Controller.act`.
"""
from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import torch
from torch import nn

from hdrqn_ros.agents.replay import EpisodeReplay, SequenceBatch
from hdrqn_ros.config import ControllerConfig


class TrainingDiverged(RuntimeError):
    """A loss or gradient became NaN or infinite."""


InputBuilder = Callable[[SequenceBatch], np.ndarray]
"""Turns a sampled window into the network input ``(B, n+1, ...)``."""


def meta_transition(option_extrinsic: float, terminated: bool, option_steps: int, next_place: int,
                    gamma: float, smdp_discount: bool) -> tuple[float, float, bool, int]:
    """The meta-controller's transition for an option that just ended, as its target reads
    it: ``(reward, discount, terminal, next_invalid)``.

    * reward: the option's summed extrinsic reward;
    * discount: ``gamma ** option_steps`` with ``smdp_discount`` (the SMDP option of k steps),
      else ``gamma`` (the thesis: one meta step per option);
    * terminal: the episode terminated (a time limit is not terminal: it bootstraps);
    * next_invalid: ``next_place``, the subgoal whose place the next decision starts from
      (the meta-controller may not pick it), or -1 (``NO_SUBGOAL``).
    """
    discount = gamma ** option_steps if smdp_discount else gamma
    return option_extrinsic, discount, terminated, next_place


class Controller:
    """A meta-controller or a sub-controller (or the single controller of DQN/DRQN).

    ``net`` maps ``(B, T, ...)`` inputs to Q-values ``(B, T, n_outputs)``; ``build_input``
    assembles a sampled window into that input (e.g. observation + subgoal image).
    Replay fields used (read as :class:`~hdrqn_ros.agents.replay.ReplaySamples`):
    ``action`` (int), ``reward`` (float32), ``terminal`` (bool, no bootstrap), ``discount``
    (float32, gamma or gamma**k) and, optionally, ``next_invalid`` (int, -1 for none): a
    choice the next step may not take (the meta-controller cannot pick the subgoal it
    stands on), left out of the target's max. A sub-controller (or flat) step stores the
    intrinsic (flat: classical) reward, ``terminal`` =
    :func:`~hdrqn_ros.critic.sub_controller_terminal` and the sub gamma; a meta step is
    :func:`meta_transition`.
    """

    def __init__(self, name: str, net: nn.Module, cfg: ControllerConfig, build_input: InputBuilder,
                 device: str | torch.device = "cpu", seed: int = 0):
        self.name = name
        self.cfg = cfg
        self.device = torch.device(device)
        self.online = net.to(self.device)
        self.target = copy.deepcopy(net).to(self.device).requires_grad_(False)
        self.optimizer = torch.optim.Adam(self.online.parameters(), lr=cfg.lr, fused=True)
        self.replay = EpisodeReplay(cfg.replay_episodes, capacity_bytes=cfg.replay_bytes, seed=seed)
        self.build_input = build_input
        self.recurrent = bool(getattr(net, "recurrent", False))
        # a feed-forward network learns from single transitions (DQN); an LSTM from windows of n
        self.seq_len = cfg.seq_len if self.recurrent else 1
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

    def update(self) -> float:
        """Sample windows, take one Adam step on the Double DQN loss, soft-update the target.

        Loss only on each window's ``mask`` steps (the last n/2). Returns the loss.
        Raises :class:`TrainingDiverged` when the loss is not finite.
        """
        batch = self.replay.sample_transitions(self.cfg.batch_size, self.seq_len, self.build_input, self.device,
                                               history=self.cfg.window_history)

        # ALGO LOGIC: the Double DQN target on a window of n steps (thesis Algorithms 3, 4)
        #   y_t = r_t + discount_t * (1 - terminal_t) * Q_target(s_{t+1}, argmax_a Q(s_{t+1}, a))
        # where r_t, discount_t (gamma, or gamma**k after an option of k steps), terminal_t and
        # the invalid choice at s_{t+1} are what the replay stored for step t (see
        # ``meta_transition`` below and training/episodes.py); s_{t+1} = batch.obs[:, t + 1].
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
            y = batch.reward + batch.discount * (1 - batch.terminal) * next_value
        per_step = (q_taken - y).pow(2) if self.cfg.loss == "mse" else \
            nn.functional.smooth_l1_loss(q_taken, y, reduction="none")
        loss = (per_step * batch.mask).sum() / batch.mask.sum().clamp(min=1)
        if not torch.isfinite(loss):
            raise TrainingDiverged(f"{self.name} loss is {loss.item()} at update {self.updates}")

        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.cfg.grad_clip is not None:
            nn.utils.clip_grad_norm_(self._online_params, self.cfg.grad_clip, foreach=True)
        self.optimizer.step()
        self.soft_update()
        self.updates += 1
        return float(loss.detach())

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

