"""agents/policy.py: the hierarchical policy's rules on stub controllers whose LSTM states
count their steps (h += 1, c += 2 per act), so every zeroing and every read is visible."""
from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import torch

import hdrqn_ros.agents.policy as policy_module
from hdrqn_ros.agents.policy import HierarchicalPolicy
from hdrqn_ros.envs.domain import NO_SUBGOAL

N, S = 4, 3


class Counting:
    """A controller: fixed Q-values ``q`` (n,), state (h + 1, c + 2) per step; keeps its inputs."""

    def __init__(self, q, inference: bool = False):
        self.q = np.asarray(q, np.float32)
        self.inference = inference  # return inference tensors, like the nodes' ActingNetwork
        self.inputs = []

    def initial_state(self, batch_size):
        z = torch.zeros(batch_size, 256)
        return z, z.clone()

    def act(self, x, state):
        self.inputs.append(np.array(x, copy=True))
        with torch.inference_mode(self.inference):
            h, c = state
            return np.tile(self.q, (len(x), 1)), (h + 1, c + 2)


def _obs(n=N):
    return np.arange(n, dtype=np.uint8)[:, None, None, None] * np.ones((1, 44, 44, 3), np.uint8)


def _rows(*r):
    return np.array(r, bool)


def test_never_chooses_the_subgoal_it_stands_on():
    meta = Counting([0.0, 5.0, 1.0])  # greedy: subgoal 1
    pol = HierarchicalPolicy(N, Counting([0.0]), meta, "image")
    rng = np.random.default_rng(0)
    every = np.ones(N, bool)
    g, _ = pol.choose_subgoals(every, _obs(), 0.0, rng)
    assert g.tolist() == [1] * N  # nothing stood on yet: the greedy choice
    pol.end_options(every, np.array([1, 1, NO_SUBGOAL, 2]))
    g, _ = pol.choose_subgoals(every, _obs(), 0.0, rng)
    assert g.tolist() == [2, 2, 1, 1]  # the best other subgoal where it stands on 1
    chosen = np.array([pol.choose_subgoals(every, _obs(), 1.0, rng)[0] for _ in range(600)])
    assert not (chosen[:, :2] == 1).any() and not (chosen[:, 3] == 2).any()
    assert set(chosen[:, 2]) == {0, 1, 2}  # random and no restriction elsewhere
    pol.start_episodes(_rows(True, False, False, False))  # a new episode stands on nothing
    assert pol.place.tolist() == [NO_SUBGOAL, 1, NO_SUBGOAL, 2]


def test_new_options_zero_the_sub_state_of_their_rows_only():
    sub = Counting([0.0, 1.0])
    pol = HierarchicalPolicy(N, sub, Counting([1.0, 0.0, 0.0]), "image")
    rng = np.random.default_rng(0)
    for _ in range(3):
        pol.act(_obs(), 0.0, rng)
    assert pol.sub_state[0][:, 0].tolist() == [3] * N
    pol.choose_subgoals(_rows(True, False, True, False), _obs(), 0.0, rng)
    assert pol.sub_state[0][:, 0].tolist() == [0, 3, 0, 3] and pol.sub_state[1][:, 0].tolist() == [0, 6, 0, 6]
    assert pol.subgoal.tolist() == [0, -1, 0, -1]
    np.testing.assert_array_equal(sub.inputs[0], _obs())
    pol.act(_obs(), 0.0, rng)
    assert pol.sub_state[0][:, 0].tolist() == [1, 4, 1, 4]
    pol.start_options(_rows(False, True, False, False), np.array([2]))  # a subgoal chosen elsewhere
    assert pol.sub_state[0][:, 0].tolist() == [1, 0, 1, 4] and pol.subgoal.tolist() == [0, 2, 0, -1]


def test_meta_state_advances_in_the_deciding_rows_and_restarts_with_episodes():
    meta = Counting([1.0, 0.0, 0.0])
    pol = HierarchicalPolicy(N, Counting([0.0]), meta, "image")
    rng = np.random.default_rng(0)
    pol.choose_subgoals(np.ones(N, bool), _obs(), 0.0, rng)
    _, x = pol.choose_subgoals(_rows(False, True, False, True), _obs(), 0.0, rng)
    np.testing.assert_array_equal(x, _obs()[[1, 3]])  # the meta inputs of the deciding rows
    assert pol.meta_state[0][:, 0].tolist() == [1, 2, 1, 2]
    pol.start_episodes(_rows(False, False, False, True))
    assert pol.meta_state[0][:, 0].tolist() == [1, 2, 1, 0] and pol.sub_state[0][:, 0].tolist() == [0] * N


def test_hdrqn_v2_meta_input_is_the_sub_c_state_at_option_ends():
    for meta_state, per_step in (("c", 2), ("h", 1)):
        meta = Counting([1.0, 0.0, 0.0])
        pol = HierarchicalPolicy(N, Counting([0.0]), meta, "state", meta_state=meta_state)
        rng = np.random.default_rng(0)
        every = np.ones(N, bool)
        _, x = pol.choose_subgoals(every, None, 0.0, rng)
        np.testing.assert_array_equal(x, 0.0)  # an episode's first decision sees zeros
        for _ in range(3):
            pol.act(_obs(), 0.0, rng)
        ended = _rows(False, True, True, False)
        pol.end_options(ended, np.full(N, NO_SUBGOAL))
        assert pol.last_sub_state[:, 0].tolist() == [0, 3 * per_step, 3 * per_step, 0]
        after = pol.meta_input_after(_obs())
        np.testing.assert_array_equal(after, pol.last_sub_state)
        _, x = pol.choose_subgoals(ended, None, 0.0, rng)
        np.testing.assert_array_equal(x, np.full((2, 256), 3.0 * per_step))
        np.testing.assert_array_equal(meta.inputs[-1], x)
        pol.act(_obs(), 0.0, rng)  # the new options' sub state restarted, the others did not
        assert pol.sub_end_state()[:, 0].tolist() == [4 * per_step, per_step, per_step, 4 * per_step]
        pol.start_episodes(_rows(True, True, False, False))
        assert pol.last_sub_state[:, 0].tolist() == [0, 0, 3 * per_step, 0]
        pol.end_options(_rows(False, False, False, True), np.full(N, NO_SUBGOAL), np.full((1, 256), 7.0))
        assert pol.last_sub_state[:, 0].tolist() == [0, 0, 3 * per_step, 7]  # a state heard from elsewhere
        np.testing.assert_array_equal(after[:, 0], [0, 3 * per_step, 3 * per_step, 0])  # a copy


