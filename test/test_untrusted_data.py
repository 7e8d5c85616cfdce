"""No code runs from data: a malicious pickle fed through every loading path is refused.

The payload's ``__reduce__`` would create a marker file when unpickled; every path must
reject it with a clear error and leave no marker: checkpoints (``torch.load`` with
``weights_only=True``), weights on the wire (safetensors), bags (CDR in MCAP), configs (YAML
safe loading).
"""
from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from hdrqn_ros.agents.algorithms import make_network
from hdrqn_ros.agents.weights import WeightsError, load_weights
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint


class Exploit:
    """Unpickling this runs ``os.system("touch <marker>")``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture
def payloads(tmp_path):
    marker = tmp_path / "PWNED"
    raw = pickle.dumps({"format": "hdrqn_ros-checkpoint", "agent": Exploit(marker)})
    torch_file = tmp_path / "evil.pt"
    torch.save({"format": "hdrqn_ros-checkpoint", "version": 1, "agent": Exploit(marker)}, torch_file)
    raw_file = tmp_path / "evil.pkl"
    raw_file.write_bytes(raw)
    pickle.loads(raw)  # the payload works: unpickling it does run code
    assert marker.exists()
    marker.unlink()
    return marker, raw, torch_file, raw_file


def cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hdrqn_ros.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


def test_checkpoints_refuse_pickled_code(payloads, tmp_path):
    marker, _, torch_file, raw_file = payloads
    for path in (torch_file, raw_file):
        with pytest.raises(CheckpointError, match="not a readable hdrqn_ros checkpoint"):
            load_checkpoint(path)
        r = cli("eval", "--checkpoint", path, "--episodes", "1")
        assert r.returncode == 2 and str(path) in r.stderr and "Traceback" not in r.stderr
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.pt").write_bytes(torch_file.read_bytes())
    r = cli("train", "--resume", "--episodes", "2", "--out", run, "--no-progress")
    assert r.returncode == 2 and "last.pt" in r.stderr
    node = subprocess.run([sys.executable, "-c", "import sys; from hdrqn_ros.nodes.controllers import main_sub; "
                           "sys.exit(main_sub())", "--ros-args", "-p", f"checkpoint:={torch_file}"],
                          capture_output=True, text=True, timeout=120,
                          env={**os.environ, "ROS_DOMAIN_ID": str(150 + os.getpid() % 50)})
    assert node.returncode == 2 and str(torch_file) in node.stderr and "Traceback" not in node.stderr
    assert not marker.exists()


def test_weights_on_the_wire_refuse_pickled_code(payloads):
    marker, raw, torch_file, _ = payloads
    net = make_network("hdrqn-v2", "sub", 4, 2)
    for data in (raw, torch_file.read_bytes()):
        with pytest.raises(WeightsError, match="not safetensors"):
            load_weights(net, data)
    assert not marker.exists()


def test_bags_refuse_pickled_code(payloads, tmp_path):
    marker, raw, _, _ = payloads
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag_0.mcap").write_bytes(raw)
    (bag / "metadata.yaml").write_bytes(raw)
    for args in (("bag", "info", bag), ("bag", "repair", bag), ("train", "--from-bag", bag, "--out", tmp_path / "o")):
        r = cli(*args)
        assert r.returncode == 2 and str(bag) in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)
    assert not marker.exists()


def test_configs_refuse_python_objects(payloads, tmp_path):
    marker = payloads[0]
    config = tmp_path / "evil.yaml"
    config.write_text(f"algo: !!python/object/apply:os.system ['touch {marker}']\n")
    r = cli("train", "--config", config, "--episodes", "1", "--out", tmp_path / "run")
    assert r.returncode == 2 and str(config) in r.stderr and "Traceback" not in r.stderr
    assert not marker.exists()
