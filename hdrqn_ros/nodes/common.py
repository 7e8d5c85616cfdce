"""What every node executable shares: start-up, parameters, the spin loop, clean exit."""
from __future__ import annotations

import signal
import sys
import threading
from typing import Any, Callable

import numpy as np
import torch

from hdrqn_ros.agents.algorithms import ALGO_SPECS, make_network
from hdrqn_ros.agents.weights import WeightsError, load_weights
from hdrqn_ros.config import ConfigError
from hdrqn_ros.envs.registration import GRID_IDS, MONTEZUMA_IDS, make_batch
from hdrqn_ros.middleware import (LATCHED_QOS, BackendError, Middleware, Node, ParameterError, RosArgsError,
                                  open_middleware)
from hdrqn_ros.protocol import wire
from hdrqn_ros.nodes.nav import NavConfigError
from hdrqn_ros.recording.bag import BagError
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint
from hdrqn_ros.throttle import Throttle

ENV_DEFAULTS = {"algo": "hdrqn-v2", "env": "hdrqn/GridWorld-2Goals-v0", "view": "5", "seed": 0}
"""Parameters every training-graph node declares (the launch files set them once for all
nodes with a ``/**`` entry)."""


class NodeConfigError(ValueError):
    """A parameter value the node cannot work with."""


def env_kwargs(env_id: str, view: str) -> dict:
    """``make_batch`` keyword arguments from the ``view`` parameter ("3", "5", "full"...)."""
    if env_id in MONTEZUMA_IDS:
        return {}
    if env_id not in GRID_IDS:
        raise NodeConfigError(f"unknown env {env_id!r}; choose one of {sorted(GRID_IDS) + sorted(MONTEZUMA_IDS)}")
    if view == "full":
        return {"view": "full"}
    if not view.isdigit():
        raise NodeConfigError(f"view must be an odd number of cells or 'full', got {view!r}")
    return {"view": int(view)}


def check_algo(algo: str) -> None:
    if algo not in ALGO_SPECS:
        raise NodeConfigError(f"unknown algo {algo!r}; choose one of {sorted(ALGO_SPECS)}")


def domain_sizes(env_id: str, view: str) -> tuple[int, int]:
    """(num_actions, num_subgoals) of the domain."""
    probe = make_batch(env_id, 1, **env_kwargs(env_id, view))
    return probe.num_actions, probe.num_subgoals


class ActingNetwork:
    """A controller's Q-network for acting in a node, its exploration (``epsilon``,
    ``rng``), weights from a checkpoint and from the learner's ``/learner/*_weights`` topic.
    Inference tensors: its LSTM states are replaced, never changed in place (N = 1)."""

    def __init__(self, node: Node, role: str, params: dict, default_epsilon: float):
        check_algo(params["algo"])
        torch.set_num_threads(1)
        self.node, self.role = node, role
        self.num_actions, self.num_subgoals = domain_sizes(params["env"], params["view"])
        self.net = make_network(params["algo"], role, self.num_actions, self.num_subgoals)
        self.net.eval()
        self.rng = np.random.default_rng(params["seed"] + (7 if role == "meta" else 11))
        self.fixed_epsilon = params["epsilon"] if params["epsilon"] >= 0 else None
        self.epsilon = self.fixed_epsilon if self.fixed_epsilon is not None else default_epsilon
        self.weights_version = -1
        if params["checkpoint"]:
            self._load_checkpoint(params["checkpoint"])
        self.rejected_weights = Throttle(node.logger, f"rejected {role} weights on {wire.WEIGHTS[role]}")
        node.create_subscription(wire.BYTES, wire.WEIGHTS[role], self._on_weights, LATCHED_QOS)

    def _load_checkpoint(self, path: str) -> None:
        payload = load_checkpoint(path)
        try:
            self.net.load_state_dict(payload["agent"][self.role]["online"])
        except (KeyError, RuntimeError) as exc:
            raise CheckpointError(f"{path} has no {self.role} network for this algo: "
                                  f"{str(exc).splitlines()[0]}") from None
        self.weights_version = 0
        self.node.logger.info("loaded %s weights from %s", self.role, path)

    def _on_weights(self, msg) -> None:
        try:
            version = wire.read_weights_version(msg)
            load_weights(self.net, wire.as_bytes(msg.data))
        except (WeightsError, ValueError) as exc:
            self.rejected_weights.warn(exc)
            return
        if self.weights_version < 0 or version // 100 > self.weights_version // 100:
            self.node.logger.info("acting with the learner's %s weights of update %d", self.role, version)
        self.weights_version = version

    def on_credit(self, credit: dict) -> None:
        if self.fixed_epsilon is None:
            self.epsilon = credit["eps_meta" if self.role == "meta" else "eps_sub"]

    def act(self, x: np.ndarray, state):
        """``x`` (B, ...) -> (Q-values (B, n) numpy, new LSTM state): a controller of
        :class:`~hdrqn_ros.agents.policy.HierarchicalPolicy`."""
        with torch.inference_mode():
            q, state = self.net.act(torch.tensor(x), state)  # a copy: x may be read-only
        return q.numpy(), state

    def initial_state(self, batch_size: int):
        return self.net.initial_state(batch_size)


def run_node(build: Callable[[Middleware], Any], argv: list[str] | None = None) -> int:
    """Open the middleware, build the node object, spin until it finishes, Ctrl-C or
    SIGTERM, then clean up (the object's ``close()`` first, then the middleware).

    SIGINT (Ctrl-C, what ``ros2 launch`` sends) and SIGTERM are a normal stop: exit code
    the object's ``exit_code`` (0). 2 for bad parameters, arguments, checkpoints or bags."""
    argv = list(sys.argv if argv is None else argv)
    stopped = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stopped.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    mw = obj = None
    try:
        mw = open_middleware(argv)
        obj = build(mw)
        mw.spin(until=lambda: stopped.is_set() or getattr(obj, "finished", False))
        return getattr(obj, "exit_code", 0)
    except KeyboardInterrupt:
        return 130
    except (NodeConfigError, NavConfigError, ConfigError, ParameterError, RosArgsError, BackendError,
            CheckpointError, BagError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    finally:
        if obj is not None and hasattr(obj, "close"):
            obj.close()
        if mw is not None:
            mw.shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
