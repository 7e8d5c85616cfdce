"""``hdrqn bag play``: a real player process on real rclpy (loopback only), received here by
an rclpy node, byte for byte."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.nodes.player import on_wire  # noqa: E402
from hdrqn_ros.nodes.qos import keep_last  # noqa: E402
from hdrqn_ros.nodes.ros_messages import MissingRosPackage, from_cdr  # noqa: E402
from hdrqn_ros.recording.bag import BagWriter, read_messages  # noqa: E402
from hdrqn_ros.recording.bag_format import TYPESTORE  # noqa: E402

from conftest import ros_probe  # noqa: E402

TS = TYPESTORE
T = TS.types
T0 = 1_700_000_000_000_000_000
IMAGE, FLOATS, STRING, CLOCK = ("sensor_msgs/msg/Image", "std_msgs/msg/Float64MultiArray", "std_msgs/msg/String",
                                "rosgraph_msgs/msg/Clock")
TOPICS = {"/camera/image": (IMAGE, "best_effort", False), "/scores": (FLOATS, "reliable", False),
          "/chatter": (STRING, "reliable", True)}  # topic: (type, reliability, transient_local)




def _cdr(msg) -> bytes:
    return bytes(TS.serialize_cdr(msg, msg.__msgtype__))


def _stamp(t: int):
    return T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """``main``: 10 images, 10 score arrays, 5 strings over 0.95 s of bag time;
    ``clocked``: 5 recorded ``/clock`` messages over the same span."""
    root = tmp_path_factory.mktemp("bags")
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    with BagWriter(root / "main") as w:
        for topic, (type_name, rel, latched) in TOPICS.items():
            w.add_topic(topic, type_name, qos=rel, transient_local=latched, depth=5)
        for i in range(10):
            t = T0 + i * 100_000_000
            pixels = np.random.default_rng(i).integers(0, 256, 24 * 32 * 3, dtype=np.uint8)
            w.write("/camera/image", t, _cdr(T[IMAGE](
                header=T["std_msgs/msg/Header"](stamp=_stamp(t), frame_id="cam"), height=24, width=32,
                encoding="rgb8", is_bigendian=0, step=96, data=pixels)))
            w.write("/scores", t + 30_000_000, _cdr(T[FLOATS](layout=layout, data=np.arange(3.0) + i / 7)))
            if i % 2:
                w.write("/chatter", t + 50_000_000, _cdr(T[STRING](data=f"hello {i} ünïcode")))
    with BagWriter(root / "clocked") as w:
        w.add_topic("/clock", CLOCK)
        for i in range(5):
            t = T0 + 10_000_000 + i * 200_000_000
            w.write("/clock", t, _cdr(T[CLOCK](clock=_stamp(t))))
    return root


def recorded(bag: Path) -> dict[str, list[bytes]]:
    """The bag's messages per topic, as they go on the wire (zero-padded to 4 bytes)."""
    out: dict[str, list[bytes]] = {}
    for topic, _type, _t, data in read_messages(bag):
        out.setdefault(topic, []).append(on_wire(data))
    return out


def start_play(tmp_path: Path, *args: str) -> tuple[subprocess.Popen, Path]:
    """The player, waiting for the Receiver's subscription on each topic (a loaded machine may
    take longer than ``--delay`` to match them), then the delay for the Receiver's side."""
    log = tmp_path / f"play{len(list(tmp_path.glob('play*.log')))}.log"
    proc = subprocess.Popen([sys.executable, "-m", "hdrqn_ros.cli", "bag", "play", "--wait-for-subscribers", "1", *args],
                            stdout=subprocess.DEVNULL, stderr=log.open("w"))
    return proc, log


class Receiver:
    """Subscribes to the bag topics and /clock; keeps the CDR bytes as received."""

    def __init__(self):
        self.mw = ros_probe()
        self.node = self.mw.create_node("bag_probe")
        self.got: dict[str, list[bytes]] = {}
        subs = {t: (ty, keep_last(200, reliable=rel == "reliable")) for t, (ty, rel, _l) in TOPICS.items()}
        subs["/clock"] = (CLOCK, keep_last(200))
        for topic, (type_name, qos) in subs.items():
            self.node.create_subscription(type_name, topic, lambda m, t=topic: self.got.setdefault(t, []).append(m),
                                          qos, raw=True)

    def spin_until(self, cond, timeout: float, what: str, proc: subprocess.Popen | None = None, log=None):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.mw.spin(timeout_s=0.05)
            if cond():
                return
        raise AssertionError(f"timed out after {timeout} s waiting for {what}; received "
                             f"{ {t: len(v) for t, v in self.got.items()} }; player exit {proc and proc.poll()}"
                             + (f"; player log:\n{log.read_text()}" if log else ""))

    def close(self):
        self.mw.shutdown()


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def clock_ns(cdr: bytes) -> int:
    msg = TS.deserialize_cdr(cdr, CLOCK)
    return msg.clock.sec * 10**9 + msg.clock.nanosec


