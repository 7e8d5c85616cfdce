"""A node's DDS traffic stays on loopback by default (rclpy, Fast DDS).

Everything runs inside a network namespace the test makes, ``hdrqn-lo-<pid>``: ``lo`` up
and one more interface, ``hq<pid>d``, with the private address ``10.213.0.1/24`` and the
default route through it, so a node that is *not* loopback-only sends its datagrams (SPDP
multicast to 239.255.0.1, unicast to other addresses) out of ``hq<pid>d``. That interface
is a ``dummy`` where the kernel has the dummy driver, else a veth pair whose two ends both
live in the namespace. Either way the namespace has no link to the outside, so nothing a
test runs here can reach a real network, and deleting the namespace removes it all. IPv6
is switched off in the namespace only (the kernel's own neighbour discovery would
otherwise put frames on the interface that no node sent).

A small helper process in the namespace captures with raw ``AF_PACKET`` sockets
(``ETH_P_ALL``) bound to ``hq<pid>d`` and to ``lo``: it counts every frame in either
direction and records the destination address:port of each IPv4 UDP datagram, and prints
the tally as JSON when its stdin closes (after draining what the kernel queued).

* Positive: a talker publishing a 44x44 ``sensor_msgs/Image`` and a listener that must
  receive and check N of them run with our defaults. The capture must see zero frames on
  ``hq<pid>d`` (and none dropped), while it saw the nodes' UDP traffic on ``lo``.
* Control (the check can fail): the same talker with ``HDRQN_DDS_INTERFACE=hq<pid>d`` in
  its environment: the capture must see its UDP datagrams on ``hq<pid>d`` (discovery
  multicast to 239.255.0.1:7400+250*domain), so a leak would have been caught.

Skips (with the reason) where the namespace cannot be made: not root, no ``ip``, no
``CAP_SYS_ADMIN``/``CAP_NET_ADMIN``; and (test/conftest.py) where rclpy cannot be imported.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SUBNET = "10.213.0"
WANT = 10
"""Images the listener must receive: proof that traffic flowed while the capture ran."""
TOPIC = "/hdrqn_loopback/image"
IMAGE_BYTES = 44 * 44 * 3
DISCOVERY_GROUP = "239.255.0.1"
NETWORK_ENV = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_AUTOMATIC_DISCOVERY_RANGE",
               "ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY", "HDRQN_DDS_INTERFACE", "RMW_IMPLEMENTATION", "ROS_DOMAIN_ID")
"""Cleared for every node process, so only our defaults (or the interface the control test
names) decide where traffic goes."""

CAPTURE = r"""
import json, select, socket, struct, sys, time
ETH_P_ALL, SOL_PACKET, PACKET_STATISTICS, PACKET_OUTGOING = 0x0003, 263, 6, 4
socks, stats = {}, {}
for name in sys.argv[1].split(","):
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)  # receives nothing until bound
    try:
        sock.setsockopt(socket.SOL_SOCKET, 33, 8 << 20)  # SO_RCVBUFFORCE (root)
    except OSError:
        pass
    sock.bind((name, ETH_P_ALL))
    socks[sock] = name
    stats[name] = {"frames": 0, "outgoing": 0, "ethertypes": {}, "udp": {}, "ip_protocols": {}, "udp_frames": 0,
                   "udp_bytes": 0, "drops": 0}

def take(sock):
    frame, addr = sock.recvfrom(65535)
    st = stats[socks[sock]]
    st["frames"] += 1
    st["outgoing"] += addr[2] == PACKET_OUTGOING
    ethertype = "%04x" % int.from_bytes(frame[12:14], "big")
    st["ethertypes"][ethertype] = st["ethertypes"].get(ethertype, 0) + 1
    if ethertype == "0800" and len(frame) >= 34:
        st["ip_protocols"][frame[23]] = st["ip_protocols"].get(frame[23], 0) + 1
    if ethertype == "0800" and len(frame) >= 34 and frame[23] == 17:
        udp = 14 + (frame[14] & 0x0F) * 4
        dst = "%s:%d" % (socket.inet_ntoa(frame[30:34]), int.from_bytes(frame[udp + 2:udp + 4], "big"))
        st["udp_frames"] += 1
        st["udp_bytes"] += len(frame) - udp - 8
        st["udp"][dst] = st["udp"].get(dst, 0) + 1

