"""Which middleware runs a node, and bad input about it: rclpy asked for where it cannot be
imported, a Fast DDS profile that does not exist or parse, an unknown backend name."""
from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

from hdrqn_ros.middleware import BackendError, chosen_backend
from hdrqn_ros.middleware.network import (FASTDDS_LOOPBACK_PROFILE, SOCKET_BUFFER_BYTES, apply_rmw_network_defaults,
                                          check_user_fastdds_profile, fastdds_interface_profile)
from hdrqn_ros.middleware.port import ParameterError

from conftest import NO_RCLPY

WITHOUT_RCLPY = "import sys; sys.modules['rclpy'] = None  # import rclpy now fails, as without the wheels\n"


def run_python(code: str, env: dict | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


@NO_RCLPY
def test_auto_is_rclpy_where_it_imports(monkeypatch):
    monkeypatch.delenv("HDRQN_MIDDLEWARE", raising=False)
    assert chosen_backend() == "rclpy"
    assert chosen_backend("cyclone") == "cyclone"
    monkeypatch.setenv("HDRQN_MIDDLEWARE", "cyclone")
    assert chosen_backend() == "cyclone" and chosen_backend("auto") == "rclpy"


def test_unknown_backend_names_the_choices():
    with pytest.raises(BackendError, match="auto, rclpy, cyclone.*'zenoh'"):
        chosen_backend("zenoh")


def test_without_rclpy_auto_is_cyclone_and_rclpy_exits_2_naming_what_to_install(tmp_path):
    code = WITHOUT_RCLPY + f"""
from hdrqn_ros.middleware import chosen_backend
assert chosen_backend("auto") == "cyclone", chosen_backend("auto")
from hdrqn_ros.cli import main
rc = main(["up", "--middleware", "rclpy", "--out", {str(tmp_path / "run")!r}, "--episodes", "1"])
from hdrqn_ros.nodes.environment import main as env_main
sys.exit(10 * rc + env_main(["environment"]))
"""
    run = run_python(code, env={"HDRQN_MIDDLEWARE": "rclpy"})
    assert run.returncode == 22, run.stderr  # hdrqn up: 2, the node (HDRQN_MIDDLEWARE=rclpy): 2
    assert run.stderr.count("pip install 'hdrqn_ros[ros]'") == 2 and "Traceback" not in run.stderr, run.stderr
    assert not (tmp_path / "run").exists(), "nothing is started or written"


@pytest.mark.parametrize("content, problem", [(None, "cannot read"), ("<dds><profiles>", "not valid XML"),
                                              ("<CycloneDDS/>", "root element is <CycloneDDS>")])
def test_a_bad_fastdds_profile_is_named(tmp_path, content, problem):
    path = tmp_path / "profile.xml"
    if content is not None:
        path.write_text(content)
    with pytest.raises(ParameterError, match=f"FASTRTPS_DEFAULT_PROFILES_FILE={path}: .*{problem}"):
        check_user_fastdds_profile({"FASTRTPS_DEFAULT_PROFILES_FILE": str(path)})
    with pytest.raises(ParameterError, match=problem):
        apply_rmw_network_defaults(None, {"FASTRTPS_DEFAULT_PROFILES_FILE": str(path)})


def test_network_defaults_of_the_rmw():
    env: dict = {}
    assert apply_rmw_network_defaults(None, env) == "rmw_fastrtps_cpp on loopback only"
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(FASTDDS_LOOPBACK_PROFILE)
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SYSTEM_DEFAULT"
    assert apply_rmw_network_defaults(None, env) == "rmw_fastrtps_cpp on loopback only", "ours, inherited"
    own = {"FASTRTPS_DEFAULT_PROFILES_FILE": str(FASTDDS_LOOPBACK_PROFILE.parent / "port.py")}
    with pytest.raises(ParameterError, match="not valid XML"):
        apply_rmw_network_defaults(None, own)
    cyclone = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    assert "loopback" in apply_rmw_network_defaults(None, cyclone)
    assert '<NetworkInterface name="lo"/>' in cyclone["CYCLONEDDS_URI"]
    with pytest.raises(ParameterError, match="no-such-if0"):
        apply_rmw_network_defaults("no-such-if0", {})
    env = {}
    assert apply_rmw_network_defaults("lo", env) == "rmw_fastrtps_cpp on loopback only"


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


@NO_RCLPY
def test_nodes_and_hdrqn_up_exit_2_on_a_bad_profile(tmp_path):
    bad = tmp_path / "missing.xml"
    env = {"FASTRTPS_DEFAULT_PROFILES_FILE": str(bad), "HDRQN_MIDDLEWARE": "rclpy"}
    run = subprocess.run([sys.executable, "-m", "hdrqn_ros.nodes.critic"], capture_output=True, text=True,
                         timeout=120, env={**__import__("os").environ, **env})
    assert run.returncode == 2 and str(bad) in run.stderr and "Traceback" not in run.stderr, run.stderr
    up = run_python(f"""
import sys
from hdrqn_ros.cli import main
sys.exit(main(["up", "--out", {str(tmp_path / "run")!r}, "--episodes", "1"]))
""", env=env)
    assert up.returncode == 2 and str(bad) in up.stderr, up.stderr


def test_cyclone_names_an_interface_that_does_not_exist():
    from hdrqn_ros.middleware.cyclone import CycloneMiddleware

    with pytest.raises(ParameterError, match="dds_interface 'no-such-if0'"):
        CycloneMiddleware([], interface="no-such-if0")
