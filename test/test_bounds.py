"""Bounded resources: an oversized image or weights message is rejected before decoding,
logged, and does not grow the receiving node's memory (real rclpy processes)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.nodes.qos import LATCHED_QOS, STEP_QOS  # noqa: E402
from hdrqn_ros.protocol import wire  # noqa: E402
from hdrqn_ros.supervisor import Supervisor  # noqa: E402

from conftest import node_process, ros_probe  # noqa: E402
from test_graph import wait_for  # noqa: E402

LIMIT = 1 << 20  # the sub-controller's max_message_bytes in this test


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def test_oversized_images_and_weights_are_dropped_without_growing_memory(domain, tmp_path):
    sub = node_process("sub", "sub_controller", "-p", "algo:=dqn", "-p", f"max_message_bytes:={LIMIT}")
    sup = Supervisor([sub], log_dir=tmp_path / "logs", stop_timeout_s=30)
    log = tmp_path / "logs" / "sub.log"
    sup.start()
    mw = ros_probe()
    try:
        node = mw.create_node("flooder")
        obs_pub = node.create_publisher(wire.IMAGE, "/observation", STEP_QOS)
        weights_pub = node.create_publisher(wire.BYTES, wire.WEIGHTS["sub"], LATCHED_QOS)
        step_pub = node.create_publisher(wire.FLOATS, wire.ENV_STEP, STEP_QOS)
        answered: list[int] = []
        node.create_subscription(wire.INTS, wire.ACTION, lambda m: answered.extend(
            int(r["key"]) for r in wire.read_records(m, wire.ACTION_FIELDS, np.int64)), STEP_QOS)
        for pub in (obs_pub, weights_pub, step_pub):
            mw.spin(until=lambda: pub.get_subscription_count() > 0, timeout_s=60)
            assert pub.get_subscription_count(), "the sub-controller never subscribed"
        pid = sup.pids["sub"]
        big_image = np.zeros((1024, 1024, 3), np.uint8)  # 3 MiB, over the 1 MiB limit
        big_weights = bytes(4 * LIMIT)

        def flood(rounds: int) -> None:
            for i in range(rounds):
                obs_pub.publish(wire.make_image(node, 10_000_000 * (i + 1), big_image, "map"))
                weights_pub.publish(wire.make_weights(node, big_weights, i))
                mw.spin(timeout_s=0.05)

        def taken_up_to(key: int) -> None:
            """A valid step after the flood, on the same writers: once the sub-controller has
            answered it, it has taken (and dropped) every sample before it. A loaded machine
            delays that, and until then the samples wait in its DDS reader (up to the QoS depth)."""
            obs_pub.publish(wire.make_image(node, key, np.zeros((44, 44, 3), np.uint8), "map"))
            record = dict.fromkeys(wire.STEP_FIELDS, 0.0) | {"key": key}
            step_pub.publish(wire.make_record(node, wire.FLOATS, wire.STEP_FIELDS, [record[f] for f in wire.STEP_FIELDS]))
            mw.spin(until=lambda: key in answered, timeout_s=120)
            assert key in answered, f"the sub-controller never answered step {key} after the flood"

        flood(10)  # warm-up: DDS buffers and the allocator settle
        taken_up_to(1)
        wait_for(lambda: log.read_text().count("exceeds the") >= 2, 30, "the rejections to be logged", sup)
        before = rss_mib(pid)
        flood(60)  # 60 x (3 + 4) MiB = 420 MiB offered
        taken_up_to(2)
        after = rss_mib(pid)
        sup.poll()
        assert sup.returncodes["sub"] is None, "the sub-controller died"
    finally:
        mw.shutdown()
        sup.stop()
    text = log.read_text()
    assert f"exceeds the {LIMIT} B message limit" in text and "/observation" in text and "sub_weights" in text
    assert "Traceback" not in text
    assert after - before < 40, f"RSS grew from {before:.0f} to {after:.0f} MiB while dropping 420 MiB of samples"


BURST = """
import os
import subprocess
import sys
from hdrqn_ros.nodes.process import return_large_buffers_to_the_os
if sys.argv[1] == "node":
    return_large_buffers_to_the_os()
def rss_mib():
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmRSS:")) / 1024
first = bytearray(8 << 20)
del first  # glibc's default now serves buffers under 8 MiB from the heap
before = rss_mib()
big, small = [], []
for _ in range(64):  # a burst of 4 MiB samples (as 64 taken at once), small objects allocated between them
    sample = bytearray(4 << 20)
    sample[::4096] = bytes(1024 * [1])  # every page touched
    big.append(sample)
    small.append(bytearray(4096))
del big
print(rss_mib() - before)
"""


def test_a_node_process_returns_a_burst_of_big_buffers_to_the_os():
    """What keeps test_oversized_... within its bound: after a burst of 256 MiB of 4 MiB buffers
    with small objects between them, a node process's RSS is back within a few MiB, where
    glibc's default keeps the burst in the heap."""
    def kept_mib(mode: str) -> float:
        run = subprocess.run([sys.executable, "-c", BURST, mode], capture_output=True, text=True, timeout=120,
                             env={k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_THRESHOLD_"})
        assert run.returncode == 0, run.stderr
        return float(run.stdout)

    assert kept_mib("node") < 16
    assert kept_mib("default") > 200  # what the node avoids (so the first assertion can fail)
