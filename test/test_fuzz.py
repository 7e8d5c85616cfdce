"""Fuzzing the untrusted inputs (issue 7): wire messages, configs and ROS parameters, bags, the CLI.

Hypothesis feeds every parser random and mutated input. The only failure allowed is the
documented error type, with a message naming the problem: for CDR bytes rclpy's
deserializer raises (a node drops the sample, the player names the bag), ``ProtocolError``
for message contents, ``ConfigError`` for configs, for ROS arguments and parameters files
rcl's ``RuntimeError`` (a node exits 2) or ``NodeConfigError`` naming the parameter,
``BagError`` for bags, and for the CLI an exit code 0/1/2 with no traceback. Sizes are
capped so that no example can hang or exhaust memory. The message and ROS-argument tests
need rclpy; the others run without ROS.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import logging
import math
import os
import shutil
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import hdrqn_ros
from hdrqn_ros import cli
from hdrqn_ros.config import ConfigError, TrainConfig, build_config, parse_set
from hdrqn_ros.envs.registration import GRID_IDS, make_batch
from hdrqn_ros.protocol import follower, wire
from hdrqn_ros.protocol.assembly import TransitionAssembler
from hdrqn_ros.recording.bag import TYPESTORE, BagError, bag_summary, bag_topics, read_messages, repair_bag
from hdrqn_ros.recording.transitions import (GROUP_TOPICS, BagReadStats, BagRecorder, RosbagsMessages, bag_config, episode_summary,
                                             read_episodes, recorded_topics)

from conftest import NEEDS_RCLPY

QUICK = dict(deadline=None, database=None,
             suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                    HealthCheck.data_too_large])
OBS = 44
NUM_ACTIONS, NUM_SUBGOALS = 4, 2  # the two-goal gridworld
CFG = build_config([], algo="hdrqn-v2", env="hdrqn/GridWorld-2Goals-v0", episodes=5, num_envs=1)
LOG = logging.getLogger("hdrqn.test_fuzz")
OCCUPANCY_GRID, TWIST = "nav_msgs/msg/OccupancyGrid", "geometry_msgs/msg/Twist"
"""``nav.OCCUPANCY_GRID`` and ``nav.TWIST``, named here: :mod:`hdrqn_ros.nodes.nav` imports ROS."""


def ros(module: str):
    """``hdrqn_ros.nodes.<module>``, imported when a test that needs rclpy runs."""
    return importlib.import_module(f"hdrqn_ros.nodes.{module}")


class RclpyMessages:
    """rclpy's message factory (:data:`hdrqn_ros.nodes.ros_messages.ROS_MESSAGES`), imported on
    first use."""

    @staticmethod
    def msg(type_name: str) -> type:
        return ros("ros_messages").interface_class(type_name)

    @staticmethod
    def pack(values):
        return ros("ros_messages").pack(values)


RC = RclpyMessages()


def received(msg):
    """``msg`` as a node's subscription receives it: serialized by the RMW and deserialized."""
    from rclpy.serialization import deserialize_message, serialize_message

    return deserialize_message(serialize_message(msg), type(msg))


# -- 1. CDR bytes, as rclpy's deserializer takes them ------------------------------------------------
SUBSCRIBED = [wire.IMAGE, wire.FLOATS, wire.INTS, wire.BYTES, OCCUPANCY_GRID]
"""Every type a node subscribes to (observations and subgoal images; env_step, critic, credit,
sub_state; action, subgoal; weights; the Nav2 costmap)."""
PLAYED = [wire.STRING, wire.POSE_STAMPED, wire.CLOCK_TYPE, TWIST, "rcl_interfaces/msg/Log"]
"""Further types the bag player decodes (``ros_messages.from_cdr``) from recordings."""
HEADERS = [b"\x00\x01\x00\x00", b"\x00\x00\x00\x00", b"\x00\x07\x00\x00", b"\x00\x09\x00\x00"]
"""CDR little- and big-endian, XCDR2 little-endian, XCDR2 delimited."""
WORDS = [(2**32 - 1).to_bytes(4, "little"), (2**31 - 1).to_bytes(4, "little"), (2**31).to_bytes(4, "big"),
         (2**20).to_bytes(4, "little"), (3).to_bytes(4, "little"), b"\x00\x00\x00\x00"]
"""Lengths that lie: huge, negative when signed, a few, none."""
SAMPLE_NAMES = ("observation", "env_step", "action", "sub_state", "weights", "costmap", "pose", "string")


class Undecodable(Exception):
    """rclpy's deserializer refused the bytes."""


def decoded(type_name: str, data: bytes):
    """``data`` through rclpy's deserializer, as a node's subscription and the player take
    received bytes (``ros_messages.from_cdr``); its refusal, rclpy's ``RMWError`` (a
    ``RuntimeError``, which they catch), as :class:`Undecodable`. Anything else (a crash,
    another exception) fails the test."""
    try:
        return ros("ros_messages").from_cdr(type_name, data)
    except RuntimeError as exc:
        assert "deserialize" in str(exc), exc
        raise Undecodable(str(exc)) from None


@functools.cache
def samples() -> dict[str, tuple[str, bytes]]:
    """One realistic sample of each subscribed type, as CDR."""
    grid = RC.msg(OCCUPANCY_GRID)()
    grid.info.width, grid.info.height, grid.info.resolution = 6, 5, 0.05
    grid.data = RC.pack(np.arange(30, dtype=np.int8))
    pixels = np.arange(OBS * OBS * 3, dtype=np.uint32).astype(np.uint8).reshape(OBS, OBS, 3)
    step = [20_000_000, 10_000_000, 1, 0, 1, 2, 0.5, -0.1, 0, 0, -1, 0, 0, 0, 0, 1]
    msgs = {"observation": (wire.IMAGE, wire.make_image(RC, 20_000_000, pixels, "map")),
            "env_step": (wire.FLOATS, wire.make_record(RC, wire.FLOATS, wire.STEP_FIELDS, step)),
            "action": (wire.INTS, wire.make_record(RC, wire.INTS, wire.ACTION_FIELDS, [10_000_000, 3])),
            "sub_state": (wire.FLOATS, wire.make_state(RC, 10_000_000, np.linspace(-1, 1, 256))),
            "weights": (wire.BYTES, wire.make_weights(RC, bytes(range(64)), 1234)),
            "costmap": (OCCUPANCY_GRID, grid),
            "pose": (wire.POSE_STAMPED, wire.make_pose(RC, 20_000_000, "map", 1.0, 2.0)),
            "string": (wire.STRING, RC.msg(wire.STRING)(data="status ok"))}
    assert set(msgs) == set(SAMPLE_NAMES)
    return {name: (type_name, ros("ros_messages").to_cdr(msg)) for name, (type_name, msg) in msgs.items()}