def test_cdr_round_trip_equals_rosbags(domain, bags):
    """``to_cdr`` / ``from_cdr`` (:mod:`hdrqn_ros.nodes.ros_messages`) against rosbags' CDR:
    rclpy decodes what a bag holds, and what it encodes, rosbags re-encodes byte for byte as
    the bag holds it (Fast CDR leaves alignment padding unset, so rclpy's own bytes may
    differ there)."""
    mw = ros_probe()
    try:
        node = mw.create_node("cdr_probe")
        for topic, type_name, _t, data in read_messages(bags / "main"):
            msg = from_cdr(type_name, data)
            assert type(msg) is node.msg(type_name)
            ours = node.to_cdr(msg)
            assert len(ours) == len(data) and _cdr(TS.deserialize_cdr(ours, type_name)) == data, topic
        assert node.to_cdr(node.msg(STRING)(data="x")) == _cdr(T[STRING](data="x"))
        with pytest.raises(MissingRosPackage, match="foo_msgs/msg/Bar"):
            from_cdr("foo_msgs/msg/Bar", b"\x00\x01\x00\x00")
        with pytest.raises(ValueError, match="std_msgs/msg/Nope"):
            from_cdr("std_msgs/msg/Nope", b"\x00\x01\x00\x00")
    finally:
        mw.shutdown()


def test_play_delivers_every_message_bit_exact_with_clock(domain, bags, tmp_path):
    want = recorded(bags / "main")
    rx = Receiver()
    proc = None
    try:
        proc, log = start_play(tmp_path, str(bags / "main"), "--delay", "2")
        rx.spin_until(lambda: proc.poll() is not None and all(len(rx.got.get(t, [])) >= len(v)
                                                            for t, v in want.items()),
                      60, "every message and the player's exit", proc, log)
        rx.mw.spin(timeout_s=0.3)  # nothing extra may follow
        assert proc.returncode == 0, log.read_text()
    finally:
        rx.close()
        if proc is not None:
            stop(proc)
    for topic, messages in want.items():
        assert rx.got[topic] == messages, f"{topic}: received bytes differ from the bag's"
    clock = [clock_ns(c) for c in rx.got.get("/clock", [])]
    assert clock, "no /clock"
    assert clock == sorted(clock), "/clock went backwards"
    assert T0 <= clock[0] and clock[-1] <= T0 + 950_000_000, "/clock outside the bag's time span"
    text = log.read_text()
    assert "played 25 messages on 3 topics" in text and "Traceback" not in text


def test_loop_and_topic_filter(domain, bags, tmp_path):
    want = recorded(bags / "main")["/chatter"]
    rx = Receiver()
    proc = None
    try:
        proc, log = start_play(tmp_path, str(bags / "main"), "--loop", "--rate", "4", "--no-clock", "--delay", "2",
                               "--topics", "chatter")
        rx.spin_until(lambda: len(rx.got.get("/chatter", [])) > 2 * len(want), 60, "more than two passes", proc, log)
        proc.send_signal(signal.SIGINT)  # Ctrl-C: a normal stop
        assert proc.wait(timeout=30) == 0, log.read_text()
    finally:
        rx.close()
        if proc is not None:
            stop(proc)
    got = rx.got["/chatter"]
    assert got == [want[i % len(want)] for i in range(len(got))]
    assert not {"/camera/image", "/scores", "/clock"} & set(rx.got), "only /chatter was asked for"
    text = log.read_text()
    assert "playing pass 2" in text and "Traceback" not in text


def test_two_bags_with_a_recorded_clock(domain, bags, tmp_path):
    """Two bags merge by time; the recorded /clock is played instead of a generated one."""
    want_clock = recorded(bags / "clocked")["/clock"]
    want_scores = recorded(bags / "main")["/scores"]
    rx = Receiver()
    proc = None
    try:
        proc, log = start_play(tmp_path, str(bags / "main"), str(bags / "clocked"), "--rate", "2", "--delay", "2",
                               "--topics", "/scores")
        rx.spin_until(lambda: proc.poll() is not None and len(rx.got.get("/scores", [])) >= len(want_scores)
                      and len(rx.got.get("/clock", [])) >= len(want_clock), 60, "/scores, /clock and the exit",
                      proc, log)
        rx.mw.spin(timeout_s=0.3)
        assert proc.returncode == 0, log.read_text()
    finally:
        rx.close()
        if proc is not None:
            stop(proc)
    assert rx.got["/scores"] == want_scores
    assert rx.got["/clock"] == want_clock, "the recorded clock, and only it"
    assert not {"/camera/image", "/chatter"} & set(rx.got)


