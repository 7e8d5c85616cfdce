"""The node graph as real processes, on real rclpy (ROS 2 Jazzy, Fast DDS) and on real
Cyclone DDS (loopback only; no fake bus): every graph test runs on both backends
(the ``backend`` fixture), and a mixed graph runs half the nodes on each."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from itertools import count
from pathlib import Path

import numpy as np
import pytest

from hdrqn_ros.config import build_config
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.graph import graph_processes, write_params
from hdrqn_ros.middleware.cyclone import CycloneMiddleware, _dds_qos
from hdrqn_ros.middleware.rclpy_backend import RclpyMiddleware
from hdrqn_ros.middleware.messages import typestore, to_rosbags
from hdrqn_ros.middleware.port import LATCHED_QOS, QoS
from hdrqn_ros.protocol import wire
from hdrqn_ros.protocol.wire import obs_digest
from hdrqn_ros.recording.bag import BagWriter
from hdrqn_ros.recording.transitions import GROUP_TOPICS, episode_summary, read_episodes
from hdrqn_ros.nodes import STACK_DUMP_SIGNAL
from hdrqn_ros.supervisor import Supervisor
from hdrqn_ros.throttle import BURST, THROTTLE_PERIOD_S

from conftest import NO_RCLPY, node_process, probe_middleware

ENV = "hdrqn/GridWorld-2Goals-v0"
FLOOD = 300
"""Bad messages of one kind sent in a burst by the malformed-messages test."""
_domains = count((os.getpid() * 13) % 150 + 20)


@pytest.fixture
def domain(monkeypatch):
    """A DDS domain of this test's own, so tests running side by side never meet."""
    d = next(_domains) % 200 + 20
    monkeypatch.setenv("ROS_DOMAIN_ID", str(d))
    monkeypatch.delenv("CYCLONEDDS_URI", raising=False)
    return d


def wait_for(cond, timeout: float, what: str, sup: Supervisor | None = None):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if sup is not None:
            sup.poll()
        value = cond()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


CONFIG = Path(__file__).resolve().parents[1] / "config"


def graph_params(tmp_path: Path, cfg, groups: int = 1, extra: dict | None = None, num_envs: int = 1) -> Path:
    """``tmp_path/run`` with the config as ``config-in.yaml`` and the graph's ``params.yaml`` (returned)."""
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    config = run_dir / "config-in.yaml"
    config.write_text(json.dumps(cfg.model_dump()))
    return write_params(cfg, run_dir, groups, config, extra=extra, num_envs=num_envs)


def start_graph(tmp_path: Path, algo: str = "hdrqn-v2", episodes: int = 8, respawn: bool = False,
                learner: dict | None = None, middleware: dict[str, str] | None = None, num_envs: int = 1) -> Supervisor:
    """The graph with the Nav2 adapters on (one environment), or a batch of ``num_envs``."""
    cfg = build_config([], algo=algo, env=ENV, episodes=episodes, seed=3, learning_starts=60, checkpoint_every=2,
                       eval_episodes=4, update_every=5, sub={"batch_size": 2}, meta={"batch_size": 2})
    nav = {"meta_controller": {"subgoal_table": str(CONFIG / "nav2" / "subgoals.yaml")},
           "sub_controller": {"action_table": str(CONFIG / "nav2" / "actions.yaml")}} if num_envs == 1 else {}
    params = graph_params(tmp_path, cfg, num_envs=num_envs, extra={
        "environment": {"step_log": str(tmp_path / "env_steps.jsonl")},
        "learner": {"transition_log": str(tmp_path / "transitions.jsonl"), "weights_every": 5, **(learner or {})},
        **nav})
    sup = Supervisor(graph_processes(cfg, params, 1, respawn=respawn, middleware=middleware), log_dir=tmp_path / "logs",
                     stop_timeout_s=30)
    sup.start()
    return sup


def check_env_log_replays_in_process(env_rows: list[dict], seed: int = 3) -> None:
    """The environment node's steps equal an in-process env stepped with the same seed and
    actions (environment ``i`` of a batch: seed + i)."""
    for i in sorted({row["env"] for row in env_rows}):
        check_one_env_replays(i, [row for row in env_rows if row["env"] == i], seed + i)


