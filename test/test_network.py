"""The network settings of the rclpy processes (:mod:`hdrqn_ros.dds`), and rclpy missing.

DDS stays on loopback unless ``HDRQN_DDS_INTERFACE`` names an interface (``hdrqn up
--interface`` sets it for its nodes); a user's Fast DDS profile is checked up front; another
RMW keeps its own settings; a bad setting exits 2 naming it. Where rclpy cannot be imported,
``hdrqn up``/``robot``/``bag play`` and the node executables exit 2 naming what to install,
while the in-process commands work without any ROS.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from hdrqn_ros import dds
from hdrqn_ros.cli import main as hdrqn
from hdrqn_ros.dds import (FASTDDS_LOOPBACK_PROFILE, INTERFACE_ENV, SOCKET_BUFFER_BYTES, NetworkConfigError,
                           apply_rmw_network_defaults, check_user_fastdds_profile, fastdds_interface_profile,
                           interface_address)
from hdrqn_ros.nodes.ros_packages import RosNotInstalled, require_rclpy

from conftest import NEEDS_RCLPY

WITHOUT_ROS = """import importlib.machinery
tried = []  # the ROS packages something looked for
_find_spec = importlib.machinery.PathFinder.find_spec
def find_spec(name, path=None, target=None):  # no ROS package is found, as on a machine without ROS
    top = name.partition(".")[0]
    if top.startswith(("rcl", "rmw", "rosidl", "ament", "launch", "tf2")) or \\
            top.endswith(("_msgs", "_srvs", "_interfaces")):
        tried.append(name)
        return None
    return _find_spec(name, path, target)
importlib.machinery.PathFinder.find_spec = staticmethod(find_spec)
"""
"""Python source after which no ROS package can be found (``importlib.util.find_spec`` gives
None, an import raises ``ModuleNotFoundError``), as where none is installed; ``tried`` lists
the lookups."""
INSTALL = "pip install 'hdrqn_ros[ros]'"
PROFILE_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"


def run_python(code: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


# -- rclpy missing ------------------------------------------------------------------------------
@NEEDS_RCLPY
def test_require_rclpy_passes_where_it_imports():
    require_rclpy()


def test_require_rclpy_names_what_to_install(monkeypatch):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "rclpy" else find_spec(name, *a))
    with pytest.raises(RosNotInstalled) as err:
        require_rclpy()
    for what in (INSTALL, "Linux x86-64", "CPython 3.10-3.13", "source /opt/ros/jazzy/setup.bash", "RoboStack",
                 "macOS"):
        assert what in str(err.value), what


def test_without_ros_the_node_commands_and_executables_exit_2_with_one_line_naming_what_to_install(tmp_path):
    """``hdrqn up``, ``hdrqn robot``, ``hdrqn bag play`` and a node executable (``ros2 run
    hdrqn_ros critic``): exit 2, one line, no traceback, nothing started or written."""
    code = WITHOUT_ROS + f"""
import contextlib, io, json
from hdrqn_ros.cli import main
from hdrqn_ros.nodes.executables import critic
out = {{}}
for name, run in (("up", lambda: main(["up", "--out", {str(tmp_path / "run")!r}, "--episodes", "1"])),
                  ("robot", lambda: main(["robot", "--checkpoint", "x.pt"])),
                  ("bag play", lambda: main(["bag", "play", {str(tmp_path / "bag")!r}])),
                  ("critic", critic)):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = run()
    out[name] = [rc, err.getvalue()]
print(json.dumps(out))
"""
    run = run_python(code)
    assert run.returncode == 0, run.stderr
    results = json.loads(run.stdout)
    assert set(results) == {"up", "robot", "bag play", "critic"}
    for command, (rc, err) in results.items():
        assert rc == 2 and INSTALL in err and "Traceback" not in err, (command, err)
        assert len(err.strip().splitlines()) == 1, (command, err)
    assert "rclpy (ROS 2 Jazzy)" in results["up"][1]
    assert "critic needs the ROS package" in results["critic"][1]
    assert not (tmp_path / "run").exists(), "nothing is started or written"


def test_without_ros_train_eval_bag_info_export_and_experiment_work(tmp_path):
    """The in-process commands import no ROS package: train, eval (recording a bag), bag info,
    export and experiment run where rclpy cannot be imported."""
    run, bag, policy = tmp_path / "run", tmp_path / "bag", tmp_path / "policy"
    checkpoint = str(run / "checkpoints" / "last.pt")
    code = WITHOUT_ROS + f"""
