"""Q-values where a controller acts, against where its training windows put them.

For the stored episodes of a run (its checkpoint's replay snapshot), each recurrent
controller's online network is run twice over every segment (an episode of options for the
meta-controller, an option for the sub-controller, an episode for a flat agent):

* **acting**: unrolled from the segment's start, as the policy acts (Algorithm 1);
* **zero-state windows**: from a zero state at each window start, as the thesis's
  bootstrapped random updates train it; the decision at segment position t is then seen
  at window position p = 0 .. n (n = ``seq_len``; position n is where a target is read).

Both are set beside the discounted return actually obtained from t to the segment's end
(nothing bootstrapped after it), by t (0, 1, 2, 3, >= 4). ``hdrqn values RUN``
prints the tables (:func:`audit_run`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from hdrqn_ros.agents.controller import Controller
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint
from hdrqn_ros.training.learner import load_trained_agent
from hdrqn_ros.training.replay_snapshot import load_replay_snapshot

BUCKETS = 5
"""Segment positions 0 .. 3 one by one, then 4 and later together."""
CHUNK = 8
"""Segments run through the network at once."""
START_BLOCK = 32
"""Window starts per segment run through the network at once (with CHUNK: at most 256 windows)."""


def _taken(q: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Q (..., A) at ``action`` (...)."""
    return q.gather(-1, action.unsqueeze(-1)).squeeze(-1)


@torch.no_grad()
def _chunk_values(ctrl: Controller, slots: list[int], n: int):
    """Per valid step of the whole segments of replay ``slots``: (position t, return G_t,
    acting Q, (n + 1, steps) zero-state window Q at positions 0 .. n, NaN where t < p)."""
    batch = ctrl.replay.whole_segments(slots, gamma=ctrl.cfg.gamma, smdp_discount=ctrl.smdp_discount)
    obs = torch.as_tensor(ctrl.build_input(batch), device=ctrl.device)
    action = torch.as_tensor(batch.fields["action"], device=ctrl.device).long()
    b, length = action.shape
    acting = _taken(ctrl.online(obs)[0][:, :-1], action)  # (B, L)
    # every window start s = 0 .. L-1 of n + 1 inputs, zero-padded past the segment's end, a
    # block of starts at a time (a window copies its inputs: Montezuma's options are long)
    padded = torch.cat([obs, obs.new_zeros((b, n) + obs.shape[2:])], 1)
    blocks = []
    for first in range(0, length, START_BLOCK):
        starts = min(START_BLOCK, length - first)
        windows = padded[:, first:first + starts + n].unfold(1, n + 1, 1)  # (B, starts, ..., n + 1)
        windows = windows.movedim(-1, 2).reshape((b * starts, n + 1) + obs.shape[2:])
        blocks.append(ctrl.online(windows)[0].view(b, starts, n + 1, -1))
    q_windows = torch.cat(blocks, 1)  # (B, L, n + 1, A)
    zero = torch.full((n + 1, b, length), float("nan"), device=ctrl.device)
    for p in range(n + 1):  # the decision at t seen at position p of the window begun at t - p
        if p < length:
            zero[p, :, p:] = _taken(q_windows[:, : length - p, p], action[:, p:])
    valid = torch.as_tensor(batch.valid, device=ctrl.device)
    position = torch.arange(length, device=ctrl.device).expand(b, length)
    returns = torch.as_tensor(batch.return_to_go, device=ctrl.device)
    return position[valid], returns[valid], acting[valid], zero[:, valid]


def audit_controller(ctrl: Controller, episodes: int = 200) -> dict:
    """The table of one recurrent controller over the newest ``episodes`` of its replay:
    ``rows`` by segment position (``count``, ``return``, ``q_acting``, ``q_window`` per window
    position) and ``gap``: mean |acting Q - zero-state Q| per window position."""
    n = ctrl.cfg.seq_len
    slots = list(range(max(0, len(ctrl.replay) - episodes), len(ctrl.replay)))
    parts = [_chunk_values(ctrl, slots[i:i + CHUNK], n) for i in range(0, len(slots), CHUNK)]
    position, returns, acting = (torch.cat([p[k] for p in parts]).cpu().numpy() for k in range(3))
    zero = torch.cat([p[3] for p in parts], 1).cpu().numpy()  # (n + 1, steps)
    bucket = np.minimum(position, BUCKETS - 1)
    rows = []
    for k in range(BUCKETS):
        at = bucket == k
        if not at.any():
            continue
        rows.append({"position": f"{k}+" if k == BUCKETS - 1 else str(k), "count": int(at.sum()),
                     "return": float(returns[at].mean()), "q_acting": float(acting[at].mean()),
                     "q_window": [None if np.isnan(zero[p, at]).all() else float(np.nanmean(zero[p, at]))
                                  for p in range(n + 1)]})
    gap = [None if np.isnan(zero[p]).all() else float(np.nanmean(np.abs(acting - zero[p]))) for p in range(n + 1)]
    return {"controller": ctrl.name, "episodes": len(slots), "steps": int(len(position)), "window": n,
            "sampling": ctrl.cfg.sampling, "rows": rows, "gap": gap}


def audit_run(run_dir: str | Path, episodes: int = 200) -> list[dict]:
    """:func:`audit_controller` for each recurrent controller of the run in ``run_dir``, on
    the replay its last checkpoint saved. Raises :class:`CheckpointError` for a run without
    a checkpoint or replay snapshot."""
    path = Path(run_dir) / "checkpoints" / "last.pt"
    if not path.is_file():
        raise CheckpointError(f"{run_dir} holds no checkpoints/last.pt (is it a run directory of hdrqn train?)")
    payload = load_checkpoint(path)
    snapshot = payload["progress"].get("replay")
    if not snapshot:
        raise CheckpointError(f"{path} saved no replay (the run had save_replay false): nothing to audit")
    cfg, agent = load_trained_agent(path)
    replays = {c.name: c.replay for c in agent.controllers}
    load_replay_snapshot(path.parent / snapshot["file"], replays, snapshot,
                         {"algo": cfg.algo, "env": cfg.env, "env_kwargs": cfg.env_kwargs}, written_with=payload["config"])
    return [{**audit_controller(ctrl, episodes), "run_episodes": payload["progress"]["episodes"]}
            for ctrl in agent.controllers if ctrl.recurrent]


def audit_markdown(table: dict) -> str:
    """One controller's audit as a Markdown table."""
    n = table["window"]
    head = ["position t", "steps", "return obtained", "Q acting"] + [
        f"Q window pos {p}" + (" (target)" if p == n else "") for p in range(n + 1)]
    lines = [f"{table['controller']} ({table['episodes']} episodes, {table['steps']} steps; windows of n = {n}; "
             f"trained with sampling={table['sampling']})", "", "| " + " | ".join(head) + " |",
             "|" + "---|" * len(head)]

    def cell(v):
        return "" if v is None else f"{v:.3g}"

    for row in table["rows"]:
        lines.append("| " + " | ".join([row["position"], str(row["count"]), cell(row["return"]),
                                        cell(row["q_acting"]), *map(cell, row["q_window"])]) + " |")
    gap = ", ".join(f"pos {p}: {cell(v)}" for p, v in enumerate(table["gap"]))
    lines += ["", f"mean |Q acting - Q window|: {gap}"]
    return "\n".join(lines)