def check_one_env_replays(env: int, env_rows: list[dict], seed: int) -> None:
    batch = make_batch(ENV, 1)
    obs = batch.reset(seed=seed)[0]
    for row in env_rows:
        assert row["obs"] == obs_digest(obs), f"observation mismatch before step key {row['key']} of env {env}"
        step = batch.step(np.array([row["action"]]))
        assert row["next_obs"] == obs_digest(step.obs[0])
        assert (row["extrinsic"], row["terminated"], row["truncated"]) == \
            (float(step.extrinsic[0]), bool(step.terminated[0]), bool(step.truncated[0]))
        obs = batch.reset_where(np.ones(1, bool))[0] if step.done[0] else step.obs[0]


def check_transitions_match_env(transitions: list[dict], env_rows: list[dict]) -> None:
    """Every transition the learner assembled is the environment's step with that key (and
    environment of the batch)."""
    by_key = {(r["key"], r["env"]): r for r in env_rows}
    assert transitions, "the learner assembled no transitions"
    for tr in transitions:
        env = by_key[tr["key"], tr["env"]]
        for field in ("prev_key", "action", "extrinsic", "classical", "terminated", "truncated", "obs", "next_obs"):
            assert tr[field] == env[field], f"{field} of transition {tr['key']}: {tr[field]} != {env[field]}"


def test_payload_bytes_equal_rosbags_cdr(domain):
    """Bytes taken off a real DDS reader equal rosbags' CDR of the same message, per published type."""
    from cyclonedds._clayer import ddspy_take
    from cyclonedds.core import InstanceState, SampleState, ViewState
    from cyclonedds.sub import DataReader

    mw = CycloneMiddleware([])
    try:
        node = mw.create_node("probe")
        samples = wire_samples(node)
        store = typestore()
        for i, (type_name, msg) in enumerate(samples.items()):
            topic = f"/probe{i}"
            pub = node.create_publisher(type_name, topic, LATCHED_QOS)
            reader = DataReader(mw.participant, mw.topic(topic, type(msg)), qos=_dds_qos(LATCHED_QOS))
            pub.publish(msg)
            raw = wait_for(lambda: ddspy_take(reader._ref, SampleState.Any | ViewState.Any | InstanceState.Any, 1),
                           5, f"a sample of {type_name}")
            sample = bytes(raw[0][0])
            expected = bytes(store.serialize_cdr(to_rosbags(msg), type_name))
            assert sample[:4] == b"\x00\x01\x00\x00", "XCDR1 little-endian encapsulation"
            assert sample[:len(expected)] == expected and not any(sample[len(expected):]), type_name
    finally:
        mw.shutdown()


def wire_samples(node) -> dict:
    """One message of every type the graph publishes, built through ``node``'s backend."""
    rng = np.random.default_rng(0)
    return {
        wire.IMAGE: wire.make_image(node, 123_000_000, rng.integers(0, 255, (44, 44, 3), dtype=np.uint8), "map"),
        wire.FLOATS: wire.make_record(node, wire.FLOATS, wire.CRITIC_FIELDS, [5e6, -1.0, 0, 1, 1]),
        wire.INTS: wire.make_record(node, wire.INTS, wire.ACTION_FIELDS, [5_000_000, 3]),
        wire.BYTES: wire.make_weights(node, b"\x01\x02\x03", 7),
        wire.STRING: node.msg(wire.STRING)(data='{"episodes": 3}'),
        wire.POSE_STAMPED: wire.make_pose(node, 10, "map", 1.5, -2.0),
        wire.CLOCK_TYPE: node.msg(wire.CLOCK_TYPE)(clock=wire.make_time(node, 3_000_000_123)),
        "geometry_msgs/msg/Twist": node.msg("geometry_msgs/msg/Twist")(
            linear=node.msg("geometry_msgs/msg/Vector3")(x=0.2, y=0.0, z=0.0)),
    }