def read_as_node(name: str, msg):
    """What the node that subscribes to sample ``name``'s topic reads from ``msg``."""
    nav = ros("nav")
    readers = {"observation": lambda: wire.read_image(msg, OBS, OBS),
               "env_step": lambda: wire.read_record(msg, wire.STEP_FIELDS),
               "action": lambda: wire.check_index(wire.read_record(msg, wire.ACTION_FIELDS, np.int64)["action"],
                                               NUM_ACTIONS, "action"),
               "sub_state": lambda: wire.read_state(msg, 256),
               "weights": lambda: (wire.read_weights_version(msg), wire.as_bytes(msg.data)),
               "costmap": lambda: nav.costmap_to_observation(msg, view_cells=5),
               "pose": lambda: wire.key_of(msg.header.stamp),
               "string": lambda: msg.data}
    return readers[name]()


lying_bytes = st.lists(st.one_of(st.binary(max_size=24), st.sampled_from(WORDS)), max_size=24).map(b"".join)


@NEEDS_RCLPY
@settings(max_examples=300, **QUICK)
@given(type_name=st.sampled_from(SUBSCRIBED + PLAYED), header=st.sampled_from(HEADERS) | st.binary(max_size=4),
       body=lying_bytes)
@example(type_name=wire.FLOATS, header=HEADERS[0], body=b"")  # an empty payload is not a default message
@example(type_name=wire.BYTES, header=HEADERS[0], body=WORDS[0] * 6)  # lengths far beyond the bytes
def test_arbitrary_bytes_decode_or_are_refused(type_name, header, body):
    try:
        msg = decoded(type_name, header + body)
    except Undecodable:
        return
    assert type(msg) is RC.msg(type_name) and len(header + body) >= 8


def _mutate(data: bytes, edits) -> bytes:
    out = bytearray(data)
    for kind, where, value in edits:
        if not out:
            break
        pos = where % len(out)
        if kind == "flip":
            out[pos] ^= value % 255 + 1
        elif kind == "word":
            pos -= pos % 4  # lengths sit on 4-byte boundaries
            out[pos:pos + 4] = WORDS[value % len(WORDS)]
        else:
            del out[pos:]
    return bytes(out)


edits = st.lists(st.tuples(st.sampled_from(["flip", "word", "cut"]), st.integers(0, 2**16), st.integers(0, 255)),
                 min_size=1, max_size=3)


@NEEDS_RCLPY
@settings(max_examples=300, **QUICK)
@given(name=st.sampled_from(SAMPLE_NAMES), edits=edits)
def test_mutated_samples_are_read_or_rejected_like_a_node_does(name, edits):
    """A corrupted sample: the deserializer refuses it or the node's reader raises
    ProtocolError (NavConfigError for a costmap); a shortened one never decodes."""
    type_name, data = samples()[name]
    try:
        msg = decoded(type_name, _mutate(data, edits))
    except Undecodable:
        return
    assert any(kind != "cut" for kind, *_ in edits), "a truncated sample decoded"
    try:
        read_as_node(name, msg)
    except (wire.ProtocolError, ros("nav").NavConfigError) as exc:
        assert str(exc)


@NEEDS_RCLPY
@settings(max_examples=100, **QUICK)
@given(name=st.sampled_from(SAMPLE_NAMES), cut=st.integers(1, 64))
def test_truncated_samples_never_decode(name, cut):
    type_name, data = samples()[name]
    with pytest.raises(Undecodable):
        decoded(type_name, data[:-cut])
    assert read_as_node(name, decoded(type_name, data)) is not None  # the whole one does


# -- 2. message contents, as the nodes read them -----------------------------------------------------
any_float = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-2**63, 2**63 - 1).map(float)
key_like = st.integers(-5, 2**54).map(float) | any_float


def _record_values(fields: tuple[str, ...]):
    """Field values for a record of ``fields``: mostly plausible, sometimes absurd, sometimes too few/many."""
    plausible = st.lists(st.floats(-10, 10) | st.integers(-2, 5).map(float), min_size=len(fields) - 1,
                         max_size=len(fields) - 1).flatmap(lambda rest: key_like.map(lambda k: [k, *rest]))
    return st.one_of(plausible, plausible.flatmap(lambda v: st.lists(any_float, max_size=3).map(lambda x: v + x)),
                     st.lists(any_float, max_size=len(fields) + 2))


RECORDS = [(wire.STEP_FIELDS, np.float64), (wire.CRITIC_FIELDS, np.float64), (wire.CREDIT_FIELDS, np.float64),
           (wire.ACTION_FIELDS, np.int64), (wire.SUBGOAL_FIELDS, np.int64)]


@NEEDS_RCLPY
@settings(max_examples=300, **QUICK)
@given(data=st.data(), which=st.integers(0, len(RECORDS) - 1))
def test_records_with_random_values_are_read_or_rejected(data, which):
    fields, dtype = RECORDS[which]
    values = data.draw(_record_values(fields))
    type_name = wire.FLOATS if dtype == np.float64 else wire.INTS
    if dtype == np.int64:
        values = [int(v) if math.isfinite(v) and abs(v) < 2**63 else -1 for v in values]
    msg = received(RC.msg(type_name)(data=RC.pack(np.asarray(values, dtype))))
    try:
        rec = wire.read_record(msg, fields, dtype)
    except wire.ProtocolError as exc:
        assert str(exc)
        return
    assert list(rec) == list(fields) and [rec[f] for f in fields] == list(np.asarray(values, dtype))
    assert all(math.isfinite(v) for v in rec.values()) and 0 < rec.get("key", 1) < wire.MAX_KEY
    for name, n in (("action", NUM_ACTIONS), ("subgoal", NUM_SUBGOALS)):
        if name in rec:
            try:
                assert 0 <= wire.check_index(rec[name], n, name) < n
            except wire.ProtocolError as exc:
                assert name in str(exc)