print("ready", flush=True)
deadline, stopped = time.monotonic() + float(sys.argv[2]), False
while not stopped:
    ready = select.select([*socks, sys.stdin], [], [], max(0.0, deadline - time.monotonic()))[0]
    if not ready:  # the time limit: the test never stopped it (the report says so)
        break
    stopped = sys.stdin in ready  # stdin closed: drain and stop
    for sock in ready:
        if sock in socks:
            take(sock)
for sock in socks:  # what the kernel had queued before the stop
    sock.setblocking(False)
    while True:
        try:
            take(sock)
        except BlockingIOError:
            break
    stats[socks[sock]]["drops"] = struct.unpack("II", sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))[1]
print(json.dumps({"stopped": stopped, "interfaces": stats}), flush=True)
"""

NODE = r"""
import faulthandler, json, signal, sys
faulthandler.register(signal.SIGUSR1)  # the test asks for every thread's stack when the node hangs
# Ctrl-C stops the talker, even where the test runs with SIGINT ignored (a background job of a
# non-interactive shell), which Python would otherwise keep
signal.signal(signal.SIGINT, signal.default_int_handler)
import os, time
import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from hdrqn_ros.dds import INTERFACE_ENV, apply_rmw_network_defaults
from hdrqn_ros.nodes.qos import DEFAULT_QOS
from hdrqn_ros.nodes.ros_messages import ROS_MESSAGES, interface_class
from hdrqn_ros.protocol import wire
role, want, limit_s = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
network = apply_rmw_network_defaults(os.environ.get(INTERFACE_ENV) or None)
rclpy.init(args=sys.argv, signal_handler_options=SignalHandlerOptions.NO)
node = rclpy.create_node(role)
executor = SingleThreadedExecutor()
executor.add_node(node)
pixels = np.arange(44 * 44 * 3, dtype=np.uint32).astype(np.uint8).reshape(44, 44, 3)
sent, got = [0], []
try:
    if role == "talker":
        pub = node.create_publisher(interface_class(wire.IMAGE), sys.argv[4], DEFAULT_QOS)
        def tick():
            sent[0] += 1
            pub.publish(wire.make_image(ROS_MESSAGES, sent[0] * 1_000_000, pixels, "camera"))
        node.create_timer(0.05, tick)
    else:
        def on_image(msg):
            key, image = wire.read_image(msg, 44, 44)
            got.append(key if (image == pixels).all() else -1)
        node.create_subscription(interface_class(wire.IMAGE), sys.argv[4], on_image, DEFAULT_QOS)
    end = time.monotonic() + limit_s
    while time.monotonic() < end and not (role == "listener" and len(got) >= want):
        executor.spin_once(timeout_sec=0.05)
except KeyboardInterrupt:  # the test stops the talker with SIGINT
    pass
finally:
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()
print(json.dumps({"role": role, "network": network, "sent": sent[0], "got": got}),
      flush=True)