@NO_RCLPY
def test_rclpy_serializes_every_graph_message_like_the_cyclone_backend(domain):
    """rclpy's own serializer (rmw_fastrtps) and the Cyclone backend encode each message type of
    the graph alike (same length, same values, padding aside), and each decodes the other's bytes."""
    rclpy_mw, cyclone_mw = RclpyMiddleware(["probe"]), CycloneMiddleware([])
    try:
        ours, theirs = wire_samples(cyclone_mw.create_node("a")), wire_samples(rclpy_node := rclpy_mw.create_node("b"))
        cyc = cyclone_mw.create_node("c")
        for type_name, msg in ours.items():
            a, b = cyc.to_cdr(msg), rclpy_node.to_cdr(theirs[type_name])
            # Fast CDR leaves alignment padding unset, so compare after a decode and a re-encode
            assert len(a) == len(b) and cyc.to_cdr(cyc.from_cdr(type_name, b)) == a, type_name
            back = rclpy_node.to_cdr(rclpy_node.from_cdr(type_name, a))
            assert cyc.to_cdr(cyc.from_cdr(type_name, back)) == a, type_name
    finally:
        rclpy_mw.shutdown()
        cyclone_mw.shutdown()


def record_like_ros2_bag(node, writer: BagWriter, topics: dict[str, str]) -> None:
    """What ``ros2 bag record -s mcap`` does: subscribe, write each sample's CDR at receipt time."""
    for topic, type_name in topics.items():
        conn = writer.add_topic(topic, type_name, depth=wire.STEP_QOS.depth)
        node.create_subscription(type_name, topic, lambda m, c=conn: writer.write(c, time.time_ns(), node.to_cdr(m)),
                                 wire.STEP_QOS)


def test_graph_trains_and_transitions_align(domain, backend, tmp_path):
    """Also: the Nav2 adapters publish a goal_pose per option and a cmd_vel per action; the
    learner records what it receives, and a ros2-bag-record-style recorder records the topics."""
    learner_bag, ros2_bag = tmp_path / "learner-bag", tmp_path / "ros2-bag"
    mw = probe_middleware(backend)
    goals, twists, subgoals = [], [], []
    writer = BagWriter(ros2_bag)
    sup = None
    try:  # the recorder is up before the graph, as one starts `ros2 bag record` first
        node = mw.create_node("nav_probe")
        node.create_subscription(wire.POSE_STAMPED, "/goal_pose", goals.append)
        node.create_subscription("geometry_msgs/msg/Twist", "/cmd_vel", twists.append)
        node.create_subscription(wire.INTS, "/subgoal", lambda m: subgoals.append(wire.read_record(m, wire.SUBGOAL_FIELDS,
                                                                                               np.int64)))
        record_like_ros2_bag(node, writer, {**{f"/{t}": ty for t, ty in GROUP_TOPICS.items()},
                                            "/clock": wire.CLOCK_TYPE})
        sup = start_graph(tmp_path, episodes=8, learner={"record": str(learner_bag)})

        def finished():
            mw.spin(timeout_s=0.05)
            return (tmp_path / "run" / "summary.json").exists()

        wait_for(finished, 150, "the learner to finish", sup)
    finally:
        mw.shutdown()
        writer.close()
        if sup is not None:
            sup.stop()
    check_recordings(tmp_path, learner_bag, ros2_bag)
    assert twists and goals and len(twists) > len(goals)
    assert {round(g.pose.position.x, 3) for g in goals} <= {1.0, 3.5}  # poses from config/nav2/subgoals.yaml
    assert any(s["new_option"] for s in subgoals)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["episodes"] == 8 and summary["updates"] > 0
    env_rows, transitions = read_jsonl(tmp_path / "env_steps.jsonl"), read_jsonl(tmp_path / "transitions.jsonl")
    assert len(transitions) >= 200
    check_env_log_replays_in_process(env_rows)
    check_transitions_match_env(transitions, env_rows)
    sub_log = (tmp_path / "logs" / "graph_sub_controller.log").read_text()
    assert "acting with the learner's sub weights of update 0" in sub_log