def test_one_environment_on_inference_tensors_like_the_nodes():
    sub, meta = Counting([0.0, 1.0], inference=True), Counting([0.0, 0.5, 1.0], inference=True)
    one = np.ones(1, bool)
    sub_pol = HierarchicalPolicy(1, sub, None, "state")
    meta_pol = HierarchicalPolicy(1, None, meta, "state")
    rng = np.random.default_rng(0)
    meta_pol.start_episodes(one)
    g, _ = meta_pol.choose_subgoals(one, None, 0.0, rng)
    sub_pol.start_episodes(one)
    sub_pol.start_options(one, g)
    for _ in range(2):
        assert sub_pol.act(_obs(1), 0.0, rng).tolist() == [1]
    meta_pol.end_options(one, np.array([2]), sub_pol.sub_end_state())
    sub_pol.start_options(one, meta_pol.choose_subgoals(one, None, 0.0, rng)[0])
    assert meta_pol.subgoal.tolist() == sub_pol.subgoal.tolist() == [1]  # 2 is where it stands
    assert meta.inputs[-1][0, 0] == 4.0 and sub_pol.sub_state[1][0, 0] == 0.0


def test_policy_imports_stay_in_the_agents_layer():
    allowed = ("numpy", "torch", "hdrqn_ros.envs", "hdrqn_ros.envs.critic", "hdrqn_ros.agents.specs",
               "hdrqn_ros.agents.policy", "__future__", "dataclasses", "typing")
    tree = ast.parse(Path(policy_module.__file__).read_text())
    imported = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    imported += [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert imported and all(any(m == a or m.startswith(a + ".") for a in allowed) for m in imported), imported


class CountingNumpy(Counting):
    """The same controller with numpy LSTM states, as an exported ONNX policy acts."""

    def initial_state(self, batch_size):
        return np.zeros((batch_size, 256), np.float32), np.zeros((batch_size, 256), np.float32)

    def act(self, x, state):
        self.inputs.append(np.array(x, copy=True))
        h, c = state
        return np.tile(self.q, (len(x), 1)), (h + 1, c + 2)


def _run_rules(controller_type) -> list:
    """One sequence of every rule on N environments (partial rows throughout); what it saw."""
    sub, meta = controller_type([0.0, 1.0]), controller_type([0.2, 0.5, 1.0])
    pol = HierarchicalPolicy(N, sub, meta, "state")
    rng = np.random.default_rng(4)
    seen = []
    for step in range(12):
        rows = np.arange(N) % 3 == step % 3
        if rows.any():
            pol.end_options(rows, np.where(rows, step % S, NO_SUBGOAL))
            seen.append(pol.choose_subgoals(rows, None, 0.3, rng))
        seen.append(pol.act(_obs(), 0.3, rng))
        pol.start_episodes(np.arange(N) == step % 5)
        seen += [np.asarray(part).copy() for part in (*pol.sub_state, *pol.meta_state)]
        seen += [pol.sub_end_state(), pol.sub_end_state(_rows(True, False, True, False)), pol.last_sub_state.copy()]
    return seen


def test_numpy_states_follow_the_same_rules_as_torch_states():
    """ONNX controllers carry numpy (h, c): every zeroing and read is the torch path's."""
    torch_seen, numpy_seen = _run_rules(Counting), _run_rules(CountingNumpy)
    assert len(torch_seen) == len(numpy_seen)
    for a, b in zip(torch_seen, numpy_seen):
        if isinstance(a, tuple):
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x, y)
        else:
            assert isinstance(b, np.ndarray)
            np.testing.assert_array_equal(a, b)


def test_the_policy_module_acts_on_numpy_states_without_importing_torch():
    code = textwrap.dedent("""
        import sys
        import numpy as np
        from hdrqn_ros.agents.policy import HierarchicalPolicy

        class Stub:
            def initial_state(self, n):
                return np.zeros((n, 256), np.float32), np.zeros((n, 256), np.float32)

            def act(self, x, state):
                return np.ones((len(x), 3), np.float32), (state[0] + 1, state[1] + 2)

        pol = HierarchicalPolicy(2, Stub(), Stub(), "state")
        rng = np.random.default_rng(0)
        pol.choose_subgoals(np.array([True, False]), None, 0.5, rng)
        pol.act(np.zeros((2, 44, 44, 6), np.uint8), 0.5, rng)
        pol.end_options(np.array([False, True]), np.array([0, 1]))
        pol.start_episodes(np.array([True, False]))
        assert pol.last_sub_state[1, 0] == 2.0 and pol.sub_state[0][:, 0].tolist() == [0.0, 1.0]
        print("torch" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[1],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["False"]