from hdrqn_ros.cli import main
rcs = [main(["train", "--algo", "dqn", "--episodes", "2", "--out", {str(run)!r}, "--no-progress",
             "--set", "eval_episodes=1", "--set", "num_envs=1"]),
       main(["eval", "--checkpoint", {checkpoint!r}, "--episodes", "1", "--record", {str(bag)!r}]),
       main(["bag", "info", {str(bag)!r}]),
       main(["export", "--checkpoint", {checkpoint!r}, "--out", {str(policy)!r}]),
       main(["experiment", "exp3-gridworld-2goals", "--algos", "dqn", "--seeds", "0", "--dry-run",
             "--out", {str(tmp_path / "exp")!r}])]
print("RCS", rcs, "TRIED", sorted(set(tried)))
"""
    result = run_python(code, timeout=600)
    assert result.returncode == 0, result.stderr
    assert "RCS [0, 0, 0, 0, 0] TRIED []" in result.stdout, result.stdout + result.stderr
    assert (policy / "policy.json").exists()


# -- the RMW's network settings ---------------------------------------------------------------------
@pytest.mark.parametrize("content, problem", [(None, "cannot read"), ("<dds><profiles>", "not valid XML"),
                                              ("<config/>", "root element is <config>")])
def test_a_bad_fastdds_profile_is_named(tmp_path, content, problem):
    path = tmp_path / "profile.xml"
    if content is not None:
        path.write_text(content)
    with pytest.raises(NetworkConfigError, match=f"{PROFILE_VARIABLE}={path}: .*{problem}"):
        check_user_fastdds_profile({PROFILE_VARIABLE: str(path)})
    with pytest.raises(NetworkConfigError, match=problem):
        apply_rmw_network_defaults(None, {PROFILE_VARIABLE: str(path)})


def test_loopback_by_default_and_a_users_profile_is_kept(tmp_path):
    env: dict = {}
    assert apply_rmw_network_defaults(None, env) == "rmw_fastrtps_cpp on loopback only"
    assert env[PROFILE_VARIABLE] == env["FASTDDS_DEFAULT_PROFILES_FILE"] == str(FASTDDS_LOOPBACK_PROFILE)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert apply_rmw_network_defaults(None, env) == "rmw_fastrtps_cpp on loopback only", "ours, inherited"
    env = {}
    assert apply_rmw_network_defaults("lo", env) == "rmw_fastrtps_cpp on loopback only"
    assert env[PROFILE_VARIABLE] == str(FASTDDS_LOOPBACK_PROFILE)
    own = tmp_path / "own.xml"
    own.write_text('<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"><profiles/></dds>')
    env = {PROFILE_VARIABLE: str(own)}
    assert apply_rmw_network_defaults(None, env) == f"rmw_fastrtps_cpp with the user's profile {own}"
    assert env == {PROFILE_VARIABLE: str(own)}, "the user's profile is left as it is"
    with pytest.raises(NetworkConfigError, match="not valid XML"):
        apply_rmw_network_defaults(None, {PROFILE_VARIABLE: str(Path(dds.__file__))})


def test_another_rmw_keeps_its_own_settings():
    other = {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"}
    assert apply_rmw_network_defaults(None, other) == \
        "rmw_zenoh_cpp with its own network settings (the loopback-only default covers Fast DDS)"
    assert other == {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp"}


def test_an_interface_gets_a_profile_of_its_own(monkeypatch):
    """``HDRQN_DDS_INTERFACE``: Fast DDS on that interface's address only, discovering by
    multicast on it, even where a loopback-only parent set the range."""
    assert interface_address("lo") == "127.0.0.1"
    monkeypatch.setattr(dds, "interface_address", lambda interface: {"eth9": "192.0.2.7"}[interface])
    env = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT", PROFILE_VARIABLE: str(FASTDDS_LOOPBACK_PROFILE)}
    assert apply_rmw_network_defaults("eth9", env) == "rmw_fastrtps_cpp on eth9 (192.0.2.7)"
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    assert env[PROFILE_VARIABLE] == env["FASTDDS_DEFAULT_PROFILES_FILE"] != str(FASTDDS_LOOPBACK_PROFILE)
    assert Path(env[PROFILE_VARIABLE]).read_text() == fastdds_interface_profile("192.0.2.7")


def test_an_interface_without_ipv4_is_named():
    for ask in (lambda: interface_address("no-such-if0"), lambda: apply_rmw_network_defaults("no-such-if0", {})):
        with pytest.raises(NetworkConfigError, match=f"{INTERFACE_ENV}='no-such-if0': no IPv4 address"):
            ask()


def test_both_fastdds_profiles_give_udp_the_socket_buffers_batches_need():
    """Batched groups' samples are several 64 KB datagrams: with the system's default
    buffers their fragments overflow and wait for heartbeats (bench: 125 vs 2,158 env steps/s
    at num_envs 16). The loopback profile and the interface profile set both sizes."""
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    for text in (FASTDDS_LOOPBACK_PROFILE.read_text(), fastdds_interface_profile("127.213.0.9")):
        transports = ET.fromstring(text).findall(".//f:transport_descriptor", ns)
        assert [t.findtext("f:type", namespaces=ns) for t in transports] == ["UDPv4"]
        for field in ("sendBufferSize", "receiveBufferSize"):
            assert int(transports[0].findtext(f"f:{field}", namespaces=ns)) == SOCKET_BUFFER_BYTES, field
    assert "<address>127.213.0.9</address>" in fastdds_interface_profile("127.213.0.9")


# -- hdrqn up ---------------------------------------------------------------------------------------
class Started(Exception):
    """Raised where ``hdrqn up`` would start its node processes."""


def up(argv: list[str], monkeypatch) -> tuple[int | None, str, dict | None]:
    """``hdrqn up ARGV`` in this process, stopped where it would start the nodes: (exit code
    or None where it got that far, stderr, the environment it gives the nodes)."""
    import hdrqn_ros.supervisor

    given = {}

    def supervisor(specs, env=None, **kwargs):
        given.update(env or {})
        raise Started()

    monkeypatch.setattr(hdrqn_ros.supervisor, "Supervisor", supervisor)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            rc = hdrqn(["up", *argv])
        except Started:
            return None, err.getvalue(), given
    return rc, err.getvalue(), None


@NEEDS_RCLPY
def test_hdrqn_up_gives_its_nodes_the_interface(tmp_path, monkeypatch):
    monkeypatch.delenv(INTERFACE_ENV, raising=False)
    rc, err, env = up(["--out", str(tmp_path / "run"), "--episodes", "1", "--interface", "lo"], monkeypatch)
    assert rc is None and env == {INTERFACE_ENV: "lo"}, err
    rc, err, env = up(["--out", str(tmp_path / "run2"), "--episodes", "1", "--domain-id", "7"], monkeypatch)
    assert rc is None and env == {"ROS_DOMAIN_ID": "7"}, err


@NEEDS_RCLPY
@pytest.mark.parametrize("argv, env, problem", [
    (["--interface", "no-such-if0"], {}, f"{INTERFACE_ENV}='no-such-if0': no IPv4 address"),
    ([], {PROFILE_VARIABLE: "/nonexistent/profile.xml"}, "/nonexistent/profile.xml: cannot read"),
])
def test_hdrqn_up_refuses_a_bad_network_setting_up_front(tmp_path, monkeypatch, argv, env, problem):
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    rc, err, started = up(["--out", str(tmp_path / "run"), "--episodes", "1", *argv], monkeypatch)
    assert rc == 2 and problem in err and started is None, err
    assert not (tmp_path / "run").exists(), "nothing is started or written"


# -- node processes -----------------------------------------------------------------------------------
@NEEDS_RCLPY
@pytest.mark.processes
@pytest.mark.parametrize("env, problem", [
    ({PROFILE_VARIABLE: "/nonexistent/profile.xml"}, "/nonexistent/profile.xml: cannot read"),
    ({INTERFACE_ENV: "no-such-if0"}, f"{INTERFACE_ENV}='no-such-if0': no IPv4 address"),
    ({"ROS_DOMAIN_ID": "x"}, "ROS_DOMAIN_ID must be an integer in 0..232"),
    ({"ROS_DOMAIN_ID": "300"}, "ROS_DOMAIN_ID must be an integer in 0..232"),
])
def test_a_node_exits_2_naming_a_bad_network_setting(env, problem):
    """A node process (``ros2 run hdrqn_ros critic``) with a setting it cannot use: one
    line naming it, exit 2, no traceback; it never joins DDS."""
    run = subprocess.run([sys.executable, "-m", "hdrqn_ros.nodes.critic"], capture_output=True, text=True,
                         timeout=120, env={**os.environ, **env})
    assert run.returncode == 2 and problem in run.stderr and "Traceback" not in run.stderr, run.stderr