def check_recordings(tmp_path: Path, learner_bag: Path, ros2_bag: Path) -> None:
    """Both bags give the same episodes; the learner node trains offline from its bag."""
    cfg = build_config([tmp_path / "run" / "config-in.yaml"])
    episodes = {}
    for bag in (learner_bag, ros2_bag):
        episodes[bag] = {ep.frames.tobytes(): (ep, meta) for _, ep, meta, _ in read_episodes([bag], cfg, 2)}
    assert len(episodes[learner_bag]) >= 8
    shared = episodes[learner_bag].keys() & episodes[ros2_bag].keys()
    assert len(shared) >= 6  # the test's recorder may join after the first episode began
    for frames in shared:
        (a, am), (b, bm) = episodes[learner_bag][frames], episodes[ros2_bag][frames]
        assert all(np.array_equal(a.fields[k], b.fields[k]) for k in a.fields)
        assert np.array_equal(am.frames, bm.frames) and np.array_equal(am.fields["action"], bm.fields["action"])
    out = tmp_path / "offline"
    run = subprocess.run([sys.executable, "-m", "hdrqn_ros.nodes.learner", "--ros-args", "-p",
                          f"config:={tmp_path / 'run' / 'config-in.yaml'}", "-p", "groups:=['']", "-p",
                          f"bags:=['{learner_bag}']", "-p", "offline_updates:=10", "-p", f"run_dir:={out}",
                          "-p", "episodes:=8", "-p", "seed:=3"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["prefilled"]["episodes"] == len(episodes[learner_bag]) and summary["updates"] == 10


@pytest.mark.parametrize("algo", ["hdrqn-v1", "dqn"])
def test_other_algorithms_train_aligned(domain, backend, tmp_path, algo):
    """Image-input meta-controller (hDRQNv1) and a flat agent (no critic, no meta)."""
    assert train_to_the_end_aligned(tmp_path, algo=algo)["updates"] > 0


def train_to_the_end_aligned(tmp_path: Path, episodes: int = 5, **graph) -> dict:
    """Run ``start_graph(tmp_path, episodes=episodes, **graph)`` until the learner finishes,
    check every transition against the environment's log; the learner's summary."""
    sup = start_graph(tmp_path, episodes=episodes, **graph)
    try:
        wait_for(lambda: (tmp_path / "run" / "summary.json").exists(), 150, "the learner to finish", sup)
    finally:
        sup.stop()
    env_rows, transitions = read_jsonl(tmp_path / "env_steps.jsonl"), read_jsonl(tmp_path / "transitions.jsonl")
    check_env_log_replays_in_process(env_rows)
    check_transitions_match_env(transitions, env_rows)
    return json.loads((tmp_path / "run" / "summary.json").read_text())


@pytest.mark.parametrize("num_envs", [1, 4], ids=["one-env", "batch-of-4"])
def test_learner_killed_and_restarted_resumes_aligned(domain, backend, tmp_path, num_envs):
    """kill -9 of the learner mid-run, also with a batched group."""
    sup = start_graph(tmp_path, episodes=10, respawn=True, num_envs=num_envs)
    status = tmp_path / "run" / "status.json"
    try:
        checkpoint = tmp_path / "run" / "checkpoints" / "last.pt"  # written atomically, after the count goes up
        wait_for(lambda: status.exists() and json.loads(status.read_text())["episodes"] >= 3 and checkpoint.exists(),
                 120, "3 episodes and a checkpoint before the kill", sup)
        sup.kill("learner")
        wait_for(lambda: sup.restarts["learner"] >= 1, 60, "the learner respawn", sup)
        wait_for(lambda: (tmp_path / "run" / "summary.json").exists(), 150, "the learner to finish", sup)
    finally:
        sup.stop()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["episodes"] == 10
    env_rows, transitions = read_jsonl(tmp_path / "env_steps.jsonl"), read_jsonl(tmp_path / "transitions.jsonl")
    check_env_log_replays_in_process(env_rows)
    check_transitions_match_env(transitions, env_rows)
    assert "resumed from" in (tmp_path / "logs" / "learner.log").read_text()


def test_batched_group_trains_records_and_aligns(domain, backend, tmp_path):
    """One environment node steps 4 environments as a batch: every transition is its
    environment's step, the learner's bag holds the batched messages, and ``bag info`` and
    the bag reader take each environment's episodes from them."""
    bag = tmp_path / "learner-bag"
    summary = train_to_the_end_aligned(tmp_path, episodes=12, num_envs=4, learner={"record": str(bag)})
    assert summary["episodes"] == 12 and summary["updates"] > 0
    group = summary["groups"]["/"]
    assert group["num_envs"] == 4 and group["lost_episodes"] == 0 and group["rejected"] == 0
    transitions = read_jsonl(tmp_path / "transitions.jsonl")
    assert {t["env"] for t in transitions} == {0, 1, 2, 3}
    info = episode_summary(bag)["/"]
    assert info["num_envs"] == 4 and info["episodes"] >= 12
    cfg = build_config([tmp_path / "run" / "config-in.yaml"])
    episodes = list(read_episodes([bag], cfg, 2))
    assert len(episodes) == info["episodes"]
    assert sum(len(sub.fields["action"]) for _, sub, _, _ in episodes) <= len(transitions)


def test_nodes_of_a_group_with_different_num_envs_stop_with_exit_2(domain, backend, tmp_path):
    """An environment of 4 and a sub-controller of 1: the sub-controller exits 2 naming both
    values, and never answers (no misaligned transitions)."""
    common = ["--ros-args", "-p", "algo:=drqn", "-p", "epsilon:=1.0"]
    env = subprocess.Popen([sys.executable, "-m", "hdrqn_ros.nodes.environment", *common, "-p", "num_envs:=4"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        sub = subprocess.run([sys.executable, "-c", "import sys; from hdrqn_ros.nodes.controllers import main_sub "
                              "as m; sys.exit(m())", *common], capture_output=True, text=True, timeout=60)
    finally:
        env.terminate()
        env.wait(10)
    assert sub.returncode == 2, sub.stderr
    assert "steps of 4 environment(s)" in sub.stderr and "num_envs 1" in sub.stderr
    bad = subprocess.run([sys.executable, "-m", "hdrqn_ros.nodes.environment", *common, "-p", "num_envs:=0"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "num_envs must be in 1..64, got 0" in bad.stderr


def test_sub_controller_drives_cmd_vel_from_a_costmap(domain, backend, tmp_path):
    """Nav2 path: OccupancyGrid in, Twist out, no environment node; zero Twist on shutdown."""
    spec = node_process("sub", "sub_controller", "-p", "algo:=drqn", "-p", "epsilon:=0.0",
                        "-p", "observation_source:=costmap", "-p", f"action_table:={CONFIG / 'nav2' / 'actions.yaml'}")
    sup = Supervisor([spec], log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    mw = probe_middleware(backend)
    twists = []
    try:
        node = mw.create_node("robot")
        node.create_subscription("geometry_msgs/msg/Twist", "/cmd_vel", twists.append)
        pub = node.create_publisher("nav_msgs/msg/OccupancyGrid", "/local_costmap/costmap", LATCHED_QOS)
        grid = node.msg("nav_msgs/msg/OccupancyGrid")(
            header=wire.make_header(node, 5_000_000_000, "odom"),
            info=node.msg("nav_msgs/msg/MapMetaData")(resolution=0.05, width=60, height=60),
            data=node.pack(np.zeros(3600, np.int8)))
        mw.spin(until=lambda: pub.get_subscription_count() > 0, timeout_s=120)
        sup.poll()
        assert pub.get_subscription_count() > 0, f"the sub-controller never subscribed: {sup.returncodes}"
        end = time.monotonic() + 120  # one costmap update per half second, as Nav2's local costmap publishes
        while len(twists) < 2 and time.monotonic() < end:
            pub.publish(grid)
            mw.spin(until=lambda: len(twists) >= 2, timeout_s=0.5)
        assert len(twists) >= 2, "no cmd_vel from the costmap"
        moving = len(twists)
        sup.stop()  # SIGINT: the node publishes the zero command on its way out
        mw.spin(until=lambda: len(twists) > moving and (twists[-1].linear.x, twists[-1].angular.z) == (0.0, 0.0),
                timeout_s=30)
        last = twists[-1]
        assert (last.linear.x, last.angular.z) == (0.0, 0.0), "no stop command on shutdown"
    finally:
        mw.shutdown()
        sup.stop()


def test_late_joiner_sees_ros_discovery_info(domain, backend, tmp_path):
    """Read by a Cyclone participant: rmw_fastrtps writes ros_discovery_info for rclpy nodes,
    the Cyclone backend for its own."""
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic

    from hdrqn_ros.middleware.messages import message_class

    specs = [node_process(name, node, "-r", "__ns:=/g7") for name, node in (("env", "environment"), ("critic", "critic"))]
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    try:
        logs = [tmp_path / "logs" / f"{name}.log" for name in ("env", "critic")]
        wait_for(lambda: all(log.exists() and "middleware" in log.read_text() for log in logs), 120,
                 "both nodes up before we join", sup)
        mw = CycloneMiddleware([])
        try:
            info = message_class("rmw_dds_common/msg/ParticipantEntitiesInfo")
            # keyless topic: a keep-last-1 reader would keep only one participant's sample
            reader = DataReader(mw.participant, Topic(mw.participant, "ros_discovery_info", info),
                                qos=_dds_qos(QoS(depth=64, transient_local=True)))
            seen: dict[str, int] = {}

            def nodes():
                for sample in reader.take(N=64):
                    for n in sample.node_entities_info_seq:
                        seen[f"{n.node_namespace}/{n.node_name}"] = len(n.writer_gid_seq)
                # the info is republished as each writer is created: wait for the full list
                # (observation, subgoal_images, env_step, pose, clock), not the first sample
                return {"/g7/environment", "/g7/critic"} <= set(seen) and seen["/g7/environment"] >= 5

            wait_for(nodes, 120, "ros_discovery_info listing /g7/critic and /g7/environment with its 5 writers", sup)
        finally:
            mw.shutdown()
    finally:
        sup.stop()


def test_a_node_prints_its_stacks_on_sigusr1_and_goes_on(domain, backend, tmp_path):
    """``kill -USR1`` shows where a node is (what the supervisor asks of a node that will not
    stop); the node keeps running and later stops normally."""
    sup = Supervisor([node_process("env", "environment")], log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    try:
        wait_for(lambda: "middleware" in sup.log_tail("env"), 120, "the environment node's start", sup)
        sup.kill("env", STACK_DUMP_SIGNAL)
        # written a line at a time: wait for the main thread's frame inside run_node
        wait_for(lambda: "in run_node" in sup.log_tail("env", 200), 60, "the node's stacks in its log", sup)
        assert "most recent call first" in sup.log_tail("env", 200)
    finally:
        codes = sup.stop()
    assert codes == {"env": 0}, sup.log_tail("env")


def test_malformed_messages_are_rejected_and_logged(domain, backend, tmp_path):
    """Bad messages from a real publisher of the same backend are rejected with a throttled
    warning; the nodes keep running and answering."""
    specs = [node_process("env", "environment"),
             node_process("sub", "sub_controller", "-p", "algo:=dqn", "-r", "observation:=/probe_obs",
                          "-r", "env_step:=/probe_step")]
    sup = Supervisor(specs, log_dir=tmp_path / "logs", stop_timeout_s=30)
    sup.start()
    mw = probe_middleware(backend)
    try:
        node = mw.create_node("prober")
        steps, actions = [], []
        node.create_subscription(wire.FLOATS, "/env_step", lambda m: steps.append(wire.read_record(m, wire.STEP_FIELDS)))
        node.create_subscription(wire.INTS, "/action", lambda m: actions.append(wire.read_record(m, ("key",), np.int64,
                                                                                             extra=True)))
        action_pub = node.create_publisher(wire.INTS, "/action")
        credit_pub = node.create_publisher(wire.FLOATS, "/learner_credit", LATCHED_QOS)
        obs_pub = node.create_publisher(wire.IMAGE, "/probe_obs")
        step_pub = node.create_publisher(wire.FLOATS, "/probe_step")
        mw.spin(until=lambda: bool(steps), timeout_s=120)
        assert steps, "the environment never stepped"
        key = int(steps[0]["key"])

        def sub_answers(k: int, deadline_s: float) -> bool:
            """Like the environment, send step ``k`` (again every 3 s) until the sub-controller answers it."""
            end = time.monotonic() + deadline_s
            step = dict(steps[0], key=k)
            while time.monotonic() < end:
                obs_pub.publish(wire.make_image(node, k, np.zeros((44, 44, 3), np.uint8), "map"))
                step_pub.publish(wire.make_record(node, wire.FLOATS, wire.STEP_FIELDS,
                                                  [step[f] for f in wire.STEP_FIELDS]))
                mw.spin(until=lambda: any(a["key"] == k for a in actions), timeout_s=3)
                if any(a["key"] == k for a in actions):
                    return True
            return False

        assert sub_answers(key + 1, 180), "the sub-controller never answered"  # it imports torch: slow under load
        for pub in (action_pub, credit_pub, obs_pub, step_pub):  # every reader has found our writers
            mw.spin(until=lambda: pub.get_subscription_count() > 0, timeout_s=60)
        flood_started = time.monotonic()
        action_pub.publish(wire.make_record(node, wire.INTS, wire.ACTION_FIELDS, [key, 99]))  # action out of range
        action_pub.publish(wire.make_record(node, wire.INTS, ("key",), [key]))  # too few values
        credit_pub.publish(wire.make_record(node, wire.FLOATS, wire.CREDIT_FIELDS, [np.nan, 0, 0, 0, 0]))  # NaN
        obs_pub.publish(wire.make_image(node, key + 20, np.zeros((30, 44, 3), np.uint8), "map"))  # wrong size
        bad = node.msg(wire.IMAGE)(header=wire.make_header(node, key + 20, "map"), height=44, width=44, encoding="bgr8",
                                step=132, data=node.pack(np.zeros(44 * 44 * 3, np.uint8)))
        obs_pub.publish(bad)  # wrong encoding
        nan_step = dict(steps[0], key=key + 20, extrinsic=np.nan)
        step_pub.publish(wire.make_record(node, wire.FLOATS, wire.STEP_FIELDS, [nan_step[f] for f in wire.STEP_FIELDS]))
        mw.spin(timeout_s=1.0)
        for i in range(FLOOD):  # a flood: the warnings are throttled, the nodes keep up
            action_pub.publish(wire.make_record(node, wire.INTS, wire.ACTION_FIELDS, [key, 99]))
            obs_pub.publish(wire.make_image(node, key + 20, np.zeros((30, 44, 3), np.uint8), "map"))
            if i % 20 == 0:
                mw.spin(timeout_s=0.01)
        mw.spin(timeout_s=1.0)
        action_pub.publish(wire.make_record(node, wire.INTS, wire.ACTION_FIELDS, [key, 1]))  # a good one: the env goes on
        mw.spin(until=lambda: len({s["key"] for s in steps}) >= 2, timeout_s=60)
        assert len({s["key"] for s in steps}) >= 2, "the environment stopped stepping"
        assert sub_answers(key + 30, 60), "the sub-controller stopped answering after the bad messages"
    finally:
        mw.shutdown()
        codes = sup.stop()
    flood_s = time.monotonic() - flood_started
    assert all(rc == 0 for rc in codes.values()), \
        f"{codes}\n" + "\n".join(f"--- {name}:\n{sup.log_tail(name)}" for name, rc in codes.items() if rc)
    env_log = (tmp_path / "logs" / "env.log").read_text()
    sub_log = (tmp_path / "logs" / "sub.log").read_text()
    assert "action 99 is out of range" in env_log and "expected 2 values" in env_log and "NaN" in env_log
    assert "image must be 44x44" in sub_log and "encoding must be rgb8" in sub_log and "non-finite" in sub_log
    assert "Traceback" not in env_log + sub_log
    for log, topic in ((env_log, "/action"), (sub_log, "/probe_obs")):
        lines = [line for line in log.splitlines() if f"rejected a message on {topic}:" in line]
        # the burst, then at most one line per throttle period while the flood was being read
        most = BURST + 1 + math.ceil(flood_s / THROTTLE_PERIOD_S)
        assert BURST <= len(lines) <= most, f"{len(lines)} rejection lines for {topic} after a flood of {FLOOD} " \
                                            f"read in {flood_s:.0f} s (at most {most})"


@NO_RCLPY
@pytest.mark.parametrize("cyclone_nodes,num_envs", [(("environment", "critic"), 1),
                                                    (("meta_controller", "sub_controller", "learner"), 1),
                                                    (("environment", "critic"), 4)],
                         ids=["env-critic-on-cyclone", "controllers-learner-on-cyclone", "env-critic-on-cyclone-4-envs"])
def test_mixed_graph_trains_aligned(domain, tmp_path, cyclone_nodes, num_envs):
    """Half the graph on the Cyclone backend, the other half on rclpy: training runs end to end
    and every transition the learner assembled is the environment's step (also for a batch)."""
    nodes = ("environment", "critic", "meta_controller", "sub_controller", "learner")
    middleware = {n: "cyclone" if n in cyclone_nodes else "rclpy" for n in nodes}
    summary = train_to_the_end_aligned(tmp_path, middleware=middleware, num_envs=num_envs)
    assert summary["episodes"] == 5 and summary["updates"] > 0
    for node, backend in middleware.items():  # each process really ran on its backend
        log = (tmp_path / "logs" / f"{'learner' if node == 'learner' else 'graph_' + node}.log").read_text()
        assert f"middleware {backend}" in log, (node, backend)
