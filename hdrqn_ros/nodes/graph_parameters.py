"""The parameters every training-graph node declares (the agent, its domain, message limits),
and what the nodes derive from them. The launch files set the shared ones once for all nodes
with a ``/**`` entry."""
from __future__ import annotations

from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.envs.registration import GRID_IDS, MONTEZUMA_IDS, make_batch
from hdrqn_ros.nodes.parameters import Param
from hdrqn_ros.nodes.ros_messages import DEFAULT_MAX_MESSAGE_BYTES
from hdrqn_ros.protocol.wire import MAX_ENVS

ENV_PARAMETERS = {
    "algo": Param("hdrqn-v2", "agent: " + ", ".join(ALGO_SPECS), choices=tuple(ALGO_SPECS)),
    "env": Param("hdrqn/GridWorld-2Goals-v0", "environment id (hdrqn envs lists them)",
                 choices=tuple(sorted(GRID_IDS) + sorted(MONTEZUMA_IDS))),
    "view": Param("5", "gridworld view: an odd number of cells or 'full' (a string)",
                  check=lambda view: None if view == "full" or odd_cells(view) else
                  f"must be an odd number of cells or 'full', got {view!r}"),
    "seed": Param(0, "seed of the environments and of the controllers' exploration"),
}
"""The agent and its domain: what every training-graph node must agree on."""
NUM_ENVS = {"num_envs": Param(1, "environments the environment node steps as one batch (the same on every node of "
                                 "a group)", low=1, high=MAX_ENVS)}
MAX_MESSAGE_BYTES = {"max_message_bytes": Param(DEFAULT_MAX_MESSAGE_BYTES, "received samples larger than this "
                                                "(bytes) are dropped with a warning", positive=True)}


def odd_cells(view: str) -> bool:
    """Whether ``view`` is an odd number of cells written in ASCII digits ("5", not "full" or "²")."""
    return view.isascii() and view.isdigit() and int(view) % 2 == 1


def env_kwargs(env_id: str, view: str) -> dict:
    """``make_batch`` keyword arguments from the (declared, so checked) ``view`` parameter."""
    if env_id in MONTEZUMA_IDS:
        return {}
    return {"view": "full" if view == "full" else int(view)}


def domain_sizes(env_id: str, view: str) -> tuple[int, int]:
    """(num_actions, num_subgoals) of the domain."""
    probe = make_batch(env_id, 1, **env_kwargs(env_id, view))
    return probe.num_actions, probe.num_subgoals