@NEEDS_RCLPY
@settings(max_examples=200, **QUICK)
@given(height=st.sampled_from([OBS, 2 * OBS, 0, 1, 2**32 - 1]) | st.integers(0, 2**32 - 1),
       width=st.sampled_from([OBS, 0, 2**31]) | st.integers(0, 2**32 - 1),
       step=st.sampled_from([OBS * 3, 0, 2**32 - 1]) | st.integers(0, 2**32 - 1),
       encoding=st.sampled_from(["rgb8", "bgr8", "mono8", ""]) | st.text(max_size=8),
       size=st.sampled_from([OBS * OBS * 3, 2 * OBS * OBS * 3, 0]) | st.integers(0, 3 * OBS * OBS * 3),
       sec=st.integers(-2**31, 2**31 - 1), nanosec=st.integers(0, 2**32 - 1), rows=st.sampled_from([1, 2]))
def test_images_with_random_fields_are_read_or_rejected(height, width, step, encoding, size, sec, nanosec, rows):
    Image, Header, Time = (RC.msg(t) for t in (wire.IMAGE, "std_msgs/msg/Header", "builtin_interfaces/msg/Time"))
    img = Image(header=Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id="map"), height=height, width=width,
                encoding=encoding, is_bigendian=0, step=step,
                data=RC.pack(np.arange(size, dtype=np.uint32).astype(np.uint8)))
    msg = received(img)
    try:
        key, pixels = wire.read_image(msg, OBS * rows, OBS)
    except wire.ProtocolError as exc:
        assert "image" in str(exc)
        return
    assert pixels.shape == (OBS * rows, OBS, 3) and 0 < key < wire.MAX_KEY
    assert (pixels.reshape(-1) == np.arange(size, dtype=np.uint32).astype(np.uint8)).all()


@NEEDS_RCLPY
@settings(max_examples=100, **QUICK)
@given(key=key_like, state=st.lists(any_float, min_size=250, max_size=260))
def test_sub_states_with_random_values_are_read_or_rejected(key, state):
    msg = received(RC.msg(wire.FLOATS)(data=RC.pack(np.asarray([key, *state]))))
    try:
        got_key, got = wire.read_state(msg, 256)
    except wire.ProtocolError as exc:
        assert str(exc)
        return
    assert got_key == key and got.shape == (256,) and got.dtype == np.float32 and np.isfinite(got).all()


@NEEDS_RCLPY
@settings(max_examples=200, **QUICK)
@given(labels=st.lists(st.text(max_size=12).map(lambda s: "safetensors update=" + s) | st.text(max_size=30),
                       max_size=2),
       version=st.integers(0, 10**30))
@example(labels=["safetensors update=\u00b2"], version=0)  # a superscript two: str.isdigit, but not int()
@example(labels=["safetensors update=" + "9" * 5000], version=0)  # over int()'s digit limit
def test_weights_version_labels_never_raise(labels, version):
    Dim, Layout = RC.msg("std_msgs/msg/MultiArrayDimension"), RC.msg("std_msgs/msg/MultiArrayLayout")
    layout = Layout(dim=[Dim(label=label, size=0, stride=0) for label in labels], data_offset=0)
    msg = received(RC.msg(wire.BYTES)(layout=layout, data=RC.pack(np.zeros(3, np.uint8))))
    assert wire.read_weights_version(msg) >= 0
    if version < 10**18:
        assert wire.read_weights_version(received(wire.make_weights(RC, b"xyz", version))) == version


@NEEDS_RCLPY
@settings(max_examples=150, **QUICK)
@given(width=st.integers(0, 12) | st.integers(0, 2**32 - 1), height=st.integers(0, 12),
       resolution=st.floats(width=32), x=st.floats(), y=st.floats(), size=st.integers(0, 150))
def test_costmaps_with_random_fields_are_read_or_rejected(width, height, resolution, x, y, size):
    nav = ros("nav")
    grid = RC.msg(OCCUPANCY_GRID)()
    grid.info.width, grid.info.height, grid.info.resolution = width, height, resolution
    grid.info.origin.position.x, grid.info.origin.position.y = x, y
    grid.data = RC.pack((np.arange(size) % 256 - 128).astype(np.int8))
    msg = received(grid)
    try:
        obs = nav.costmap_to_observation(msg, view_cells=5)
    except nav.NavConfigError as exc:
        assert "costmap" in str(exc)
        return
    assert obs.shape == (OBS, OBS, 3) and obs.dtype == np.uint8


# -- 3. the learner's assembly of transitions (the node's subscriptions, and bags) -------------------
STEP_NS = 10_000_000


def _image(m, key: int, rows: int, fill: int):
    return wire.make_image(m, key, np.full((OBS * rows, OBS, 3), fill, np.uint8), "map")


def group_stream(episodes: list[list[dict]], m=RosbagsMessages()) -> list[tuple[str, object]]:
    """(topic, message) of one hDRQNv2 group in the order the trainer records them
    (:class:`~hdrqn_ros.recording.transitions.TransitionRecorder`). Each episode is a list of
    steps, each a dict of the values to publish (plausible or not) - see :func:`steps`."""
    out, key, env_steps = [], 0, 0
    for e, ep in enumerate(episodes):
        key += STEP_NS
        first = dict.fromkeys(wire.STEP_FIELDS, 0)
        first.update(key=key, env_steps=env_steps, episode=e, at_subgoal=-1, decision_point=1)
        out += [(wire.ENV_STEP, wire.make_record(m, wire.FLOATS, wire.STEP_FIELDS, [first[f] for f in wire.STEP_FIELDS])),
                (wire.OBSERVATION, _image(m, key, 1, e)),
                (wire.CRITIC, wire.make_record(m, wire.FLOATS, wire.CRITIC_FIELDS, [key, 0, 0, 1, -1]))]
        new_option = True
        for t, s in enumerate(ep, 1):
            prev = key
            out.append((wire.ACTION, wire.make_record(m, wire.INTS, wire.ACTION_FIELDS, [prev, s["action"]])))
            if new_option:
                out += [(wire.SUBGOAL, wire.make_record(m, wire.INTS, wire.SUBGOAL_FIELDS, [prev, s["subgoal"], 1])),
                        (wire.SUBGOAL_IMAGES, _image(m, prev, s["image_rows"], t))]
            if s["option_done"]:
                out.append((wire.SUB_STATE, wire.make_state(m, prev, np.full(256, s["state"]))))
            key += STEP_NS + s["key_gap"]
            env_steps += 1
            step = {"key": key, "prev_key": prev, "env_steps": env_steps, "episode": e, "t": t,
                    **{f: s[f] for f in wire.STEP_FIELDS if f in s}}
            out += [(wire.ENV_STEP, wire.make_record(m, wire.FLOATS, wire.STEP_FIELDS, [step.get(f, 0) for f in wire.STEP_FIELDS])),
                    (wire.CRITIC, wire.make_record(m, wire.FLOATS, wire.CRITIC_FIELDS,
                                             [key, s["intrinsic"], s["reached"], s["option_done"], s["subgoal"]])),
                    (wire.OBSERVATION, _image(m, key, 1, t)),
                    (wire.POSE, wire.make_pose(m, key, "map", 1.0, 2.0))]
            new_option = bool(s["option_done"])
    return out


