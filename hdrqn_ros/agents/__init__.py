"""Agents: Q-networks, updates and episodic replay (torch), and the acting policy.

Importing this package imports nothing: :mod:`hdrqn_ros.agents.policy` (the acting rules)
imports no torch, so a controller node acting from an exported ONNX policy never loads
it. ``Episode``, ``EpisodeReplay`` and ``SequenceBatch`` are taken from
:mod:`hdrqn_ros.agents.replay` (which imports torch) when first used.
"""
from __future__ import annotations

__all__ = ["Episode", "EpisodeReplay", "SequenceBatch"]


def __getattr__(name: str):
    if name in __all__:
        from hdrqn_ros.agents import replay

        return getattr(replay, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
