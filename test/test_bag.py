"""rosbag2 MCAP bag layer: write/read round trip, splitting, crash repair, bad input."""
import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from ruamel.yaml import YAML

from hdrqn_ros.recording import bag as bagmod
from hdrqn_ros.recording.bag import BagError, BagWriter, bag_summary, read_messages, repair_bag
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
TOPICS = {"/obs": "sensor_msgs/msg/Image", "/q": "std_msgs/msg/Float64MultiArray",
          "/act": "std_msgs/msg/Int64MultiArray"}


def _cdr(msg):
    return bytes(TS.serialize_cdr(msg, msg.__msgtype__))


def make_stream(n_images, t0=1_700_000_000_000_000_000, dt=50_000_000):
    """Deterministic (topic, type, t_ns, cdr) list: per step one image, Q-values, action."""
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0)
    out = []
    for i in range(n_images):
        t = t0 + i * dt
        stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
        pixels = np.random.default_rng(i).integers(0, 256, 44 * 44 * 3, dtype=np.uint8)
        img = T["sensor_msgs/msg/Image"](
            header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam"), height=44, width=44,
            encoding="rgb8", is_bigendian=0, step=44 * 3, data=pixels)
        q = T["std_msgs/msg/Float64MultiArray"](layout=layout, data=np.arange(4.0) * i)
        a = T["std_msgs/msg/Int64MultiArray"](layout=layout, data=np.array([i % 4, i], np.int64))
        out += [("/obs", TOPICS["/obs"], t, _cdr(img)), ("/q", TOPICS["/q"], t + 1, _cdr(q)),
                ("/act", TOPICS["/act"], t + 2, _cdr(a))]
    return out


def write_bag(path, stream, **kw):
    with BagWriter(path, **kw) as w:
        for topic, type_name in TOPICS.items():
            w.add_topic(topic, type_name, qos="best_effort" if topic == "/obs" else "reliable",
                        transient_local=topic == "/act", depth=5)
        for topic, _type, t, data in stream:
            w.write(topic, t, data)


def metadata(path):
    return YAML(typ="safe").load((Path(path) / "metadata.yaml").read_text())[
        "rosbag2_bagfile_information"]


