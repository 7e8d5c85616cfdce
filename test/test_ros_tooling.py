"""ROS 2 tooling against a real graph of rclpy node processes (hdrqn-v2, one group): what
``ros2 param``, ``ros2 node/topic list``, ``ros2 topic info`` and ``/rosout`` see, and the
node loggers on real rclpy (severities, throttled warnings). Skipped where rclpy cannot be
imported.

The test process's own rclpy context is a :class:`ros_probe.RosProbe` (the loopback-only
Fast DDS defaults applied before ``rclpy.init``); its probe node, a plain rclpy node, is
used for the rclpy APIs the ``ros2`` CLI uses.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import pytest
import yaml

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from rcl_interfaces.msg import Log  # noqa: E402
from rclpy.parameter import Parameter, parameter_value_to_python  # noqa: E402
from rclpy.parameter_client import AsyncParameterClient  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402

from hdrqn_ros.nodes import critic, environment, learner, meta_controller, sub_controller  # noqa: E402
from hdrqn_ros.nodes.controller_node import CONTROLLER_PARAMETERS  # noqa: E402
from hdrqn_ros.nodes.graph_parameters import ENV_PARAMETERS  # noqa: E402
from hdrqn_ros.nodes.nav_adapters import GOAL_PARAMETERS, VELOCITY_PARAMETERS  # noqa: E402
from hdrqn_ros.nodes.node_logger import python_logger  # noqa: E402
from hdrqn_ros.nodes.qos import STEP_QOS  # noqa: E402
from hdrqn_ros.protocol import wire  # noqa: E402
from hdrqn_ros.supervisor import Supervisor  # noqa: E402
from hdrqn_ros.throttle import BURST  # noqa: E402

from ros_probe import ProbeNode, RosProbe  # noqa: E402
from conftest import new_domain  # noqa: E402
from test_graph import CONFIG, ENV, start_graph  # noqa: E402

EPISODES = 100_000
"""The learner's ``episodes`` (not its default 1000); far more than the module's run time
allows, so every node stays up while it is probed."""
NODES = ("environment", "critic", "meta_controller", "sub_controller", "learner")
DECLARED = {
    "environment": environment.PARAMETERS,
    "critic": critic.PARAMETERS,
    "meta_controller": meta_controller.PARAMETERS,
    "sub_controller": sub_controller.PARAMETERS,
    "learner": learner.PARAMETERS,
}
"""What each node declares (its module's ``PARAMETERS``, name -> ``Param``)."""
MANAGED = {"meta_controller", "sub_controller"}
"""Lifecycle nodes: a parameter read at configure is writable in the descriptor and refused
by the node while it is configured."""
RCLPY_PARAMETERS = {"use_sim_time", "start_type_description_service"}
"""Parameters every rclpy node declares itself (Jazzy)."""
RCLPY_TOPICS = {"/rosout": "rcl_interfaces/msg/Log", "/parameter_events": "rcl_interfaces/msg/ParameterEvent"}
"""Topics every rclpy node publishes."""
LIFECYCLE_TOPIC = ("transition_event", "lifecycle_msgs/msg/TransitionEvent")
"""The topic every lifecycle node (:data:`MANAGED`) publishes in its own namespace (``~/transition_event``)."""
ROSOUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""What a ``/rosout`` subscriber asks for: rcl's rosout publisher profile
(``rcl_qos_profile_rosout_default``: reliable, transient-local, keep-last 1000). Its
lifespan is 10 s, so a late subscriber gets only the last 10 s of lines: the probe
subscribes before the nodes start."""
DOCS = Path(__file__).resolve().parents[1] / "docs" / "topics.md"
_ROW = re.compile(r"^\| `(?P<topic>[^`]+)` \| `(?P<type>\w+/msg/\w+)` \| [^|]+ "
                  r"\| (?P<pub>[^|]+) \| (?P<subs>[^|]+) \|$")  # topic | type | QoS | publisher | subscribers


def documented_topics(algo: str = "hdrqn-v2") -> dict[str, dict[str, Any]]:
    """The topics table of ``docs/topics.md`` (section "Topics"), names resolved in ``/``:
    ``{"/env_step": {"type": ..., "publisher": "environment", "subscribers": {...}}}``. A
    subscriber whose condition names algorithms ("meta_controller (hdrqn-v1, hdqn)") is
    left out unless ``algo`` is one of them."""
    section = DOCS.read_text().split("\n## Topics\n", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        if m := _ROW.match(line.strip()):
            subscribers = set()
            for sub in re.finditer(r"(\w+)(?: \(([^)]*)\))?", m["subs"]):
                algos = re.findall(r"\b(?:hdrqn-v[12]|hdqn|drqn|dqn)\b", sub[2] or "")
                if sub[1] in NODES and (not algos or algo in algos):
                    subscribers.add(sub[1])
            rows["/" + m["topic"].lstrip("/")] = {"type": m["type"], "publisher": re.match(r"\w+", m["pub"])[0],
                                                  "subscribers": subscribers}
    return rows


def nav2_topics() -> dict[str, dict[str, Any]]:
    """The Nav2 adapter topics ``start_graph`` turns on (subgoal and action tables; the
    "Notes" of docs/topics.md): ``goal_pose`` and ``cmd_vel`` at their default names."""
    stamped = yaml.safe_load((CONFIG / "nav2" / "actions.yaml").read_text()).get("stamped", False)
    twist = "geometry_msgs/msg/TwistStamped" if stamped else "geometry_msgs/msg/Twist"
    return {"/" + GOAL_PARAMETERS["goal_pose_topic"].default: {"type": wire.POSE_STAMPED,
                                                                "publisher": "meta_controller"},
            "/" + VELOCITY_PARAMETERS["cmd_vel_topic"].default: {"type": twist, "publisher": "sub_controller"}}


def eventually(check: Callable[[], str | None], spin: Callable[[float], None], timeout: float, what: str,
               sup: Supervisor | None = None) -> None:
    """Spin until ``check()`` returns None (ok); on timeout fail with its last complaint."""
    end = time.monotonic() + timeout
    while True:
        if sup is not None:
            sup.poll()
            assert not [n for n, rc in sup.returncodes.items() if rc is not None], \
                f"node processes exited: {sup.returncodes}"
        problem = check()
        if problem is None:
            return
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}: {problem}")
        spin(0.1)


@dataclass
class Graph:
    """The running graph and the test process's probe node (rclpy)."""

    mw: RosProbe
    node: ProbeNode
    sup: Supervisor
    tmp: Path
    rosout: list = field(default_factory=list)  # every Log received on /rosout
    steps: list = field(default_factory=list)  # env_steps from /env_step

    def spin(self, timeout_s: float) -> None:
        self.mw.spin(timeout_s=timeout_s)

    def result(self, future, timeout_s: float, what: str):
        self.mw.spin(until=future.done, timeout_s=timeout_s)
        assert future.done(), f"no answer within {timeout_s} s: {what}"
        return future.result()


@pytest.fixture(scope="module")
def graph(tmp_path_factory):
    """One graph for the module: every node process on rclpy, in a DDS domain of its own.
    The probe subscribes to /rosout before the nodes start, so it sees their first lines."""
    tmp = tmp_path_factory.mktemp("ros_tooling")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ROS_DOMAIN_ID", str(new_domain()))
        mp.setenv("ROS_LOG_DIR", str(tmp / "ros_log"))  # rcl's log files: here, not in ~/.ros/log
        mw = RosProbe(["probe"])  # loopback defaults before rclpy.init
        sup = None
        try:
            probe = mw.create_node("probe")
            g = Graph(mw, probe, None, tmp)  # type: ignore[arg-type]
            probe.create_subscription(Log, "/rosout", g.rosout.append, ROSOUT_QOS)
            steps = probe.create_subscription(wire.FLOATS, "/env_step",
                                              lambda m: g.steps.append(wire.read_record(m, wire.STEP_FIELDS)), STEP_QOS)
            sup = g.sup = start_graph(tmp, episodes=EPISODES)

            def running() -> str | None:
                names = {name for name, ns in g.node.get_node_names_and_namespaces() if ns == "/"}
                if missing := set(NODES) - names:
                    return f"nodes {sorted(missing)} not in the graph yet"
                if not any(s["env_steps"] > 0 for s in g.steps):
                    return "the environment has not stepped yet"
                return None

            eventually(running, g.spin, 120, "the graph to run", sup)
            g.node.destroy_subscription(steps)  # seen it step; no need to follow every step
            yield g
        finally:
            codes = sup.stop() if sup is not None else {}
            mw.shutdown()
    assert all(rc == 0 for rc in codes.values()), f"node exit codes after SIGINT: {codes}"


def started_parameters(tmp: Path) -> dict[str, dict[str, Any]]:
    """Per node, what it was started with: ``params.yaml`` (``/**``, then ``/**/<node>`` or
    ``/learner``) and the command line (``seed``; ``resume`` for the learner)."""
    doc = yaml.safe_load((tmp / "run" / "params.yaml").read_text())
    shared = doc["/**"]["ros__parameters"]
    started = {}
    for node in NODES:
        key = "/learner" if node == "learner" else f"/**/{node}"
        started[node] = {**shared, **doc.get(key, {}).get("ros__parameters", {}), "seed": 3}
    started["learner"]["resume"] = True
    return started


def test_declared_parameter_dicts_exist():
    """The names this module compares against are the nodes' own declarations."""
    assert {"algo", "env", "view", "seed"} <= set(ENV_PARAMETERS)
    assert {"wait_for_learner", "step_period", "publish_clock"} <= set(environment.PARAMETERS)
    assert {"episodes", "run_dir", "groups", "config"} <= set(learner.PARAMETERS)
    assert {"epsilon", "checkpoint", "meta_state"} <= set(CONTROLLER_PARAMETERS)
    for node in NODES:
        assert set(ENV_PARAMETERS) <= set(DECLARED[node]), node
    assert {"goal_pose_topic", "subgoal_poses_topic"} <= set(meta_controller.PARAMETERS) - set(sub_controller.PARAMETERS)
    assert {"cmd_vel_topic", "action_table"} <= set(sub_controller.PARAMETERS) - set(meta_controller.PARAMETERS)


def test_parameters_through_the_parameter_services(graph):
    """What ``ros2 param list`` / ``ros2 param get`` show, for every node: the declared
    names (plus rclpy's own), and the values the node was started with."""
    started = started_parameters(graph.tmp)
    got = {}
    for node in NODES:
        client = AsyncParameterClient(graph.node, f"/{node}")
        graph.mw.spin(until=client.services_are_ready, timeout_s=30)
        assert client.services_are_ready(), f"/{node} offers no parameter services"
        names = set(graph.result(client.list_parameters(), 10, f"list_parameters of /{node}").result.names)
        declared = set(DECLARED[node])
        assert declared <= names, f"/{node} lacks {sorted(declared - names)}"
        assert names - declared <= RCLPY_PARAMETERS, f"/{node} has undeclared {sorted(names - declared)}"
        assert "use_sim_time" in names
        ordered = sorted(declared)
        reply = graph.result(client.get_parameters(ordered), 10, f"get_parameters of /{node}")
        values = got[node] = {name: parameter_value_to_python(v) for name, v in zip(ordered, reply.values)}
        expected = {**{name: param.default for name, param in DECLARED[node].items()}, **started[node]}
        assert values == {name: expected[name] for name in ordered}, f"/{node}"
        # the values themselves, not only "what params.yaml says"
        assert (values["algo"], values["env"], values["view"], values["seed"]) == ("hdrqn-v2", ENV, "5", 3), node
    assert got["learner"]["episodes"] == EPISODES != learner.PARAMETERS["episodes"].default
    assert (got["learner"]["run_dir"], got["learner"]["groups"], got["learner"]["resume"]) == \
        (str(graph.tmp / "run"), ["/"], True)
    assert got["environment"]["wait_for_learner"] is True and got["environment"]["publish_clock"] is True
    assert got["meta_controller"]["subgoal_table"] == str(CONFIG / "nav2" / "subgoals.yaml")
    env = AsyncParameterClient(graph.node, "/environment")
    reply = graph.result(env.get_parameters(["wait_for_learner", "publish_clock", "step_log"]), 10, "environment")
    assert [parameter_value_to_python(v) for v in reply.values] == [True, True, str(graph.tmp / "env_steps.jsonl")]
    sub = AsyncParameterClient(graph.node, "/sub_controller")
    reply = graph.result(sub.get_parameters(["action_table", "observation_source"]), 10, "sub_controller")
    assert [parameter_value_to_python(v) for v in reply.values] == [str(CONFIG / "nav2" / "actions.yaml"), "topic"]


REFUSED = {  # node: (parameter, value, words the reason must hold)
    "environment": [("algo", "nonsense", "read-only"), ("num_envs", 99999, "read-only"),
                    ("action_timeout", -1.0, "must be > 0"), ("action_timeout", "soon", "type")],
    "critic": [("env", "hdrqn/FourRooms-2Goals-v0", "read-only"), ("option_timeout", -5.0, "out of range")],
    "meta_controller": [("checkpoint", "/nonexistent.pt", "read-only"), ("epsilon", 5.0, "out of range")],
    "sub_controller": [("algo", "nonsense", "read-only"), ("epsilon", 5.0, "out of range"),
                       ("num_envs", 2, "read-only"), ("checkpoint", "/nonexistent.pt", "read-only"),
                       ("stale_after_s", 0.0, "must be > 0"), ("epsilon", "zero", "type")],
    "learner": [("episodes", 5, "read-only"), ("record", "/tmp/x", "read-only")],
}
"""What ``ros2 param set`` must refuse, per node kind (issue 27's measured four among them)."""
ACCEPTED = {"environment": ("action_timeout", 6.0), "critic": ("option_timeout", 0.0),
            "meta_controller": ("epsilon", 0.0), "sub_controller": ("epsilon", 0.0)}
"""A live parameter per node kind that ``ros2 param set`` changes (the value is the node's already
or harmless for the running graph)."""


def test_param_set_refuses_with_a_reason_and_accepts_live_ones(graph):
    """``ros2 param set``: read-only, out-of-range and wrongly typed values are refused with a
    reason naming the parameter or the rule, and the node keeps its value; a live parameter
    is changed, and the node logs it."""
    for node, cases in REFUSED.items():
        client = AsyncParameterClient(graph.node, f"/{node}")
        graph.mw.spin(until=client.services_are_ready, timeout_s=30)
        for name, value, words in cases:
            before = graph.result(client.get_parameters([name]), 10, f"{node} {name}").values[0]
            result = graph.result(client.set_parameters([Parameter(name, value=value)]), 10, f"set {node} {name}")
            outcome = result.results[0]
            assert not outcome.successful, f"/{node} accepted {name}={value!r}"
            assert words in outcome.reason.lower(), f"/{node} {name}: {outcome.reason!r}"
            assert words == "type" or name in outcome.reason, f"/{node} {name}: {outcome.reason!r}"  # rclpy's own
            # type check names the expected type only (one parameter per call here)
            after = graph.result(client.get_parameters([name]), 10, f"{node} {name}").values[0]
            assert parameter_value_to_python(after) == parameter_value_to_python(before)
    for node, (name, value) in ACCEPTED.items():
        client = AsyncParameterClient(graph.node, f"/{node}")
        result = graph.result(client.set_parameters([Parameter(name, value=value)]), 10, f"set {node} {name}")
        assert [r.successful for r in result.results] == [True], f"/{node} {name}: {result.results[0].reason}"
        reply = graph.result(client.get_parameters([name]), 10, f"{node} {name}")
        assert parameter_value_to_python(reply.values[0]) == value
        eventually(lambda: None if any(f"parameter {name} set to" in m.msg and m.name == node for m in graph.rosout)
                   else "no log line yet", graph.spin, 30, f"/{node}'s log of {name}")


def test_param_describe_shows_descriptions_and_rules(graph):
    """``ros2 param describe``: every declared parameter has a description; read-only ones say
    so (on a managed node: writable only while unconfigured); ranges are the descriptor's."""
    for node in NODES:
        client = AsyncParameterClient(graph.node, f"/{node}")
        graph.mw.spin(until=client.services_are_ready, timeout_s=30)
        names = sorted(set(DECLARED[node]) - RCLPY_PARAMETERS)
        descriptors = {d.name: d for d in graph.result(client.describe_parameters(names), 10, node).descriptors}
        for name in names:
            assert descriptors[name].description, f"/{node} {name} has no description"
        algo = descriptors["algo"]
        if node in MANAGED:
            assert not algo.read_only and "unconfigured" in algo.additional_constraints, (node, algo)
        else:
            assert algo.read_only and "read-only" in algo.additional_constraints, (node, algo)
    sub = AsyncParameterClient(graph.node, "/sub_controller")
    epsilon = graph.result(sub.describe_parameters(["epsilon"]), 10, "epsilon").descriptors[0]
    assert not epsilon.read_only
    assert (epsilon.floating_point_range[0].from_value, epsilon.floating_point_range[0].to_value) == (-1.0, 1.0)


DIAGNOSED = ("meta_controller", "sub_controller")
"""The training graph's nodes that publish ``/diagnostics`` (docs/topics.md)."""


def test_node_and_topic_introspection_matches_the_docs(graph):
    """``ros2 node list``, ``ros2 topic list -t`` and ``ros2 node info``: the five nodes,
    every topic with the type of docs/topics.md (and the lifecycle nodes' ``~/transition_event``),
    and who publishes what."""
    table = documented_topics()
    assert {"/env_step", "/observation", "/learner/status", "/clock", "/sub_state"} <= set(table)
    assert table["/env_step"]["type"] == wire.FLOATS and table["/observation"]["type"] == wire.IMAGE
    assert table["/learner/status"] == {"type": wire.STRING, "publisher": "learner", "subscribers": set()}
    lifecycle = {f"/{node}/{LIFECYCLE_TOPIC[0]}": {"type": LIFECYCLE_TOPIC[1], "publisher": node} for node in MANAGED}
    topics = {**table, **nav2_topics(), **lifecycle}
    expected = {name: [row["type"]] for name, row in topics.items()} | {t: [ty] for t, ty in RCLPY_TOPICS.items()}

    names = {name for name, ns in graph.node.get_node_names_and_namespaces() if ns == "/"}
    assert set(NODES) <= names and names - set(NODES) <= {"probe"}, names

    def topic_list() -> str | None:
        got = dict(graph.node.get_topic_names_and_types())
        return None if got == expected else f"got {got}, expected {expected}"

    eventually(topic_list, graph.spin, 20, "the graph's topics", graph.sup)
    for node in NODES:
        published = dict(graph.node.get_publisher_names_and_types_by_node(node, "/"))
        want = {name: [row["type"]] for name, row in topics.items() if row["publisher"] == node or
                (name == "/diagnostics" and node in DIAGNOSED)}  # the one topic with several publishers
        assert published == {**want, **{t: [ty] for t, ty in RCLPY_TOPICS.items()}}, f"publishers of /{node}"
        subscribed = dict(graph.node.get_subscriber_names_and_types_by_node(node, "/"))
        want = {name: [row["type"]] for name, row in table.items() if node in row["subscribers"]}
        assert subscribed == want, f"subscriptions of /{node}"
    # ``ros2 topic info -v /rosout``: rcl's rosout profile, which ROSOUT_QOS asks for
    offers = [i for i in graph.node.get_publishers_info_by_topic("/rosout") if i.node_name in NODES]
    assert {i.node_name for i in offers} == set(NODES)
    for info in offers:
        assert info.qos_profile.reliability == ReliabilityPolicy.RELIABLE
        assert info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL


def test_node_log_lines_reach_rosout(graph):
    """``ros2 topic echo /rosout``: the nodes' log lines, with their node names, severities
    and the text of their log files."""
    def weights_lines() -> str | None:
        lines = {(m.name, m.level) for m in graph.rosout if "acting with the learner's" in m.msg}
        want = {("sub_controller", Log.INFO), ("meta_controller", Log.INFO)}
        return None if want <= lines else f"have {sorted(lines)} of {sorted(want)}"

    eventually(weights_lines, graph.spin, 30, "the controllers' weights lines on /rosout", graph.sup)
    sub = next(m for m in graph.rosout if m.name == "sub_controller" and "sub weights" in m.msg)
    assert re.fullmatch(r"acting with the learner's sub weights of update \d+", sub.msg), sub.msg
    # every node logs at least its middleware line at start-up
    assert {m.name for m in graph.rosout} >= set(NODES), sorted({m.name for m in graph.rosout})
    logs = graph.tmp / "logs"
    for m in graph.rosout:
        if m.name in NODES:  # the same line in the node's console output (its log file)
            log = logs / ("learner.log" if m.name == "learner" else f"graph_{m.name}.log")
            assert m.msg in log.read_text(), f"{m.name}: {m.msg!r} not in {log.name}"
    assert all(m.stamp.sec > 0 for m in graph.rosout)


LOG_SEQUENCE = [("info", Log.INFO, "INFO"), ("warning", Log.WARN, "WARN"), ("error", Log.ERROR, "ERROR"),
                ("info", Log.INFO, "INFO")]


def test_logger_severities_in_process_reach_rosout(graph):
    """info, warning, error, info again through the :mod:`logging` logger a node hands the
    protocol layer (:func:`~hdrqn_ros.nodes.node_logger.python_logger`): all four arrive on
    /rosout, in order, with their severities (no "severity cannot be changed")."""
    logger = python_logger(graph.mw.create_node("log_probe"))
    tag = f"tooling-{time.monotonic_ns()}"
    for i, (method, _, _) in enumerate(LOG_SEQUENCE):
        getattr(logger, method)("%s line %d", tag, i)

    def arrived() -> str | None:
        got = [m for m in graph.rosout if m.name == "log_probe" and tag in m.msg]
        return None if len(got) >= len(LOG_SEQUENCE) else f"{len(got)} lines so far"

    eventually(arrived, graph.spin, 10, "the four log_probe lines on /rosout")
    got = [(m.msg, m.level) for m in graph.rosout if m.name == "log_probe" and tag in m.msg]
    assert got == [(f"{tag} line {i}", level) for i, (_, level, _) in enumerate(LOG_SEQUENCE)]


def run_rclpy_child(code: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """``code`` in a new Python process with ``logger``, the :mod:`logging` logger of the rclpy
    node ``child`` (loopback defaults applied before rclpy.init); shut down at the end."""
    script = ("import rclpy\n"
              "from hdrqn_ros.dds import apply_rmw_network_defaults\n"
              "from hdrqn_ros.nodes.node_logger import python_logger\n"
              "apply_rmw_network_defaults(None)\n"
              "rclpy.init(args=['child'])\n"
              "node = rclpy.create_node('child')\n"
              "logger = python_logger(node)\n"
              "try:\n" + "".join(f"    {line}\n" for line in code.splitlines()) +
              "finally:\n    node.destroy_node()\n    rclpy.shutdown()\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("RCUTILS_")}  # rcutils' default console format
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=timeout, env=env)
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr and "cannot be changed" not in run.stderr, run.stderr
    return run


def test_logger_severities_show_on_stderr(graph):
    """The same four lines in a process of their own: rclpy's console output (stderr)."""
    run = run_rclpy_child("\n".join(f"logger.{method}('stderr line %d', {i})"
                                    for i, (method, _, _) in enumerate(LOG_SEQUENCE)))
    lines = [line for line in run.stderr.splitlines() if "stderr line" in line]
    assert len(lines) == len(LOG_SEQUENCE), run.stderr
    for i, (line, (_, _, severity)) in enumerate(zip(lines, LOG_SEQUENCE)):
        assert re.fullmatch(rf"\[{severity}\] \[[\d.]+\] \[child\]: stderr line {i}", line), line


def test_throttled_rejections_on_rclpy(graph):
    """200 rejections within a second through :class:`Throttle` on an rclpy node's logger
    (:func:`~hdrqn_ros.nodes.node_logger.python_logger`):
    the burst, then nothing more until the period ends; each line has the running count."""
    run = run_rclpy_child("import time\n"
                          "from hdrqn_ros.throttle import Throttle\n"
                          "rejected = Throttle(logger, 'rejected a message on /probe')\n"
                          "start = time.monotonic()\n"
                          "for i in range(200):\n"
                          "    rejected.warn(f'bad message {i}')\n"
                          "print(time.monotonic() - start, rejected.count)\n")
    elapsed, count = run.stdout.split()
    assert float(elapsed) < 1.0 and int(count) == 200
    lines = [line for line in run.stderr.splitlines() if "rejected a message on /probe" in line]
    assert BURST <= len(lines) <= BURST + 1, run.stderr
    counts = []
    for line in lines:
        m = re.fullmatch(r"\[WARN\] \[[\d.]+\] \[child\]: rejected a message on /probe: bad message (\d+) "
                         r"\((\d+) so far\)", line)
        assert m, line
        assert int(m[2]) == int(m[1]) + 1, line  # the count includes this rejection
        counts.append(int(m[2]))
    assert counts[:BURST] == list(range(1, BURST + 1)) and counts == sorted(counts)
