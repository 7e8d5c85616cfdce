"""The hierarchical epsilon-greedy policy of Algorithm 1 (lines 10-24), for N environments.

:class:`HierarchicalPolicy` holds the acting state of ``N`` environments and applies the
rules of acting once, for the trainer's in-process rollout (``N`` environments, both
controllers) and for the controller nodes (``N = 1``, one controller each):

* a new episode zeroes both LSTM states (line 11); a new option zeroes the
  sub-controller's (line 13);
* the meta-controller may not choose the subgoal whose place the agent stands on (a
  subgoal is reached "from the other subgoals", thesis 4.1.1);
* the meta input is the observation (hDRQNv1, hDQN) or, for hDRQNv2, the sub-controller's
  LSTM state (c or h) at the end of the previous option, zeros at an episode's start;
* both levels explore epsilon-greedily (:func:`epsilon_greedy`).

Per step the caller runs ``choose_subgoals`` (rows that need an option), ``act``, steps the
environments, ``end_options`` (rows whose option ended) and ``start_episodes`` (rows that
were reset). ``rows`` arguments are ``(N,)`` bool masks. A controller is anything with
``act(x (B, ...), state) -> (Q-values (B, n) numpy, new state)`` and ``initial_state(B)``
(:class:`~hdrqn_ros.agents.controller.Controller`, the nodes' acting networks); LSTM
states are ``(h, c)`` pairs of ``(N, 256)`` torch tensors (torch networks) or float32
numpy arrays (an exported ONNX policy, :mod:`hdrqn_ros.deploy`), ``None`` for
feed-forward networks. This module imports no torch: given numpy states it runs without
it (torch is imported only to index a torch state, which means torch is loaded anyway).

:class:`StepRecord` is what one step of N environments produced, for replay and recording.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from hdrqn_ros.agents.specs import STATE_SIZE
from hdrqn_ros.envs.domain import NO_SUBGOAL, StepBatch


def epsilon_greedy(q: np.ndarray, eps: float, rng: np.random.Generator,
                   invalid: np.ndarray | None = None) -> np.ndarray:
    """(B, n) Q-values -> (B,) int64 actions: random with probability ``eps``, else argmax.

    ``invalid`` (B,) int: one choice per row that may not be taken (-1: none).
    """
    b, n = q.shape
    explore = rng.random(b) < eps
    if invalid is None:
        return np.where(explore, rng.integers(0, n, size=b), q.argmax(axis=1))
    masked = np.where(np.arange(n) == invalid[:, None], -np.inf, q)
    has = invalid >= 0
    random_choice = rng.integers(0, n - has.astype(np.int64), size=b)  # uniform over the valid choices
    random_choice += has & (random_choice >= invalid)
    return np.where(explore, random_choice, masked.argmax(axis=1))


@dataclass
class StepRecord:
    """One primitive step of N environments. Arrays have N rows."""

    obs: np.ndarray  # (N, 44, 44, 3) observation the action was taken on
    new_option: np.ndarray  # (N,) bool: a subgoal was chosen before this step
    meta_input: np.ndarray | None  # (N, ...) meta input at the decision (rows of new_option)
    subgoal: np.ndarray  # (N,) int, -1 for flat agents
    subgoal_image: np.ndarray  # (N, 44, 44, 3)
    action: np.ndarray  # (N,) int
    env: StepBatch  # what the environments reported
    intrinsic: np.ndarray  # (N,) float32
    option_done: np.ndarray  # (N,) bool
    sub_terminal: np.ndarray  # (N,) bool: no bootstrap for the sub-controller (see critic.sub_controller_terminal)
    option_extrinsic: np.ndarray  # (N,) float32: extrinsic summed over the option (at option end)
    option_steps: np.ndarray  # (N,) int: option length (at option end)
    meta_next_input: np.ndarray | None  # (N, ...) meta input after the option (at option end)
    all_subgoal_images: np.ndarray | None = None  # (N, S*44, 44, 3) every subgoal's image at the
    # decision, stacked (rows of new_option); only from a rollout made with record_subgoal_images


class ActingController(Protocol):
    """What the policy needs of a controller (see the module docstring)."""

    def act(self, x: np.ndarray, state): ...

    def initial_state(self, batch_size: int): ...


def _index_for(array, index: np.ndarray):
    """``index`` (a numpy bool mask or int array) as ``array`` takes it: itself for a numpy
    array, a tensor on ``array``'s device for a torch tensor."""
    if isinstance(array, np.ndarray):
        return index
    import torch  # a torch state: torch is already loaded

    return torch.as_tensor(index, device=array.device)


def _zeroed(net: ActingController, state, rows: np.ndarray):
    """``state`` with the rows of ``rows`` (N,) bool zeroed: in place, or a fresh zero state
    when every row is (the nodes' N = 1)."""
    if state is None or not rows.any():
        return state
    if rows.all():
        return net.initial_state(len(rows))
    mask = _index_for(state[0], rows)
    for part in state:
        part[mask] = 0.0
    return state


