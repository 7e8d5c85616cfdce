"""Episodic experience replay for Bootstrapped Random Updates (thesis section 3.4).

The replay holds whole episodes. A minibatch picks ``batch_size`` episodes uniformly at
random (with replacement); in each it begins at a uniformly random step ("we begin at a
random index and select a sequence of n transitions") and takes up to ``seq_len`` steps,
cut at the end of that step's segment (shorter windows are right-padded, see ``valid``).
Training starts every window from a zero LSTM state and puts the loss only on the
window's last valid steps (``loss_mask``; the DRQN trick of thesis 3.4: the last ``n/2``
transitions) — except for a window that begins where its segment (option, episode)
begins: there the zero state is the true one, and all its steps carry the loss.
Without that exception the first step of every segment longer than ``n/2`` steps would
never be trained (with the meta-controller's ``n = 2``: its first decision of every
episode of two or more options). Cutting rather than shifting windows at a segment's end matters: with
windows kept whole inside the segment, the last step of an option (where the subgoal
reward is) would reach the loss ``n/2`` times less often than a middle step.

With ``seq_len=None`` a window is instead the whole segment of the random step, from the
segment's start, every step carrying the loss: the LSTM then sees exactly the states it
acts from (acting unrolls each segment from a zero state), and every target is read at a
position that the loss also trains (docs/training.md, "Whole sequences").

Segments are options: the sub-controller's LSTM restarts at every option, so its windows
must never cross an option boundary. Flat and meta-controller replays store one segment
per episode (``segment_starts=[0]``).

Storage layout of one episode of ``T`` steps and ``K`` segments:

* ``frames``: ``(T + 1, ...)`` the inputs ``o_0 .. o_T``; frame ``t + 1`` is the next
  input of step ``t``, so next observations are not stored twice.
* ``fields``: name -> ``(T, ...)`` per-step arrays (action, reward, terminal, ...).
* ``segment_starts``: ``(K,)`` int32, strictly increasing, starting at 0.
* ``segment_data``: name -> ``(K, ...)`` per-segment arrays (e.g. the option's subgoal
  image, stored once per option rather than once per step).

Memory (gridworld sub-controller replay, thesis table 4.7: 5000 episodes)
-------------------------------------------------------------------------
Per stored step: one 44x44x3 uint8 frame = 5808 B, plus compact fields, e.g. action
``uint8`` (1 B), intrinsic reward ``float32`` (4 B), terminal ``bool`` (1 B) = 6 B, i.e.
5814 B a step. Per episode: one extra frame (``o_T``,
5808 B) and per option its subgoal image (5808 B) plus its int32 start (4 B).

5000 episodes x 50 steps = 250,000 steps:

* steps:        250,000 x 5814 B = 1,453,500,000 B
* last frames:    5,000 x 5808 B =    29,040,000 B
* options: K per episode, 5,000 x K x 5812 B = K x 29,060,000 B

With K = 10 options an episode that is 1,773,140,000 B = 1.65 GiB <= 2 GiB; the 2 GiB
bound holds up to ~22 options per episode on average (an unbounded flat replay of 6-channel
stacked frames would need 11.6 KB a step, 2.9 GB). ``nbytes`` counts array data only;
the Python objects add roughly 1-2 KB per episode (~10 MB for 5000 episodes). Use
``capacity_bytes`` to enforce a hard bound in addition to ``capacity_episodes``.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
import torch

__all__ = ["Episode", "EpisodeReplay", "SequenceBatch", "ReplaySamples"]


def _owned(a: np.ndarray) -> np.ndarray:
    """A C-contiguous array owning its memory (so ``nbytes`` is what is really held)."""
    a = np.asarray(a)
    if a.base is not None or not a.flags.c_contiguous:
        a = np.array(a, order="C", copy=True)
    return a


def _rows_checked(what: str, arrays, rows: int, expected: str) -> dict[str, np.ndarray]:
    """``arrays`` as a dict of numpy arrays with ``rows`` leading rows, or a ValueError."""
    if not isinstance(arrays, dict):
        raise ValueError(f"Episode.{what} must be a dict name -> array")
    out = {}
    for name, arr in arrays.items():
        arr = np.asarray(arr)
        if arr.ndim < 1 or arr.shape[0] != rows:
            raise ValueError(f"Episode.{what}[{name!r}] must have {expected}, got shape {arr.shape}")
        out[name] = arr
    return out


@dataclass
class Episode:
    """One stored episode; see the module docstring for the layout.

    Arrays are converted with ``np.asarray`` (dtypes are kept: choose compact ones).
    """

    frames: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    segment_starts: np.ndarray | None = None
    segment_data: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.frames = np.asarray(self.frames)
        if self.frames.ndim < 1 or self.frames.shape[0] < 2:
            raise ValueError(
                "Episode.frames must be (T + 1, ...) with T >= 1 steps, "
                f"got shape {self.frames.shape}"
            )
        t = self.num_steps
        self.fields = _rows_checked("fields", self.fields, t, f"T = {t} rows (frames has T + 1 = {t + 1})")

        if self.segment_starts is None:
            starts = np.zeros(1, dtype=np.int32)
        else:
            raw = np.asarray(self.segment_starts)
            if raw.ndim != 1 or raw.size == 0 or not np.issubdtype(raw.dtype, np.integer):
                raise ValueError(
                    f"Episode.segment_starts must be a non-empty 1-D integer array, got "
                    f"{raw.dtype} of shape {raw.shape}"
                )
            starts = raw.astype(np.int32)
            if starts[0] != 0:
                raise ValueError(f"Episode.segment_starts must start at 0, got {starts[0]}")
            if np.any(np.diff(starts) <= 0):
                raise ValueError(f"Episode.segment_starts must strictly increase: {starts}")
            if starts[-1] >= t:
                raise ValueError(
                    f"Episode.segment_starts must be < T = {t} (no empty segment), got {starts}"
                )
        self.segment_starts = starts

        k = starts.shape[0]
        self.segment_data = _rows_checked("segment_data", self.segment_data, k, f"K = {k} rows (one per segment)")

    @property
    def num_steps(self) -> int:
        return int(self.frames.shape[0] - 1)

    @property
    def num_segments(self) -> int:
        return int(self.segment_starts.shape[0])

    @property
    def segment_lengths(self) -> np.ndarray:
        """(K,) int: steps in each segment."""
        return np.diff(np.append(self.segment_starts, self.num_steps))

    @property
    def nbytes(self) -> int:
        total = self.frames.nbytes + self.segment_starts.nbytes
        total += sum(a.nbytes for a in self.fields.values())
        total += sum(a.nbytes for a in self.segment_data.values())
        return int(total)

    def _signature(self):
        def sig(a):
            return (a.shape[1:], a.dtype.str)

        return (
            sig(self.frames),
            tuple(sorted((k, sig(a)) for k, a in self.fields.items())),
            tuple(sorted((k, sig(a)) for k, a in self.segment_data.items())),
        )


@dataclass
class SequenceBatch:
    """A minibatch of ``B`` windows of ``n = seq_len`` steps.

    * ``frames``: ``(B, n + 1, ...)``: the window's inputs plus the next input of its last
      step, so ``frames[:, t]`` / ``frames[:, t + 1]`` are the input / next input of step t.
    * ``fields``: name -> ``(B, n, ...)``.
    * ``segment_data``: name -> ``(B, ...)``: the data of the window's segment.
    * ``valid``: ``(B, n)`` bool; a window shorter than ``n`` (short segment) fills its
      first steps and is right-padded with zeros (frames after its last next-input too).
    * ``loss_mask``: ``(B, n)`` bool: the last ``loss_len`` valid steps of each window.
    * ``episode_index``, ``start``: ``(B,)`` int: where each window came from (replay slot
      at sampling time, and first step within the episode).
    * ``episode_end``: ``(B, n)`` bool: the step is its episode's last (terminal, or cut by
      the time limit).
    * ``return_to_go``: ``(B, n)`` float32 or None: the discounted return obtained from each
      step to its segment's end (:meth:`EpisodeReplay.return_to_go`), when asked for.
    """

    frames: np.ndarray
    fields: dict[str, np.ndarray]
    segment_data: dict[str, np.ndarray]
    valid: np.ndarray
    loss_mask: np.ndarray
    episode_index: np.ndarray
    start: np.ndarray
    episode_end: np.ndarray
    return_to_go: np.ndarray | None = None

    def samples(self, obs: np.ndarray, device: torch.device | str = "cpu") -> "ReplaySamples":
        """The window as the Double DQN target reads it: ``obs`` (the network input built
        from it, ``(B, n + 1, ...)``) and the fields ``action``, ``reward``, ``terminal``
        (and ``next_invalid``, ``option_steps`` when stored) as tensors on ``device``."""
        fields = self.fields
        invalid, option_steps = fields.get("next_invalid"), fields.get("option_steps")
        returns = self.return_to_go
        return ReplaySamples(
            obs=torch.as_tensor(obs, device=device),
            action=torch.as_tensor(fields["action"], device=device).long(),
            reward=torch.as_tensor(fields["reward"], device=device).float(),
            terminal=torch.as_tensor(fields["terminal"], device=device).float(),
            mask=torch.as_tensor(self.loss_mask, device=device),
            next_invalid=None if invalid is None else torch.as_tensor(invalid, device=device).long(),
            option_steps=None if option_steps is None else torch.as_tensor(option_steps, device=device).float(),
            episode_end=torch.as_tensor(self.episode_end, device=device),
            start=torch.as_tensor(self.start, device=device),
            return_to_go=None if returns is None else torch.as_tensor(returns, device=device),
        )


class ReplaySamples(NamedTuple):
    """A minibatch of ``B`` windows of ``n`` steps as one Double DQN update reads it
    (tensors on the controller's device; every per-step field is ``(B, n)``):

    * ``obs``: ``(B, n + 1, ...)`` network inputs; ``obs[:, t]`` is step t's input s_t,
      ``obs[:, t + 1]`` its next input s_{t+1}.
    * ``action``: int64, the action (or subgoal) taken at step t.
    * ``reward``: float32, r_t (the sub-controller's intrinsic reward, the meta-controller's
      summed extrinsic reward over the option, a flat agent's classical reward).
    * ``terminal``: float32, 1 where s_{t+1} is not bootstrapped from, else 0.
    * ``mask``: bool, the steps that carry the loss (:attr:`SequenceBatch.loss_mask`);
      padding and burn-in steps are False.
    * ``next_invalid``: int64 or None: a choice s_{t+1} may not take (the subgoal the
      meta-controller stands on), -1 for none; left out of the target's argmax.
    * ``option_steps``: float32 or None: the length k in primitive steps of the option that
      step t is (the meta-controller's SMDP discount gamma**k); 0 on padding steps.
    * ``episode_end``: bool, step t is its episode's last.
    * ``start``: ``(B,)`` int64, each window's first step within its episode (step t of
      the window is step ``start + t`` of the episode: for the meta-controller, its option index).
    * ``return_to_go``: float32 or None: the discounted return obtained from step t to
      the end of its segment.
    """

    obs: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    terminal: torch.Tensor
    mask: torch.Tensor
    next_invalid: torch.Tensor | None
    option_steps: torch.Tensor | None
    episode_end: torch.Tensor
    start: torch.Tensor
    return_to_go: torch.Tensor | None


class _Window(NamedTuple):
    """One sampled window: replay slot, segment, first step, steps, first loss step (relative)."""

    episode: int
    segment: int
    start: int
    length: int
    loss_from: int


def _segment_bounds(ep: Episode, segment: int) -> tuple[int, int]:
    """(first step, end step) of ``ep``'s ``segment``."""
    end = int(ep.segment_starts[segment + 1]) if segment + 1 < ep.num_segments else ep.num_steps
    return int(ep.segment_starts[segment]), end


class EpisodeReplay:
    """Ring buffer of whole episodes, bounded in episodes and optionally in bytes.

    When either bound is exceeded after an ``add``, the oldest episodes are dropped.
    """

    def __init__(
        self,
        capacity_episodes: int,
        seed: int | None = None,
        capacity_bytes: int | None = None,
    ):
        if int(capacity_episodes) < 1:
            raise ValueError(f"capacity_episodes must be >= 1, got {capacity_episodes}")
        if capacity_bytes is not None and int(capacity_bytes) < 1:
            raise ValueError(f"capacity_bytes must be >= 1 or None, got {capacity_bytes}")
        self.capacity_episodes = int(capacity_episodes)
        self.capacity_bytes = None if capacity_bytes is None else int(capacity_bytes)
        self._episodes: deque = deque()
        self._nbytes = 0
        self._num_steps = 0
        self._signature = None
        self._rng = np.random.default_rng(seed)

    def __len__(self) -> int:
        return len(self._episodes)

    @property
    def num_steps(self) -> int:
        return self._num_steps

    @property
    def nbytes(self) -> int:
        """Bytes of array data held (frames, fields, segment starts and data)."""
        return self._nbytes

    def __getitem__(self, i: int) -> Episode:
        return self._episodes[i]

    def clear(self) -> None:
        self._episodes.clear()
        self._nbytes = 0
        self._num_steps = 0
        self._signature = None

    def add(self, episode: Episode) -> None:
        """Store ``episode`` (arrays that are views are copied so that the replay never
        pins a larger buffer), then drop the oldest episodes beyond the capacities."""
        if not isinstance(episode, Episode):
            raise ValueError(f"add() expects an Episode, got {type(episode).__name__}")
        sig = episode._signature()
        if self._signature is not None and sig != self._signature and len(self) > 0:
            raise ValueError(
                "episode layout (frame shape/dtype, field or segment_data names, shapes, "
                f"dtypes) differs from the episodes already stored: {sig} != {self._signature}"
            )
        ep = Episode(
            frames=_owned(episode.frames),
            fields={k: _owned(v) for k, v in episode.fields.items()},
            segment_starts=_owned(episode.segment_starts),
            segment_data={k: _owned(v) for k, v in episode.segment_data.items()},
        )
        nb = ep.nbytes
        if self.capacity_bytes is not None and nb > self.capacity_bytes:
            raise ValueError(
                f"episode of {nb} bytes exceeds capacity_bytes = {self.capacity_bytes}"
            )
        self._signature = sig
        self._episodes.append(ep)
        self._nbytes += nb
        self._num_steps += ep.num_steps
        while len(self._episodes) > self.capacity_episodes or (
            self.capacity_bytes is not None and self._nbytes > self.capacity_bytes
        ):
            old = self._episodes.popleft()
            self._nbytes -= old.nbytes
            self._num_steps -= old.num_steps

    def sample(
        self,
        batch_size: int,
        seq_len: int | None,
        rng: np.random.Generator | None = None,
        loss_len: int | None = None,
        history: bool = False,
        gamma: float | None = None,
        smdp_discount: bool = False,
    ) -> SequenceBatch:
        """Sample ``batch_size`` windows of up to ``seq_len`` steps (see module docstring).

        ``seq_len`` None: each window is the whole segment of a random step, from the
        segment's start (the state acting starts from), every step carrying the loss; the
        batch is as long as its longest window.
        ``loss_len`` (default ``max(1, seq_len // 2)``): how many of the last valid steps
        of each window carry the loss (all of them when the window is shorter).
        ``history``: draw the first loss step uniformly instead and begin the window up to
        ``seq_len - loss_len`` steps before it, inside its segment, so that every loss step
        has that much history where the segment has it (a window that then begins at its
        segment's start still puts the loss on all its steps).
        ``gamma``: also fill ``return_to_go`` (:meth:`return_to_go`, with ``smdp_discount``).
        ``rng`` defaults to the replay's own generator (seeded by ``seed``).
        """
        if len(self._episodes) == 0:
            raise ValueError("cannot sample from an empty replay")
        if int(batch_size) < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if seq_len is not None and int(seq_len) < 1:
            raise ValueError(f"seq_len must be >= 1 or None (whole segments), got {seq_len}")
        n = None if seq_len is None else int(seq_len)
        if loss_len is None:
            loss_len = max(1, (n or 1) // 2)
        if int(loss_len) < 1:
            raise ValueError(f"loss_len must be >= 1, got {loss_len}")
        rng = self._rng if rng is None else rng

        picks = []
        for episode_index in rng.integers(len(self._episodes), size=int(batch_size)):
            ep = self._episodes[int(episode_index)]
            # A uniformly random step of the episode (thesis 3.4); its window is cut at the end
            # of that step's segment, so every step, an option's last included, reaches the
            # loss equally often.
            start = int(rng.integers(ep.num_steps))
            segment = int(np.searchsorted(ep.segment_starts, start, side="right")) - 1
            seg_start, seg_end = _segment_bounds(ep, segment)
            if n is None:
                picks.append(_Window(int(episode_index), segment, seg_start, seg_end - seg_start, 0))
                continue
            first_loss = start
            if history:  # ``start`` is the first loss step: begin up to n - loss_len steps earlier
                start = max(seg_start, start - (n - int(loss_len)))
            length = min(n, seg_end - start)
            # A window that begins where its segment begins starts from the true (zero) LSTM
            # state, so all its steps carry the loss; otherwise only the last loss_len do.
            if start == seg_start:
                loss_from = 0
            else:
                loss_from = first_loss - start if history else max(0, length - int(loss_len))
            picks.append(_Window(int(episode_index), segment, start, length, loss_from))
        return self._gather(picks, n, gamma, smdp_discount)

    def whole_segments(self, episodes: list[int], gamma: float | None = None,
                       smdp_discount: bool = False) -> SequenceBatch:
        """Every segment of the episodes at ``episodes`` (replay slots), whole, from its start,
        one row each in order: the windows of ``sample(..., seq_len=None)``, chosen."""
        picks = []
        for index in episodes:
            ep = self._episodes[int(index)]
            for segment in range(ep.num_segments):
                seg_start, seg_end = _segment_bounds(ep, segment)
                picks.append(_Window(int(index), segment, seg_start, seg_end - seg_start, 0))
        return self._gather(picks, None, gamma, smdp_discount)

    @staticmethod
    def return_to_go(episode: Episode, gamma: float, smdp_discount: bool = False) -> np.ndarray:
        """(T,) float64: the discounted return obtained from each step to the end of its
        segment (an episode of options, an option), G_t = r_t + d_t (1 - terminal_t) G_{t+1},
        with d_t = gamma, or gamma ** option_steps[t] with ``smdp_discount``; nothing is
        bootstrapped after a segment's last step."""
        rewards = episode.fields["reward"].astype(np.float64)
        discounts = np.full(len(rewards), float(gamma))
        if smdp_discount and "option_steps" in episode.fields:
            discounts = float(gamma) ** episode.fields["option_steps"].astype(np.float64)
        discounts[episode.fields["terminal"].astype(bool)] = 0.0
        discounts[episode.segment_starts[1:] - 1] = 0.0
        out = np.empty_like(rewards)
        running = 0.0
        for t in range(len(rewards) - 1, -1, -1):
            running = rewards[t] + discounts[t] * running
            out[t] = running
        return out

    def _gather(self, picks: list["_Window"], n: int | None, gamma: float | None,
                smdp_discount: bool) -> SequenceBatch:
        """The :class:`SequenceBatch` of ``picks``, ``n`` steps long (None: the longest pick)."""
        n = max(p.length for p in picks) if n is None else n
        batch_size = len(picks)
        first = self._episodes[0]
        frames = np.zeros((batch_size, n + 1) + first.frames.shape[1:], first.frames.dtype)
        fields = {k: np.zeros((batch_size, n) + a.shape[1:], a.dtype) for k, a in first.fields.items()}
        seg_data = {k: np.zeros((batch_size,) + a.shape[1:], a.dtype) for k, a in first.segment_data.items()}
        valid = np.zeros((batch_size, n), bool)
        loss_mask = np.zeros((batch_size, n), bool)
        episode_end = np.zeros((batch_size, n), bool)
        returns = None if gamma is None else np.zeros((batch_size, n), np.float32)
        for row, (episode_index, segment, start, length, loss_from) in enumerate(picks):
            ep = self._episodes[episode_index]
            frames[row, : length + 1] = ep.frames[start : start + length + 1]
            for name, a in ep.fields.items():
                fields[name][row, :length] = a[start : start + length]
            for name, a in ep.segment_data.items():
                seg_data[name][row] = a[segment]
            valid[row, :length] = True
            loss_mask[row, loss_from:length] = True
            episode_end[row, length - 1] = start + length == ep.num_steps
            if returns is not None:
                returns[row, :length] = self.return_to_go(ep, gamma, smdp_discount)[start : start + length]
        return SequenceBatch(frames, fields, seg_data, valid, loss_mask,
                             np.array([p.episode for p in picks], np.int64),
                             np.array([p.start for p in picks], np.int64), episode_end, returns)

    def sample_transitions(
        self,
        batch_size: int,
        seq_len: int,
        build_input: Callable[[SequenceBatch], np.ndarray],
        device: torch.device | str = "cpu",
        rng: np.random.Generator | None = None,
        loss_len: int | None = None,
        history: bool = False,
        gamma: float | None = None,
        smdp_discount: bool = False,
    ) -> ReplaySamples:
        """:meth:`sample` windows, as typed :class:`ReplaySamples` on ``device``; the network
        input ``obs`` is ``build_input(window)`` (e.g. each frame stacked with its option's
        subgoal image)."""
        batch = self.sample(batch_size, seq_len, rng=rng, loss_len=loss_len, history=history, gamma=gamma,
                            smdp_discount=smdp_discount)
        return batch.samples(build_input(batch), device)