def _valid_step(last: bool, reached: bool) -> dict:
    return {"action": 1, "subgoal": 0, "image_rows": NUM_SUBGOALS, "option_done": int(reached or last), "state": 0.5,
            "key_gap": 0, "extrinsic": 0.1, "classical": -0.01, "terminated": int(last), "truncated": 0,
            "at_subgoal": 0 if reached else -1, "collected": int(reached), "hit_obstacle": 0, "life_lost": 0,
            "success": 0, "decision_point": int(reached and not last), "intrinsic": float(reached),
            "reached": int(reached)}


VALID_EPISODES = [[_valid_step(t == 3, t == 2) for t in range(1, 4)], [_valid_step(t == 2, False) for t in range(1, 3)]]
"""Two episodes (3 and 2 steps), the first with two options."""

odd_int = st.sampled_from([-1, NUM_ACTIONS, 255, 256, -2**63, 2**63 - 1]) | st.integers(-2**63, 2**63 - 1)
odd_float = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([1e300, -1e39, 3.5e38, 0.5, 2.0])


@st.composite
def steps(draw, last: bool, reached: bool) -> dict:
    """A valid step's values, with a few of them replaced by odd ones."""
    step = _valid_step(last, reached)
    odd = {"action": odd_int, "subgoal": odd_int, "image_rows": st.sampled_from([1, 3]),
           "option_done": st.sampled_from([0, 1]) | odd_float, "state": odd_float,
           "key_gap": st.sampled_from([-STEP_NS, 1, -1, 2**53]), "intrinsic": odd_float, "reached": odd_float,
           **{f: odd_float for f in ("extrinsic", "classical", "terminated", "truncated", "at_subgoal", "collected",
                                     "hit_obstacle", "life_lost", "success", "decision_point")}}
    for name in draw(st.lists(st.sampled_from(sorted(odd)), max_size=2, unique=True)):
        step[name] = draw(odd[name])
    return step


fuzzed_episodes = st.lists(st.integers(1, 3), min_size=1, max_size=3).flatmap(
    lambda lengths: st.tuples(*[st.tuples(*[steps(t == n, t == 1 and n > 1) for t in range(1, n + 1)])
                                for n in lengths])).map(lambda eps: [list(ep) for ep in eps])


def check_episode(sub, meta) -> None:
    """What training needs of a replay episode: in-range actions/subgoals, finite values."""
    actions = sub.fields["action"]
    assert ((0 <= actions) & (actions < NUM_ACTIONS)).all(), actions
    assert ((0 <= meta.fields["action"]) & (meta.fields["action"] < NUM_SUBGOALS)).all(), meta.fields["action"]
    for ep in (sub, meta):
        assert all(np.isfinite(v).all() for v in ep.fields.values() if v.dtype.kind == "f")
        assert np.isfinite(ep.frames).all()
    assert sub.frames.shape[1:] == (OBS, OBS, 3) and sub.segment_data["subgoal_image"].shape[1:] == (OBS, OBS, 3)


def assemble(episodes) -> tuple[TransitionAssembler, list]:
    """Feed ``group_stream(episodes)`` to a learner-side assembler; returns it and the finished episodes."""
    finished = []
    asm = TransitionAssembler("/", CFG, NUM_SUBGOALS, finished.append, logger=LOG)
    handlers = asm.inputs()
    for topic, msg in group_stream(episodes):
        if topic in handlers:
            handlers[topic][1](msg)
    return asm, finished


def test_valid_stream_assembles_into_its_episodes():
    asm, finished = assemble(VALID_EPISODES)
    assert [len(sub.fields["action"]) for _, sub, _, _ in finished] == [3, 2]
    assert [len(meta.fields["action"]) for _, _, meta, _ in finished] == [2, 1]
    for _, sub, meta, _ in finished:
        check_episode(sub, meta)
    assert asm.rejected == 0


def test_the_learner_holds_a_first_step_only_with_the_controllers_answers():
    """Credit waits for this (``GroupAssembler.publish_credit``): a subscription matched
    late would miss the first step's action or subgoal, and every later step would wait."""
    asm = TransitionAssembler("/", CFG, NUM_SUBGOALS, [].append, logger=LOG)
    handlers, first, held = asm.inputs(), None, []
    for topic, msg in group_stream(VALID_EPISODES)[:6]:  # env_step, observation, critic, action, subgoal, images
        handlers[topic][1](msg)
        first = first or wire.read_steps(msg)
        held.append(asm.holds_answers(first))
    assert held == [False, False, False, False, False, True]


def test_the_learner_holds_a_first_step_only_with_the_critics_answer():
    """The critic answers every step, the first too: a learner whose ``/critic``
    subscription matched late holds no first step, so it grants no credit ahead until the
    environment re-publishes the step and the critic its answer (a stress run saw the
    learner lose the first episodes of a batched group this way)."""
    asm = TransitionAssembler("/", CFG, NUM_SUBGOALS, [].append, logger=LOG)
    handlers, first = asm.inputs(), None
    for topic, msg in group_stream(VALID_EPISODES)[:6]:
        if topic != wire.CRITIC:
            handlers[topic][1](msg)
            first = first or wire.read_steps(msg)
        else:
            critic = msg
    assert not asm.holds_answers(first)
    handlers[wire.CRITIC][1](critic)  # the critic's answer, re-published
    assert asm.holds_answers(first)