class HierarchicalPolicy:
    """The acting state of N environments and the rules that change it.

    ``sub``/``meta``: the two controllers; either may be ``None`` (flat agents have no
    meta-controller; each controller node holds one level). ``meta_input``: the algorithm's
    (``"image"``, ``"state"`` for hDRQNv2, ``None`` for flat agents); ``meta_state``: which
    sub LSTM state hDRQNv2's meta-controller reads, ``"c"`` or ``"h"``.

    State: ``sub_state``, ``meta_state`` (LSTM states or ``None``); ``subgoal`` (N,) int64,
    each option's subgoal (-1 before the first); ``place`` (N,) int64, the subgoal each
    environment stood on when its option ended (``NO_SUBGOAL``: none), not a valid next
    choice; ``last_sub_state`` (N, 256) float32, hDRQNv2's next meta input.
    """

    def __init__(self, num_envs: int, sub: ActingController | None, meta: ActingController | None = None,
                 meta_input: Literal["image", "state"] | None = None, meta_state: str = "c"):
        self.num_envs = num_envs
        self.sub, self.meta = sub, meta
        self.meta_input = meta_input
        self.state_index = 1 if meta_state == "c" else 0  # (h, c)[state_index]
        self.sub_state = sub.initial_state(num_envs) if sub is not None else None
        self.meta_state = meta.initial_state(num_envs) if meta is not None else None
        self.subgoal = np.full(num_envs, -1, np.int64)
        self.place = np.full(num_envs, NO_SUBGOAL, np.int64)
        self.last_sub_state = np.zeros((num_envs, STATE_SIZE), np.float32)

    def start_episodes(self, rows: np.ndarray) -> None:
        """New episodes in ``rows``: h^M, h^S <- 0, no place, hDRQNv2's meta input zeros."""
        if not rows.any():
            return
        self.place[rows] = NO_SUBGOAL
        self.last_sub_state[rows] = 0.0
        self.meta_state = _zeroed(self.meta, self.meta_state, rows)
        self.sub_state = _zeroed(self.sub, self.sub_state, rows)

    def choose_subgoals(self, rows: np.ndarray, obs: np.ndarray | None, eps: float,
                        rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """The meta-controller starts an option in each of ``rows`` (needs at least one).

        ``obs`` (N, 44, 44, 3) uint8 observations (unused for hDRQNv2, may be ``None``).
        Returns the subgoals (K,) int64 and the meta inputs they were chosen on (K, ...),
        K = ``rows.sum()``, in row order. Draws from ``rng`` as one :func:`epsilon_greedy`.
        """
        indices = np.flatnonzero(rows)
        x = self.last_sub_state[indices] if self.meta_input == "state" else obs[indices]
        if len(indices) == self.num_envs:
            q, self.meta_state = self.meta.act(x, self.meta_state)
        else:
            state = None if self.meta_state is None else tuple(part[indices] for part in self.meta_state)
            q, new_state = self.meta.act(x, state)
            if new_state is not None:
                for part, new in zip(self.meta_state, new_state):
                    part[_index_for(part, indices)] = new
        subgoals = epsilon_greedy(q, eps, rng, invalid=self.place[indices])
        self.start_options(rows, subgoals)
        return subgoals, x

    def start_options(self, rows: np.ndarray, subgoals: np.ndarray) -> None:
        """Options towards ``subgoals`` (K,) start in ``rows``: h^S <- 0 there. Called by
        :meth:`choose_subgoals`, or directly where the subgoal was chosen elsewhere."""
        self.subgoal[rows] = subgoals
        self.sub_state = _zeroed(self.sub, self.sub_state, rows)

    def act(self, x: np.ndarray, eps: float, rng: np.random.Generator) -> np.ndarray:
        """One primitive step of every environment: sub-controller inputs ``x`` (N, 44, 44, 3
        or 6) -> (N,) int64 actions; advances ``sub_state``. One :func:`epsilon_greedy` draw."""
        q, self.sub_state = self.sub.act(x, self.sub_state)
        return epsilon_greedy(q, eps, rng)

    def sub_end_state(self, rows: np.ndarray | None = None) -> np.ndarray:
        """The sub-controller's LSTM state that hDRQNv2's meta-controller reads (c or h):
        (N, 256) float32, or (K, 256) for ``rows``; shares memory with ``sub_state`` when
        on the CPU (or numpy) and ``rows`` is ``None``."""
        state = self.sub_state[self.state_index]
        if rows is not None:
            state = state[_index_for(state, rows)]
        return state if isinstance(state, np.ndarray) else state.cpu().numpy()

    def end_options(self, rows: np.ndarray, at_subgoal: np.ndarray, sub_end_state: np.ndarray | None = None) -> None:
        """The options in ``rows`` ended this step, standing on ``at_subgoal`` (N,) int
        (``NO_SUBGOAL``: none): remember the place and, for hDRQNv2, the sub LSTM state as
        the next meta input: ``sub_end_state`` (K, 256) where the sub-controller runs
        elsewhere (the meta-controller node), else :meth:`sub_end_state`."""
        self.place[rows] = at_subgoal[rows]
        if self.meta_input == "state" and rows.any():
            self.last_sub_state[rows] = self.sub_end_state(rows) if sub_end_state is None else sub_end_state

    def meta_input_after(self, obs: np.ndarray) -> np.ndarray:
        """(N, ...) copy of the meta inputs after :meth:`end_options`: hDRQNv2's stored sub
        states, else ``obs`` (N, 44, 44, 3), the observations after the step."""
        return self.last_sub_state.copy() if self.meta_input == "state" else obs.copy()