def test_bad_input_exits_2_naming_the_problem(domain, bags, tmp_path, capsys):
    from hdrqn_ros.cli import main
    from hdrqn_ros.nodes.player import main as player_main

    not_a_bag = tmp_path / "notabag"
    not_a_bag.mkdir()
    (not_a_bag / "notes.txt").write_text("hello")
    missing = tmp_path / "missing_bag"
    cli = [sys.executable, "-m", "hdrqn_ros.cli", "bag", "play"]
    procs = {path: subprocess.Popen([*cli, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for path in (not_a_bag, missing)}  # as a user runs it, side by side

    unknown = tmp_path / "unknown"
    with BagWriter(unknown) as w:
        w.add_topic("/q", FLOATS)
    meta = unknown / "metadata.yaml"
    meta.write_text(meta.read_text().replace(f"type: {FLOATS}", "type: foo_msgs/msg/Bar"))
    in_process = {  # the rest in this process: hdrqn bag play ..., then the node's own entry point
        (str(unknown),): "foo_msgs/msg/Bar", (str(bags / "main"), "--rate", "0"): "--rate",
        (str(bags / "main"), "--delay", "-1"): "--delay",
        (str(bags / "main"), "--wait-for-subscribers", "-1"): "--wait-for-subscribers", (str(bags / "main"), "--domain-id", "999"): "--domain-id",
        (str(bags / "main"), "--topics", "/nope"): "/nope"}
    for args, needle in in_process.items():
        assert main(["bag", "play", *args]) == 2, args
        assert needle in capsys.readouterr().err, args
    assert player_main(["player", "--ros-args", "-p", f"bag:=[{missing}]"]) == 2
    assert str(missing) in capsys.readouterr().err
    assert player_main(["player", "--ros-args", "-p", f"bag:=[{bags / 'main'}]", "-p", "rate:=-1.0"]) == 2
    assert "rate must be" in capsys.readouterr().err

    for path, proc in procs.items():
        _out, err = proc.communicate(timeout=60)
        assert proc.returncode == 2, err
        assert str(path) in err and "Traceback" not in err, err


def test_parameters_given_in_python_win_over_ros_args(domain, bags):
    """``hdrqn bag play`` hands the in-process player its settings as values: they are
    type-checked like ``--ros-args -p`` ones (an int for a double is a double), win over
    them, and leave the others to ``--ros-args``; an unknown name or a wrong type is refused."""
    import rclpy
    from rclpy.context import Context

    from hdrqn_ros.dds import apply_rmw_network_defaults
    from hdrqn_ros.nodes.parameters import NodeConfigError
    from hdrqn_ros.nodes.player import PlayerNode, parameter_overrides

    apply_rmw_network_defaults(None)  # loopback only, as a node process
    context = Context()
    rclpy.init(args=["player", "--ros-args", "-p", "rate:=3.0", "-p", "loop:=true", "-p", "delay:=0.5"],
               context=context)
    players = []

    def player(**values) -> PlayerNode:
        players.append(p := PlayerNode(context=context, parameter_overrides=parameter_overrides(values)))
        return p

    try:
        main = str(bags / "main")
        p = player(bag=[main], rate=2, topics=["/chatter"], clock=False, delay=60.0)
        assert (p.bags, p.rate, p.loop, p.delay) == ([main], 2.0, True, 60.0) and type(p.rate) is float
        assert list(p.topics) == ["/chatter"] and not p.generate_clock
        p = player(bag=[main], topics=[], delay=60.0)
        assert p.rate == 3.0 and set(p.topics) == set(TOPICS) and p.generate_clock  # []: every topic
        with pytest.raises(NodeConfigError, match="rate"):
            parameter_overrides({"bag": [main], "rate": "fast"})
        with pytest.raises(NodeConfigError, match="speed"):
            parameter_overrides({"bag": [main], "speed": 2.0})
    finally:
        for p in players:
            p.close()
            p.destroy_node()
        rclpy.try_shutdown(context=context)


def test_topics_are_chosen_as_recorded_or_by_their_name_in_every_group():
    """``--topics`` takes a recorded name, or a group's topic name without its namespace; a
    name that selects nothing is one error naming it and the closest recorded topics."""
    from hdrqn_ros.recording.bag import BagError, select_topics

    recorded = {"/group0/observation", "/group1/observation", "/group0/env_step", "/learner/status", "/clock"}
    assert select_topics(["/group0/observation"], recorded, "b") == {"/group0/observation"}
    assert select_topics(["observation", "/clock"], recorded, "b") == {"/group0/observation", "/group1/observation",
                                                                       "/clock"}
    assert select_topics(["status"], recorded, "b") == {"/learner/status"}
    with pytest.raises(BagError) as error:
        select_topics(["/observatio"], recorded, "bags/run1")
    assert str(error.value) == ("topic /observatio is not in bags/run1 (5 topics recorded; closest: "
                                "/group0/observation, /group1/observation; hdrqn bag info lists them)")