def test_a_late_input_is_waited_for_and_a_lost_one_given_up_after_a_later_step_is_complete():
    """DDS repairs a lost sample of one topic while the others flow on: the learner keeps
    the later steps queued until the late sample comes. One that never comes is given up
    once a later step has been complete for ``LOST_AFTER_S``: its episode is lost, the next
    ones are assembled."""
    episodes = VALID_EPISODES * 4
    stream = group_stream(episodes)
    late = next(i for i, (topic, _) in enumerate(stream) if topic == wire.ACTION)  # episode 0's first action
    for lost in (False, True):
        finished = []
        asm = TransitionAssembler("/", CFG, NUM_SUBGOALS, finished.append, logger=LOG)
        handlers = asm.inputs()
        for topic, msg in stream[:late] + stream[late + 1:]:
            if topic in handlers:
                handlers[topic][1](msg)
        assert finished == [] and asm.assembled_env_steps == 0  # everything waits for the missing action
        asm.check_stall(now=100.0)  # later steps are complete from here on
        asm.check_stall(now=100.0 + follower.LOST_AFTER_S - 0.5)
        assert finished == [] and asm.lost_episodes == 0
        if not lost:
            handlers[wire.ACTION][1](stream[late][1])
            assert len(finished) == len(episodes) and asm.lost_episodes == 0
        else:
            asm.check_stall(now=100.0 + follower.LOST_AFTER_S)
            assert len(finished) == len(episodes) - 1 and asm.lost_episodes == 1
        assert asm.assembled_env_steps == sum(map(len, episodes))


def test_batched_records_split_into_the_single_environment_ones():
    """A batch of N records is N single-environment records under an ``env`` dimension; for
    N = 1 the message is byte for byte the single-environment one."""
    m = RosbagsMessages()
    rows = [[5_000_000 + 0.0 * i, 1, 2, 3, i % 4] for i in range(3)]
    one = TYPESTORE.serialize_cdr(wire.make_records(m, wire.INTS, wire.SUBGOAL_FIELDS[:2] + ("a", "b", "c"), rows[:1]),
                                  wire.INTS)
    assert one == TYPESTORE.serialize_cdr(wire.make_record(m, wire.INTS, wire.SUBGOAL_FIELDS[:2] + ("a", "b", "c"),
                                                           rows[0]), wire.INTS)
    step = dict.fromkeys(wire.STEP_FIELDS, 0.0) | {"key": 7e6, "t": 2, "prev_key": 6e6, "action": 1}
    batch = wire.make_records(m, wire.FLOATS, wire.STEP_FIELDS,
                              [[step[f] if f != "action" else i for f in wire.STEP_FIELDS] for i in range(4)])
    assert [d.label for d in batch.layout.dim] == [wire.ENV_DIM, ",".join(wire.STEP_FIELDS)]
    assert [r["action"] for r in wire.read_steps(batch)] == [0, 1, 2, 3]
    assert wire.envs_in(batch) == 4 and wire.envs_in(wire.make_record(m, wire.FLOATS, ("key",), [1])) == 1
    batch.data[len(wire.STEP_FIELDS)] = 8e6  # environment 1's key differs
    with pytest.raises(wire.ProtocolError, match="different step keys"):
        wire.read_steps(batch)
    actions = wire.make_records(m, wire.INTS, wire.ACTION_FIELDS, [[7, -1], [7, 2]])
    assert wire.read_actions(actions, 4)[1].tolist() == [-1, 2]  # no action: that episode ended
    with pytest.raises(wire.ProtocolError, match="expected 3"):
        wire.read_actions(actions, 4, num_envs=3)
    with pytest.raises(wire.ProtocolError, match="out of range"):  # one environment always acts
        wire.read_actions(wire.make_record(m, wire.INTS, wire.ACTION_FIELDS, [7, -1]), 4)
    actions.layout.dim[0].size = wire.MAX_ENVS + 1
    with pytest.raises(wire.ProtocolError, match="expected 2..64"):
        wire.read_actions(actions, 4)


@settings(max_examples=150, **QUICK)
@given(episodes=fuzzed_episodes)
def test_learner_assembles_random_messages_without_crashing(episodes):
    """The learner node's per-group assembler (a bad message is logged and dropped): any
    stream of odd values gives no exception, and only episodes fit for training."""
    _, finished = assemble(episodes)
    for _, sub, meta, _ in finished:
        check_episode(sub, meta)


# -- 4. bags -------------------------------------------------------------------------------------------
def write_recording(path: Path, episodes: list[list[dict]], compress: bool = False) -> Path:
    """A recording of one hDRQNv2 group (what ``hdrqn train --record`` writes), uncompressed by default
    so that byte flips reach the CDR."""
    bag = BagRecorder(path, CFG, "test_fuzz", compress=compress)
    conns = bag.add_group("/", recorded_topics("hdrqn-v2"))
    for topic, msg in group_stream(episodes):
        bag.write(conns[topic], bytes(TYPESTORE.serialize_cdr(msg, GROUP_TOPICS[topic])))
    bag.close()
    return bag.path


@pytest.mark.parametrize("case", ["lost", "late", "lost, then a silent gap", "lost, then the recording ends",
                                  "lost, then a gap of years"])
def test_a_step_the_learner_gave_up_as_lost_is_given_up_in_its_recording(tmp_path, caplog, case):
    """The learner node skips a step whose input never came once a later step has been
    complete for ``LOST_AFTER_S`` by its 1 s timer, which also ticks while nothing arrives;
    reading its recording, the arrival times drive that timer, so the later episodes are
    read as the learner acknowledged them, not held until the queue overflows. A late input
    within that time is waited for. A recording that ends (a killed learner's) before
    the step was given up gives it up at its end: no input can come any more."""
    episodes = VALID_EPISODES * 4
    stream = group_stream(episodes)
    late = next(i for i, (topic, _) in enumerate(stream) if topic == wire.ACTION)  # episode 0's first action
    spacing = {"lost, then the recording ends": 0.01}.get(case, 0.25)  # s between arrivals
    arrivals = [(spacing * i, item) for i, item in enumerate(stream) if i != late]
    if case == "late":
        arrivals.append((spacing * late + follower.LOST_AFTER_S / 2, stream[late]))
    if case.startswith("lost, then a"):  # nothing arrives for a while after a later step is complete
        gap_s = 2 * follower.LOST_AFTER_S if case.endswith("silent gap") else 3e8  # 10 years: ticks are skipped
        arrivals = [(t + gap_s * (i > 40), item) for i, (t, item) in enumerate(arrivals)]
    bag = BagRecorder(tmp_path / "rec", CFG, "test_fuzz", compress=False)
    conns = bag.add_group("/", recorded_topics("hdrqn-v2"))
    for t, (topic, msg) in sorted(arrivals, key=lambda a: a[0]):
        bag.writer.write(conns[topic], int(1e18 + t * 1e9), bytes(TYPESTORE.serialize_cdr(msg, GROUP_TOPICS[topic])))
    bag.close()
    stats = BagReadStats()
    with caplog.at_level(logging.WARNING):
        read = list(read_episodes([bag.path], CFG, NUM_SUBGOALS, stats))
    expected = len(episodes) - (case != "late")
    assert len(read) == expected, len(read)
    assert sum(stats.incomplete_episodes.values()) == len(episodes) - expected
    given_up = [r.getMessage() for r in caplog.records if "never arrived" in r.getMessage()]
    assert bool(given_up) == (case != "late"), given_up
    why = "before the recording ends" if case.endswith("ends") else "while a later step was complete"
    assert all(why in line for line in given_up), given_up


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    bag = write_recording(tmp_path_factory.mktemp("fuzz") / "rec", VALID_EPISODES)
    assert [len(sub.fields["action"]) for _, sub, _, _ in read_episodes([bag], CFG, NUM_SUBGOALS)] == [3, 2]
    return bag


