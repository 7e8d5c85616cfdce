"""docs/topics.md's parameter tables are the nodes' declarations (generated; this fails when a
parameter, default, range, rule or live flag changes in code and not in the docs)."""
from __future__ import annotations

import pytest

pytest.importorskip("rclpy", reason="ROS 2 Jazzy (rclpy) is not installed here")

from hdrqn_ros.nodes import parameter_tables  # noqa: E402
from hdrqn_ros.nodes.parameters import Param  # noqa: E402


def test_docs_topics_tables_match_the_declarations():
    text = parameter_tables.TOPICS_MD.read_text(encoding="utf-8")
    assert parameter_tables.rewritten(text) == text, \
        "docs/topics.md's parameter tables are stale: run python -m hdrqn_ros.nodes.parameter_tables"


def test_a_changed_declaration_shows_in_the_tables(monkeypatch):
    """The check can fail: a default, a range and a live flag changed in code change the text."""
    before = parameter_tables.render()
    critic = parameter_tables.importlib.import_module("hdrqn_ros.nodes.critic")
    changed = dict(critic.PARAMETERS, option_timeout=Param(1.0, "changed", live=False, low=0.0, high=5.0))
    monkeypatch.setattr(critic, "PARAMETERS", changed)
    after = parameter_tables.render()
    assert before != after
    assert "| `option_timeout` | float | `1.0` | 0..5 |  | changed |" in after


def test_every_node_executable_has_a_table():
    tables = parameter_tables.node_parameters()
    assert set(tables) == set(parameter_tables.NODES)
    assert all(tables[name][1] for name in tables)