"""


@dataclass
class Netns:
    name: str
    ifname: str      # the non-loopback interface a leak would use
    kind: str        # "dummy" or "veth"

    def ip(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=20)

    def must(self, *args: str) -> None:
        run = self.ip(*args)
        if run.returncode != 0:
            raise OSError(f"ip {' '.join(args)}: {run.stderr.strip() or run.returncode}")

    def exec_argv(self, *argv: str) -> list[str]:
        return ["ip", "netns", "exec", self.name, *argv]


def make_netns(tag: str) -> Netns:
    net = Netns(f"hdrqn-lo-{tag}", f"hq{tag}d", "dummy")
    net.must("netns", "add", net.name)
    try:
        net.must("-n", net.name, "link", "set", "lo", "up")
        # IPv6 off in this namespace only: no router solicitations, DAD or MLD on the interface
        subprocess.run(net.exec_argv(sys.executable, "-c", "import pathlib\n"
                                     "for c in ('all', 'default'):\n"
                                     "    p = pathlib.Path(f'/proc/sys/net/ipv6/conf/{c}/disable_ipv6')\n"
                                     "    p.exists() and p.write_text('1')"), check=True, timeout=20,
                       capture_output=True)
        if net.ip("-n", net.name, "link", "add", net.ifname, "type", "dummy").returncode != 0:
            # no dummy driver: a veth pair with both ends in the namespace (its peer only listens)
            net.kind = "veth"
            net.must("-n", net.name, "link", "add", net.ifname, "type", "veth", "peer", "name", f"hq{tag}p")
            net.must("-n", net.name, "link", "set", f"hq{tag}p", "up")
        net.must("-n", net.name, "link", "set", net.ifname, "multicast", "on", "up")
        net.must("-n", net.name, "addr", "add", f"{SUBNET}.1/24", "dev", net.ifname)
        net.must("-n", net.name, "route", "add", "default", "via", f"{SUBNET}.254", "dev", net.ifname)
    except BaseException:
        net.ip("netns", "del", net.name)
        raise
    return net


@pytest.fixture(scope="module")
def netns():
    """The namespace of the module doc (one per module); skips where it cannot be made."""
    if os.geteuid() != 0:
        pytest.skip("network namespaces need root")
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2)")
    tag = str(os.getpid())
    try:
        net = make_netns(tag)
    except (OSError, subprocess.SubprocessError) as exc:
        pytest.skip(f"cannot create the test's network namespace and interface: {exc}")
    try:
        yield net
    finally:
        net.ip("netns", "del", net.name)
    assert net.name not in net.ip("netns", "list").stdout.split(), "namespace left over"






def kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait(timeout=10)


class Capture:
    """The AF_PACKET helper in the namespace: started before the nodes, stopped after them."""

    def __init__(self, net: Netns, interfaces: list[str], limit_s: float = 400.0):
        self.proc = subprocess.Popen(net.exec_argv(sys.executable, "-c", CAPTURE, ",".join(interfaces), str(limit_s)),
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = self.proc.stdout.readline()
        if line.strip() != "ready":
            kill(self.proc)
            raise AssertionError(f"the capture did not start: {line!r} {self.proc.stderr.read()[-2000:]}")

    def stop(self) -> dict:
        try:
            out, err = self.proc.communicate(timeout=15)  # closes stdin: the helper drains and reports
        finally:
            kill(self.proc)
        assert self.proc.returncode == 0, f"capture failed ({self.proc.returncode}): {err[-2000:]}"
        tally = json.loads(out.strip().splitlines()[-1])
        assert tally["stopped"], "the capture ran out of time before the test stopped it"
        return tally["interfaces"]


def summary(stats: dict) -> str:
    """One interface's tally, short: frame counts and the UDP destinations (ports of 127.0.0.1 folded)."""
    udp = {dst: n for dst, n in stats["udp"].items() if not dst.startswith("127.0.0.1:")}
    local = [dst for dst in stats["udp"] if dst.startswith("127.0.0.1:")]
    if local:
        udp[f"127.0.0.1 ({len(local)} ports)"] = sum(stats["udp"][dst] for dst in local)
    return (f"{stats['frames']} frames ({stats['outgoing']} outgoing, {stats['drops']} dropped), ethertypes "
            f"{stats['ethertypes']}, IPv4 protocols {stats['ip_protocols']}, "
            f"{stats['udp_frames']} UDP ({stats['udp_bytes']} B) to {udp}")