@contextlib.contextmanager
def copy_of(bag: Path):
    with tempfile.TemporaryDirectory() as tmp:
        yield Path(shutil.copytree(bag, Path(tmp) / bag.name))


BAG_READERS = {"bag_summary": bag_summary, "bag_topics": bag_topics, "bag_config": bag_config,
               "episode_summary": episode_summary, "read_messages": lambda b: list(read_messages(b)),
               "read_episodes": lambda b: list(read_episodes([b], CFG, NUM_SUBGOALS)), "repair_bag": repair_bag}
"""Everything that reads a bag (one per example: each parses metadata.yaml, which is slow)."""


yaml_junk = st.sampled_from(["", "[", "{a: 1", "2001-13-01", "!!int x", "!!bool maybe", "[" * 400, "&a [*a]", "~",
                             "- 1\n- 2", "-1", "1e999", "{}", "nanoseconds_since_epoch", "\x00"]) | st.text(max_size=20)


@st.composite
def metadata_edits(draw, text: str) -> str:
    """metadata.yaml with lines dropped, values replaced by junk, or cut short."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        i = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["drop", "value", "line", "cut"]))
        if kind == "drop":
            del lines[i]
        elif kind == "value":
            head, sep, _ = lines[i].partition(":")
            lines[i] = head + (sep or ":") + " " + draw(yaml_junk).replace("\n", " ")
        elif kind == "line":
            lines[i] = draw(yaml_junk)
        else:
            lines = lines[:i]
        if not lines:
            break
    return "\n".join(lines)


near_ends = st.integers(0, 4096) | st.integers(-4096, -1) | st.integers(0, 2**31)
"""Byte offsets, mostly in an MCAP file's header, summary and footer (negative: from the end)."""


@settings(max_examples=70, **QUICK)
@given(data=st.data(), flips=st.lists(st.tuples(near_ends, st.integers(1, 255)), max_size=4),
       cut=st.none() | near_ends, meta=st.booleans(), reader=st.sampled_from(sorted(BAG_READERS)))
def test_damaged_bags_give_bag_errors(recording, data, flips, cut, meta, reader):
    """Flipped bytes, a cut file, a mangled metadata.yaml: each reader succeeds or raises
    BagError naming the bag; a bag that repair_bag accepted can then be read."""
    with copy_of(recording) as bag:
        file = next(bag.glob("*.mcap"))
        raw = bytearray(file.read_bytes())
        for pos, value in flips:
            raw[pos % len(raw)] ^= value
        if cut is not None:
            raw = raw[:cut % len(raw)]
        file.write_bytes(bytes(raw))
        if meta:
            text = (bag / "metadata.yaml").read_text()
            (bag / "metadata.yaml").write_text(data.draw(metadata_edits(text)))
        try:
            BAG_READERS[reader](bag)
        except BagError as exc:
            assert str(bag) in str(exc), exc
        else:
            if reader == "repair_bag":
                bag_summary(bag)


@settings(max_examples=25, **QUICK)
@given(episodes=fuzzed_episodes)
def test_recordings_of_odd_values_give_episodes_fit_for_training_or_bag_errors(episodes):
    """A bag of well-formed CDR whose values are odd (out-of-range actions and subgoals,
    flags of 0.5, rewards beyond float32, contradicting critics): read_episodes yields only
    episodes training can use, or raises BagError naming the bag and topic."""
    with tempfile.TemporaryDirectory() as tmp:
        bag = write_recording(Path(tmp) / "odd", episodes)
        try:
            for _, sub, meta, _ in read_episodes([bag], CFG, NUM_SUBGOALS):
                check_episode(sub, meta)
        except BagError as exc:
            assert str(bag) in str(exc) and "topic" in str(exc), exc
        try:
            assert all(group["episodes"] <= len(episodes) for group in episode_summary(bag).values())
        except BagError as exc:
            assert str(bag) in str(exc) and "topic /env_step" in str(exc), exc


# -- 5. configs, --set overrides, ROS arguments and parameters files --------------------------------
NASTY_YAML = ["2001-13-01", "2001-02-30 10:00:00", "!!int x", "a: !!int", "!!float x", "!!bool maybe", "!!timestamp x",
              "!!binary '%'", "[" * 1200, "{" * 1200, "&a [*a]", "*x", "!!python/object/apply:os.system [ls]",
              "{[1]: 2}", "? [a]\n: 1", "\x00", "\ufeff\x85", "1e999", "-.inf", ".nan", "0x1_", "~", "''", "|\n x",
              "a: b: c", "- - -", "%YAML 1.1\n---", "--- 1\n--- 2"]
"""YAML that PyYAML rejects with ValueError, KeyError, AttributeError, RecursionError..., or that
builds odd values (recursive lists, NaN, bytes)."""
CONFIG_KEYS = sorted(TrainConfig.model_fields) + ["sub.seq_len", "meta.epsilon.steps", "env_kwargs.view", "view",
                                                  "sub.epsilon", "files", "base", "", ".", "a..b", "env_kwargs"]
yaml_values = st.sampled_from(NASTY_YAML) | st.text(max_size=12) | st.integers().map(str) | st.floats().map(str)
json_like = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
                         lambda inner: st.lists(inner, max_size=3)
                         | st.dictionaries(st.sampled_from(CONFIG_KEYS) | st.text(max_size=5) | st.integers(),
                                           inner, max_size=3), max_leaves=12)