def test_round_trip_bit_exact_with_v9_metadata(tmp_path):
    stream = make_stream(30)
    write_bag(tmp_path / "b", stream)
    assert list(read_messages(tmp_path / "b")) == stream
    assert [m[2] for m in read_messages(tmp_path / "b", topics=["/q"])] == \
        [m[2] for m in stream if m[0] == "/q"]
    info = metadata(tmp_path / "b")
    assert info["version"] == 9 and info["storage_identifier"] == "mcap"
    assert info["relative_file_paths"] == ["b_0.mcap"] and info["message_count"] == 90
    qos = {t["topic_metadata"]["name"]: t["topic_metadata"]["offered_qos_profiles"]
           for t in info["topics_with_message_count"]}
    assert qos["/obs"][0]["reliability"] == "best_effort" and qos["/obs"][0]["depth"] == 5
    assert qos["/act"][0]["durability"] == "transient_local"
    assert qos["/q"][0]["reliability"] == "reliable" and qos["/q"][0]["history"] == "keep_last"
    with open(tmp_path / "b" / "b_0.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {s.name for s in summary.schemas.values()} == set(TOPICS.values())
    assert all("offered_qos_profiles" in c.metadata for c in summary.channels.values())
    s = bag_summary(tmp_path / "b")
    assert s["topics"]["/obs"] == {"type": "sensor_msgs/msg/Image", "count": 30}
    assert s["start_ns"] == stream[0][2] and s["end_ns"] == stream[-1][2]
    assert [f["path"] for f in s["files"]] == ["b_0.mcap"]


def test_mcap_ros2_decoder_reads_every_message(tmp_path):
    stream = make_stream(10)
    write_bag(tmp_path / "b", stream)
    with open(tmp_path / "b" / "b_0.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [(ch.topic, m.log_time, msg) for _s, ch, m, msg in reader.iter_decoded_messages()]
    assert [(t, ts) for t, ts, _ in decoded] == [(m[0], m[2]) for m in stream]
    images = [msg for t, _, msg in decoded if t == "/obs"]
    assert images[3].width == 44 and images[3].encoding == "rgb8"
    assert bytes(images[3].data) == np.random.default_rng(3).integers(
        0, 256, 44 * 44 * 3, dtype=np.uint8).tobytes()
    assert list(decoded[1][2].data) == [0.0, 0.0, 0.0, 0.0]


def test_split_by_size_and_time(tmp_path):
    stream = make_stream(200)
    write_bag(tmp_path / "s", stream, split_bytes=250_000)
    info = metadata(tmp_path / "s")
    files = sorted(p.name for p in (tmp_path / "s").glob("*.mcap"))
    assert len(files) >= 4 and sorted(info["relative_file_paths"]) == files
    assert sum(f["message_count"] for f in info["files"]) == len(stream)
    for name in files:  # each file is a standalone MCAP with all schemas and channels
        with open(tmp_path / "s" / name, "rb") as f:
            assert len(make_reader(f).get_summary().channels) == 3
    assert list(read_messages(tmp_path / "s")) == stream
    write_bag(tmp_path / "t", stream, split_seconds=2.0)  # 50 ms per step -> 200 steps = 10 s
    info = metadata(tmp_path / "t")
    assert len(info["files"]) == 5
    assert all(f["duration"]["nanoseconds"] <= 2e9 for f in info["files"])
    assert list(read_messages(tmp_path / "t")) == stream


CRASH = """
import os, signal, sys
sys.path.insert(0, {testdir!r})
from test_bag import TOPICS, make_stream
from hdrqn_ros.recording.bag import BagWriter
w = BagWriter({path!r})
for topic, type_name in TOPICS.items():
    w.add_topic(topic, type_name)
for topic, _type, t, data in make_stream(600):
    w.write(topic, t, data)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_kill_9_then_repair_recovers_complete_chunks(tmp_path):
    path = tmp_path / "crash"
    code = CRASH.format(testdir=str(Path(__file__).parent), path=str(path))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert proc.returncode == -9, proc.stderr.decode()
    with pytest.raises(BagError, match="hdrqn bag repair"):
        list(read_messages(path))
    report = repair_bag(path)
    assert report.repaired == ["crash_0.mcap"] and report.files == ["crash_0.mcap"]
    got = list(read_messages(path))
    written = make_stream(600)
    assert got == written[:len(got)] and report.messages_recovered == len(got)
    assert sum(len(m[3]) for m in got) >= 2 * 2**20
    assert bag_summary(path)["message_count"] == len(got) == report.message_count


@pytest.fixture(scope="module")
def single_file_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("whole") / "b"
    stream = make_stream(450)  # ~2.6 MiB: two complete 1 MiB chunks and a partial one
    write_bag(path, stream)
    return path, stream


@settings(max_examples=25, deadline=None)
@given(frac=st.floats(0.0, 1.0))
@example(frac=0.0)
@example(frac=1.0)
def test_truncated_file_repairs_to_a_prefix_or_bag_error(single_file_bag, tmp_path_factory, frac):
    src, stream = single_file_bag
    path = tmp_path_factory.mktemp("trunc") / "b"
    shutil.copytree(src, path)
    data_file = path / "b_0.mcap"
    os.truncate(data_file, int(frac * data_file.stat().st_size))
    try:
        repair_bag(path)
    except BagError:
        return
    got = list(read_messages(path))
    assert got == stream[:len(got)]
    if frac == 1.0:
        assert got == stream


def test_bad_input_raises_bag_error_naming_path(tmp_path):
    afile = tmp_path / "file.txt"
    afile.write_text("x")
    for fn in (lambda p: list(read_messages(p)), bag_summary, repair_bag):
        for p in (afile, tmp_path / "missing"):
            with pytest.raises(BagError, match=str(p)):
                fn(p)
    empty = tmp_path / "empty"
    empty.mkdir()
    for fn in (lambda p: list(read_messages(p)), bag_summary, repair_bag):
        with pytest.raises(BagError, match=str(empty)):
            fn(empty)
    garbage = tmp_path / "garbage"
    garbage.mkdir()
    (garbage / "garbage_0.mcap").write_bytes(b"this is not an mcap file at all" * 10)
    with pytest.raises(BagError, match="repair"):
        list(read_messages(garbage))
    with pytest.raises(BagError, match="garbage_0.mcap"):
        repair_bag(garbage)
    (garbage / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9,")
    with pytest.raises(BagError, match="metadata.yaml"):
        bag_summary(garbage)
    with pytest.raises(BagError, match="already exists"):
        BagWriter(garbage)


def test_unknown_message_types(tmp_path):
    with BagWriter(tmp_path / "u") as w:
        with pytest.raises(BagError, match="foo_msgs/msg/Bar"):
            w.add_topic("/x", "foo_msgs/msg/Bar")
        w.add_topic("/q", "std_msgs/msg/Float64MultiArray")
        w.write("/q", 5, make_stream(1)[1][3])
    meta = tmp_path / "u" / "metadata.yaml"
    meta.write_text(meta.read_text().replace("type: std_msgs/msg/Float64MultiArray",
                                             "type: foo_msgs/msg/Bar"))
    with pytest.raises(BagError, match=r"metadata\.yaml.*foo_msgs/msg/Bar"):
        list(read_messages(tmp_path / "u"))


def test_disk_full_is_a_bag_error_and_closed_files_survive(tmp_path, monkeypatch):
    stream = make_stream(60)
    w = BagWriter(tmp_path / "d", split_bytes=100_000)
    for topic, type_name in TOPICS.items():
        w.add_topic(topic, type_name)
    for topic, _type, t, data in stream[:120]:
        w.write(topic, t, data)
    assert len(metadata(tmp_path / "d")["files"]) >= 1  # at least one closed file listed

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(bagmod._McapFile, "close", full)
    with pytest.raises(BagError, match=f"{tmp_path / 'd'}.*No space left"):
        for topic, _type, t, data in stream[120:]:
            w.write(topic, t, data)
        w.close()
    w.close()  # idempotent after failure
    monkeypatch.undo()
    with pytest.raises(BagError, match="repair"):
        list(read_messages(tmp_path / "d"))
    repair_bag(tmp_path / "d")
    got = list(read_messages(tmp_path / "d"))
    assert len(got) >= sum(f["message_count"] for f in metadata(tmp_path / "d")["files"][:1])
    assert got == stream[:len(got)]


def test_cli_bag_info_and_repair(tmp_path):
    """``hdrqn bag info`` / ``repair`` as a user runs them (a real subprocess), exit codes included."""
    store = get_typestore(Stores.ROS2_JAZZY)
    bag = tmp_path / "run_bag"
    with BagWriter(bag) as w:
        w.add_topic("/env_step", "std_msgs/msg/Float64MultiArray")
        for i in range(5):
            msg = store.types["std_msgs/msg/Float64MultiArray"](
                layout=store.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
                data=np.arange(3, dtype=np.float64) + i)
            w.write("/env_step", 1_000 + i, bytes(store.serialize_cdr(msg, "std_msgs/msg/Float64MultiArray")))

    def hdrqn(*args):
        return subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", "bag", *args], capture_output=True, text=True)

    info = hdrqn("info", str(bag))
    assert info.returncode == 0 and "/env_step" in info.stdout and "5" in info.stdout
    assert json.loads(hdrqn("info", "--json", str(bag)).stdout)["message_count"] == 5
    repaired = hdrqn("repair", str(bag))
    assert repaired.returncode == 0 and "5 messages" in repaired.stdout
    bad = hdrqn("info", str(tmp_path / "nope"))
    assert bad.returncode == 2 and "nope" in bad.stderr and "Traceback" not in bad.stderr
