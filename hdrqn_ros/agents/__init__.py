"""Agents: Q-networks (torch) and episodic replay (numpy).

``replay`` does not import torch; import ``hdrqn_ros.agents.networks`` explicitly for the
networks so that numpy-only users (e.g. recorder nodes) do not pay for importing torch.
"""
from hdrqn_ros.agents.replay import Episode, EpisodeReplay, SequenceBatch

__all__ = ["Episode", "EpisodeReplay", "SequenceBatch"]