@contextlib.contextmanager
def text_file(text: str | bytes, name: str = "file.yaml"):
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
        yield path


@settings(max_examples=300, **QUICK)
@given(items=st.lists(st.tuples(st.sampled_from(CONFIG_KEYS) | st.text(max_size=8), st.sampled_from(["=", ":", ""]),
                                yaml_values).map("".join), max_size=4))
@example(items=["files=[]"])  # collides with build_config's own parameter names
@example(items=["base=1"])
@example(items=["sub.seq_len=2001-13-01"])
@example(items=["env_kwargs.foo=1"])
def test_set_overrides_give_a_config_or_config_error(items):
    try:
        overrides = parse_set(items)
        cfg = build_config([], **overrides)
    except ConfigError as exc:
        assert str(exc)
        return
    usable(cfg)


def usable(cfg: TrainConfig) -> None:
    """What the trainer does with a config: a torch device, a domain of ``env_kwargs``
    (whose values it checks itself, with ValueError)."""
    import torch

    torch.device(cfg.device)
    if cfg.env in GRID_IDS:
        with contextlib.suppress(ValueError):
            make_batch(cfg.env, 1, **cfg.env_kwargs)


@settings(max_examples=200, **QUICK)
@given(doc=json_like.map(lambda d: yaml.safe_dump(d, allow_unicode=True)) | st.sampled_from(NASTY_YAML)
       | st.text(max_size=60) | st.binary(max_size=30))
@example(doc=b"algo: \xff\xfe")  # not UTF-8
@example(doc="device: junk")  # not a torch device
@example(doc="env_kwargs: {foo: 1}")  # not an option of the domain
def test_config_files_give_a_config_or_config_error_naming_the_file(doc):
    with text_file(doc) as path:
        try:
            cfg = build_config([path])
        except ConfigError as exc:
            assert str(path) in str(exc)
            return
    usable(cfg)


ROS_FLAGS = ["--ros-args", "--", "-p", "--param", "-r", "--remap", "--params-file", "--log-level", "-e", "--enclave",
             "--disable-rosout-logs", "--unknown", "-x"]
ros_values = (st.tuples(st.sampled_from(["algo", "view", "seed", "num_envs", "epsilon", "groups", "resume", "episodes",
                                         "max_message_bytes", "use_sim_time", "__node", "__ns", "env_step", "/a",
                                         "~/b", "node:topic", "", "x:y:z"]),
                        st.sampled_from([":=", "=", ""]), yaml_values).map("".join) | st.text(max_size=10))
params_files = st.dictionaries(
    st.sampled_from(["/**", "learner", "/learner", "/**/sub_controller", "/group0/sub_controller", "/a/b/learner",
                     "ns"]),
    st.dictionaries(st.sampled_from(["ros__parameters", "learner", "x"]),
                    st.dictionaries(st.sampled_from(["algo", "view", "seed", "num_envs", "epsilon", "groups",
                                                     "episodes", "max_message_bytes"]) | st.text(max_size=5),
                                    json_like, max_size=3) | json_like, max_size=2),
    max_size=2).map(yaml.safe_dump)
"""ROS 2 parameters files, mostly shaped as one (``/**:`` / node name, ``ros__parameters:``)."""
PRIVATE_DOMAIN = 228
"""The DDS domain of this module's nodes: no process test takes it (they use 20..219)."""


@functools.cache
def fuzzed_table() -> dict:
    """The parameters a node declares: the controllers' and the learner's (every kind of rule)."""
    return {**ros("controller_node").CONTROLLER_PARAMETERS, **ros("learner").PARAMETERS}


def declared_as(value, default) -> bool:
    if isinstance(default, list):
        return isinstance(value, list) and all(type(v) is type(default[0]) for v in value)
    return type(value) is type(default)


@NEEDS_RCLPY
@settings(max_examples=200, **QUICK)
@given(argv=st.lists(st.sampled_from(ROS_FLAGS) | ros_values, max_size=8),
       params=params_files | json_like.map(yaml.safe_dump) | st.sampled_from(NASTY_YAML), with_file=st.booleans(),
       node=st.sampled_from(["learner", "sub_controller"]), ns=st.sampled_from(["/", "/group0", "/a/b"]))
@example(argv=[], params="/**:\n  ros__parameters:\n    seed: 2001-13-01\n", with_file=True, node="learner", ns="/")
@example(argv=["-p", "max_message_bytes:=[1]"], params="", with_file=False, node="learner", ns="/")
@example(argv=["-p", "epsilon:=.nan"], params="", with_file=False, node="sub_controller", ns="/group0")
@example(argv=["-p", "view:=²"], params="", with_file=False, node="learner", ns="/")
def test_ros_args_and_params_files_give_parameters_or_errors(argv, params, with_file, node, ns):
    """``--ros-args`` and a random parameters file, as a node process starts (``run_node``):
    ``rclpy.init`` refuses them with a ``RuntimeError`` (the node exits 2), or the node is made
    and declares its parameters: each of its declared type and within its rules, or a
    ``NodeConfigError`` naming the parameter (exit 2)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.signals import SignalHandlerOptions

    from hdrqn_ros.dds import INTERFACE_ENV, apply_rmw_network_defaults

    parameters = ros("parameters")
    table = fuzzed_table()
    with text_file(params, "params.yaml") as path, mock.patch.dict(os.environ):
        apply_rmw_network_defaults(os.environ.get(INTERFACE_ENV) or None)
        if "--params-file" in argv:
            argv.insert(argv.index("--params-file") + 1, str(path))
        elif with_file:
            argv = ["--params-file", str(path), *argv]
        context = Context()
        try:
            rclpy.init(args=["fuzz", "--ros-args", *argv], context=context, domain_id=PRIVATE_DOMAIN,
                       signal_handler_options=SignalHandlerOptions.NO)
        except RuntimeError as exc:
            assert str(exc)
            return
        try:
            made = Node(node, namespace=ns, context=context)
            try:
                values = parameters.declare_parameters(made, table)
            except parameters.NodeConfigError as exc:
                assert any(f"parameter {name!r}" in str(exc) for name in table), exc
                return
            finally:
                made.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)
            context.destroy()
    for name, param in table.items():
        assert declared_as(values[name], param.default) and param.refusal(name, values[name]) is None, \
            (name, values[name])


# -- 6. the hdrqn command -------------------------------------------------------------------------------
class Started(BaseException):
    """Raised where a command would start its long work (training, evaluation, a graph, playing)."""


LONG_WORK = ["hdrqn_ros.training.trainer.Trainer", "hdrqn_ros.training.offline.OfflineTrainer",
             "hdrqn_ros.training.learner.evaluate", "hdrqn_ros.supervisor.Supervisor",
             "hdrqn_ros.nodes.process.run_node"]
CLI_COMMANDS = [("train",), ("eval",), ("plot",), ("up",), ("bag", "info"), ("bag", "repair"), ("bag", "play"),
                ("envs",), ("values",)]
"""The commands fuzzed (with LONG_WORK stubbed): not ``experiment``, which starts processes."""
PATHS = ["missing", "file.txt", "emptydir", "bag", "bad.yaml", "latin1.yaml", "config.yaml", "emptydir/new",
         "file.txt/below", "", "bag/metadata.yaml", "bag/rec_0.mcap"]
"""Paths in the example's working directory (see :func:`cli_workdir`)."""
junk = st.sampled_from(["--", "-", "--bogus", "-x", "nan", "inf", "-1", "0", "1e400", "full", "\x00", "=", "a=b"]) \
    | st.text(max_size=6)


