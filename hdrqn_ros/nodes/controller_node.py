"""What the ``meta_controller`` and ``sub_controller`` nodes share: one level of the agent as a
managed node.

At configure a controller node loads its acting network (torch weights, or an exported ONNX
policy: :mod:`hdrqn_ros.nodes.acting`), builds its level of the
:class:`~hdrqn_ros.agents.policy.HierarchicalPolicy` for the environment node's batch
(``num_envs``), takes the learner's exploration rates from ``learner_credit``, publishes its
health on ``/diagnostics``, and then makes its own parts (:meth:`ControllerNode.build_parts`):
the controller that decides, and the Nav2 adapters it hands its decisions to.
"""
from __future__ import annotations

from std_msgs.msg import Float64MultiArray

from hdrqn_ros.agents.policy import HierarchicalPolicy
from hdrqn_ros.agents.specs import ALGO_SPECS
from hdrqn_ros.nodes.acting import make_acting_network
from hdrqn_ros.nodes.diagnostics import OK, WARN, Diagnostics, policy_source
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS, MAX_MESSAGE_BYTES, NUM_ENVS
from hdrqn_ros.nodes.input_watch import QuietInputs
from hdrqn_ros.nodes.lifecycle import ManagedNode
from hdrqn_ros.nodes.nav import NavConfigError
from hdrqn_ros.nodes.node_logger import python_logger
from hdrqn_ros.nodes.parameters import Param
from hdrqn_ros.nodes.process import STARTUP_ERRORS
from hdrqn_ros.nodes.qos import LATCHED_QOS
from hdrqn_ros.nodes.ros_messages import bounded_subscription
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.follower import Decoder
from hdrqn_ros.training.checkpoint import CheckpointError

CONTROLLER_PARAMETERS = {
    **ENV_PARAMETERS, **NUM_ENVS, **MAX_MESSAGE_BYTES,
    "epsilon": Param(-1.0, "exploration rate; < 0: the learner's schedule (1.0 until it is heard from)", live=True,
                     low=-1.0, high=1.0),
    "checkpoint": Param("", "initial weights (RUN_DIR/checkpoints/last.pt; '': random until the learner's)"),
    "policy": Param("", "instead of checkpoint: an exported policy directory (hdrqn export; frozen, no torch); its "
                        "algo, sizes and hdrqn-v2 meta_state must be the node's"),
    "meta_state": Param("c", "hdrqn-v2: which LSTM state the meta-controller reads", choices=("c", "h")),
    "quiet_input_s": Param(10.0, "wall seconds without any input before the node says what it waits for and which "
                                 "node would publish it", live=True, positive=True),
}
"""The parameters of both controllers. Live: ``epsilon`` (from the next decision on) and
``quiet_input_s``."""


class ControllerNode(ManagedNode, Decoder):
    """One level (``role``: ``"sub"`` or ``"meta"``) of the agent. Subclasses check how their
    parameters go together (:meth:`check_parameters`) and make ``controller``, the part that
    decides (it has ``reset()`` and ``problems()``), in :meth:`build_parts`. Every malformed
    input is rejected through this node's :meth:`decode` (one count, ``messages_rejected``)."""

    role = ""
    bad_input = (*STARTUP_ERRORS, CheckpointError, NavConfigError)

    def __init__(self, name: str, parameters: dict[str, Param], **kwargs):
        super().__init__(name, parameters, **kwargs)
        self.logger = python_logger(self)
        self.spec, self.source = None, ""  # the algo's AlgoSpec; the acting weights, in words
        self.net = self.policy = self.watch = self.diagnostics = self.controller = None
        self.rejected_before = 0  # messages rejected up to the last diagnostics

    # -- what a controller node implements ---------------------------------------------------
    def check_parameters(self) -> None:
        """Raise :class:`~hdrqn_ros.nodes.parameters.NodeConfigError` for parameters that do not go together."""

    def build_parts(self) -> None:
        """Make ``controller`` (and the adapters it drives) from ``params``."""
        raise NotImplementedError

    # -- the lifecycle ---------------------------------------------------------------------------
    def build(self) -> None:
        self.check_parameters()
        params = self.params
        self.spec = ALGO_SPECS[params["algo"]]
        self.net = make_acting_network(self, self.role, params, default_epsilon=1.0)
        sub, meta = (self.net, None) if self.role == "sub" else (None, self.net)
        self.policy = HierarchicalPolicy(params["num_envs"], sub, meta, self.spec.meta_input, params["meta_state"])
        self.source = policy_source(params)
        self.watch = QuietInputs(self)
        self.diagnostics = Diagnostics(self, self.health)
        bounded_subscription(self, Float64MultiArray, wire.CREDIT, self._on_credit, LATCHED_QOS,
                             params["max_message_bytes"], self.logger)
        self.build_parts()

    def start(self) -> None:
        """Act from the next input on (what arrived while inactive is forgotten)."""
        self.watch.restart()
        self.controller.reset()

    def teardown(self) -> None:
        self.net = self.policy = self.watch = self.diagnostics = self.controller = None

    def on_live_parameter(self, name: str, value) -> None:
        """``epsilon`` holds from the next decision on."""
        if name == "epsilon" and self.net is not None:
            self.net.set_fixed_epsilon(value)

    def finish(self, exit_code: int) -> None:
        """End the process with ``exit_code`` (the group's nodes disagree on ``num_envs``)."""
        self.finished, self.exit_code = True, exit_code

    # -- inputs and health -------------------------------------------------------------------------
    def _on_credit(self, msg: Float64MultiArray) -> None:
        credit = self.decode(wire.CREDIT, lambda: wire.read_record(msg, wire.CREDIT_FIELDS))
        if credit is not None:
            self.net.on_credit(credit)

    def problems(self) -> list[str]:
        """What is wrong now, in words (the diagnostics' WARN message; none: OK)."""
        found = self.watch.quiet() + self.controller.problems()
        if (rejected := self.rejected - self.rejected_before) > 0:
            found.append(f"{rejected} message(s) rejected in the last second (see the log)")
        self.rejected_before = self.rejected
        return found

    def health(self) -> tuple[int, str, dict[str, str]]:
        """The diagnostics' level, message and values."""
        values = {"algo": self.params["algo"], "policy": self.source, "epsilon": f"{self.net.epsilon:g}",
                  "messages_rejected": str(self.rejected)}
        if not self.active:
            return OK, "inactive (managed node: activate to act)", values
        found = self.problems()
        return (WARN, "; ".join(found), values) if found else (OK, "acting", values)