def start_node(net: Netns, domain_id: int, role: str, limit_s: float,
               interface: str | None = None) -> subprocess.Popen:
    """A talker or listener in the namespace; ``interface``: its ``HDRQN_DDS_INTERFACE``."""
    env = {k: v for k, v in os.environ.items() if k not in NETWORK_ENV}
    env.update(ROS_DOMAIN_ID=str(domain_id), **({"HDRQN_DDS_INTERFACE": interface} if interface else {}))
    argv = [sys.executable, "-c", NODE, role, str(WANT), str(limit_s), TOPIC]
    return subprocess.Popen(net.exec_argv(*argv), env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def report(proc: subprocess.Popen, timeout: float) -> dict:
    """The node's JSON line (after it exits); fails with its stderr if it did not exit cleanly,
    or with its threads' stacks if it does not exit within ``timeout``."""
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(2.0)  # the stacks' dump is written (nothing to wait on: the node is stuck)
        kill(proc)
        out, err = proc.communicate()
        raise AssertionError(f"node did not exit within {timeout} s; its stacks:\n{err[-6000:]}") from None
    assert proc.returncode == 0, f"node exited with {proc.returncode}:\n{err[-3000:]}"
    return json.loads(out.strip().splitlines()[-1])


def stop_talker(proc: subprocess.Popen) -> dict:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    return report(proc, timeout=60)


LOOPBACK_ONLY = "rmw_fastrtps_cpp on loopback only"
"""What :func:`hdrqn_ros.dds.apply_rmw_network_defaults` says of the network by default."""


def test_nodes_talk_over_loopback_only(netns, domain):
    """A talker and a listener exchange images: zero frames on the namespace's other interface."""
    capture = Capture(netns, [netns.ifname, "lo"])
    listener = talker = None
    try:
        # deadlines for a loaded machine: the listener stops as soon as it has its images, the
        # talker when the test stops it
        listener = start_node(netns, domain, "listener", 120.0)
        talker = start_node(netns, domain, "talker", 180.0)
        heard = report(listener, timeout=150)
        said = stop_talker(talker)
    finally:
        for proc in (listener, talker):
            if proc is not None:
                kill(proc)
        seen = capture.stop()
    print(f"talker -> listener on {netns.kind} {netns.ifname}: sent {said['sent']}, "
          f"got {len(heard['got'])}; {netns.ifname}: {summary(seen[netns.ifname])}; lo: {summary(seen['lo'])}")
    leak = seen[netns.ifname]
    assert leak["frames"] == 0, f"traffic left loopback on {netns.ifname}: {summary(leak)}"
    assert leak["drops"] == 0, f"the capture dropped frames on {netns.ifname}: {summary(leak)}"
    assert len(heard["got"]) >= WANT and -1 not in heard["got"], f"listener got {heard['got']}"
    assert heard["got"] == sorted(heard["got"]), "images out of order"
    assert said["network"] == heard["network"] == LOOPBACK_ONLY
    # the same capture saw the nodes' datagrams on lo (unicast to 127.0.0.1): it was looking
    lo = seen["lo"]
    assert all(dst.startswith(("127.", "239.")) for dst in lo["udp"]), lo["udp"]
    assert lo["udp_bytes"] >= WANT * IMAGE_BYTES, f"the images' bytes were not seen on lo: {summary(lo)}"


def test_control_talker_on_interface_is_captured(netns, domain):
    """The same talker told to use the namespace's interface: the capture must see its datagrams."""
    capture = Capture(netns, [netns.ifname])
    talker = None
    try:
        talker = start_node(netns, domain, "talker", 2.5, interface=netns.ifname)
        said = report(talker, timeout=120)
    finally:
        if talker is not None:
            kill(talker)
        seen = capture.stop()[netns.ifname]
    print(f"control on {netns.kind} {netns.ifname}: {summary(seen)}")
    assert netns.ifname in said["network"], said
    assert seen["udp_frames"] > 0, f"the capture saw no UDP datagram on {netns.ifname}: {seen}"
    dsts = {dst.rpartition(":")[0] for dst in seen["udp"]}
    assert all(d == DISCOVERY_GROUP or d.startswith(f"{SUBNET}.") for d in dsts), seen["udp"]
    # SPDP discovery: the multicast group on the domain's discovery port (7400 + 250 * domain)
    assert f"{DISCOVERY_GROUP}:{7400 + 250 * domain}" in seen["udp"], seen["udp"]