def _subparser(parser, names):
    for name in names:
        parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
    return parser


def _values(action) -> st.SearchStrategy:
    """Values for one argument: plausible ones from its definition (four times in five), or junk."""
    if action.choices:
        plausible = st.sampled_from(sorted(map(str, action.choices)))
    elif action.type is int:  # small: --num-envs, --groups... size what a command builds before its long work
        plausible = st.integers(-3, 20).map(str)
    elif action.type is float:
        plausible = st.sampled_from(["nan", "inf", "-inf", "-1", "0", "0.5", "2", "1e400"])
    elif action.dest == "set":
        plausible = st.tuples(st.sampled_from(CONFIG_KEYS), yaml_values).map("=".join)
    else:
        plausible = st.sampled_from(PATHS)
    return st.integers(0, 4).flatmap(lambda i: plausible if i else junk)


@st.composite
def cli_argv(draw) -> list[str]:
    """A command of :data:`CLI_COMMANDS` with its positionals, its required options and about a third
    of the others (all as its parser defines them), and now and then a stray argument."""
    command = draw(st.sampled_from(CLI_COMMANDS))
    parser = _subparser(cli.build_parser(), command)
    argv = list(command)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or \
                (action.option_strings and not action.required and draw(st.integers(0, 2))):
            continue
        many = action.nargs in ("+", "*")
        count = 0 if action.nargs == 0 else draw(st.integers(int(action.nargs != "*"), 3 if many else 1))
        if action.option_strings:
            argv.append(draw(st.sampled_from(action.option_strings)))
        argv += [draw(_values(action)) for _ in range(count)]
    if not draw(st.integers(0, 5)):
        argv.append(draw(junk | st.sampled_from(["--help", "-h", "--version"])))
    return argv


@contextlib.contextmanager
def cli_workdir(recording: Path):
    """A fresh working directory holding the files that :data:`PATHS` name, with a clean environment."""
    with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp), mock.patch.dict(os.environ):
        os.environ.pop("HDRQN_DEBUG", None)
        Path("file.txt").write_text("not a config: [")
        Path("emptydir").mkdir()
        Path("bad.yaml").write_text("algo: [unclosed\n")
        Path("latin1.yaml").write_bytes("algo: caf\xe9\n".encode("latin-1"))
        Path("config.yaml").write_text("episodes: 3\nnum_envs: 1\n")
        shutil.copytree(recording, "bag")
        yield


def run_cli(argv: list[str], capsys) -> int | None:
    """``hdrqn ARGV`` in this process: its exit code, or None where it started its long work."""
    try:
        rc = cli.main(argv)
    except SystemExit as exc:
        rc = exc.code
    except Started:
        rc = None
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    if rc is not None:
        assert rc in (0, 1, 2), (rc, err)
    if rc == 2:
        assert "error" in err or "usage" in err, err
    return rc


@pytest.fixture
def long_work_stubbed(monkeypatch):
    def started(*args, **kwargs):
        raise Started()

    # import every module first: one imported while patched would keep the stub (``from x import f``)
    root = Path(hdrqn_ros.__file__).parent
    for file in sorted(f for f in root.rglob("*.py") if f.name != "__init__.py"):
        with contextlib.suppress(ImportError):
            importlib.import_module(".".join(("hdrqn_ros", *file.relative_to(root).with_suffix("").parts)))
    for target in LONG_WORK:
        monkeypatch.setattr(target, started)


@settings(max_examples=150, **QUICK)
@given(argv=cli_argv())
@example(argv=["train", "--out", "run", "--device", "junk"])
@example(argv=["train", "--out", "run", "--set", "env_kwargs.foo=1"])
@example(argv=["train", "--out", "run", "--set", "files=3"])
@example(argv=["train", "--out", "run", "--config", "latin1.yaml"])
@example(argv=["train", "--out", "run", "--set", "sub.seq_len=2001-13-01"])
@example(argv=["bag", "info", "bag"])
@example(argv=["bag", "repair", "bag"])
@example(argv=["train", "--from-bag", "bag", "--out", "offline"])
@example(argv=["eval", "--policy", "", "--subgoals", "--no-fire"])
def test_cli_exits_0_1_2_without_traceback(argv, recording, capsys, long_work_stubbed):
    with cli_workdir(recording):
        rc = run_cli(argv, capsys)
    if argv[:2] in (["bag", "info"], ["bag", "repair"]) and argv[2:] == ["bag"]:
        assert rc == 0


def test_cli_view_with_a_non_mapping_env_kwargs(recording, capsys, long_work_stubbed):
    with cli_workdir(recording):
        assert run_cli(["train", "--out", "run", "--set", "env_kwargs=5", "--view", "3"], capsys) == 2


def test_cli_up_out_is_a_file(recording, capsys, long_work_stubbed):
    with cli_workdir(recording):
        assert run_cli(["up", "--out", "file.txt"], capsys) == 2


def test_cli_infinite_record_split(recording, capsys, long_work_stubbed):
    with cli_workdir(recording):
        assert run_cli(["train", "--out", "run", "--record", "rec", "--record-split-mb", "inf"], capsys) == 2
