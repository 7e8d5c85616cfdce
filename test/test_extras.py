"""A missing optional dependency (a pip extra) exits with code 2 and the command that installs
it, for every extra: deploy (hdrqn export, hdrqn robot --policy, a node's policy:=),
cluster (hdrqn experiment --ray), ros (hdrqn up). Each runs in a fresh Python
whose import of the extra's module fails, as on a machine without it."""
from __future__ import annotations

import subprocess
import sys

import pytest

from hdrqn_ros.extras import EXTRAS, MissingExtra, require


def run_without(module: str, code: str) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter where ``import module`` raises ImportError."""
    prelude = f"import sys; sys.modules[{module!r}] = None\n"
    return subprocess.run([sys.executable, "-c", prelude + code], capture_output=True, text=True, timeout=300)


def cli(*argv: str) -> str:
    return f"from hdrqn_ros.cli import main; sys.exit(main({list(argv)!r}))"


@pytest.mark.parametrize("module, argv, extra", [
    ("onnxruntime", ["export", "--checkpoint", "x.pt", "--out", "policy"], "deploy"),
    ("onnx", ["export", "--checkpoint", "x.pt", "--out", "policy", "--no-verify"], "deploy"),
    ("onnxruntime", ["robot", "--policy", "policy"], "deploy"),
    ("ray", ["experiment", "exp1", "--ray", "--episodes", "1"], "cluster"),
    ("rclpy", ["up", "--out", "run"], "ros"),
])
def test_cli_names_the_missing_extra(tmp_path, module, argv, extra):
    result = run_without(module, f"import os; os.chdir({str(tmp_path)!r})\n" + cli(*argv))
    assert result.returncode == 2, result.stderr
    assert f"pip install 'hdrqn_ros[{extra}]'" in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_a_node_acting_from_a_policy_without_onnxruntime_exits_2(tmp_path):
    code = ("from hdrqn_ros.nodes.controllers import main_sub\n"
            f"sys.exit(main_sub(['sub_controller', '--ros-args', '-p', 'policy:={tmp_path}']))")
    result = run_without("onnxruntime", code)
    assert result.returncode == 2, result.stderr
    assert "pip install 'hdrqn_ros[deploy]'" in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_require_passes_for_installed_extras_and_names_every_extra():
    require("deploy", "test")  # the test extra installs onnxruntime and onnx
    assert set(EXTRAS) == {"deploy", "cluster", "ros"}
    with pytest.raises(MissingExtra, match=r"pip install 'hdrqn_ros\[cluster\]'"):
        require("cluster", "test", ("no_such_module_here",))
