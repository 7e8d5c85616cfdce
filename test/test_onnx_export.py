"""ONNX export and torch-free acting (issue 20 part B): the exported models compute what
the torch networks' ``act`` computes over whole gridworld episodes, the deploy module
never imports torch, and bad policy directories are refused with the file named."""
import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

import hdrqn_ros
from hdrqn_ros.agents.algorithms import ALGO_SPECS, make_network, stack_subgoal
from hdrqn_ros.config import build_config
from hdrqn_ros.deploy import OnnxPolicy, PolicyError, role_io
from hdrqn_ros.hashing import file_sha256
from hdrqn_ros.deploy import onnx_policy
from hdrqn_ros.deploy.onnx_agent import OnnxAgent
from hdrqn_ros.envs.registration import make_batch
from hdrqn_ros.training.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from hdrqn_ros.training.export import export_policy
from hdrqn_ros.training.learner import build_agent, load_trained_agent, play

ALGOS = ["hdrqn-v2", "hdrqn-v1", "hdqn", "drqn", "dqn"]
TOL = 1e-5
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Acting as the nodes act (``ActingNetwork``: 1 thread); batch-1 convs on a loaded
    2-core machine are ~20x slower with more threads."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _make_checkpoint(path: Path, algo: str, env: str, seed: int) -> None:
    """A checkpoint written by the package's own save function, of an agent whose every
    parameter (biases too: they start at zero) is moved off its initial value."""
    torch.manual_seed(seed)
    cfg = build_config([], algo=algo, env=env, seed=seed)
    agent = build_agent(cfg)
    with torch.no_grad():
        for controller in agent.controllers:
            for p in controller.online.parameters():
                p.add_(0.05 * torch.randn_like(p))
    save_checkpoint(path, config=cfg.model_dump(), agent_state=agent.state_dict(),
                    progress={"episodes": 3, "env_steps": 120, "meta_begin": None})


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """{algo: (checkpoint path, policy dir)}; hDRQNv2 on four-rooms with 3 goals, the rest on the gridworld."""
    out = {}
    for k, algo in enumerate(ALGOS):
        env = "hdrqn/FourRooms-3Goals-v0" if algo == "hdrqn-v2" else "hdrqn/GridWorld-2Goals-v0"
        base = tmp_path_factory.mktemp(algo)
        ckpt = base / "run" / "checkpoints" / "last.pt"
        _make_checkpoint(ckpt, algo, env, seed=10 + k)
        out[algo] = ckpt, export_policy(ckpt, base / "policy")
    return out


def _torch_nets(ckpt: Path) -> dict:
    """The online networks as a controller node builds them (``ActingNetwork``)."""
    payload = load_checkpoint(ckpt)
    cfg = payload["config"]
    probe = make_batch(cfg["env"], 1)
    nets = {}
    for role in (("meta", "sub") if ALGO_SPECS[cfg["algo"]].hierarchical else ("sub",)):
        net = make_network(cfg["algo"], role, probe.num_actions, probe.num_subgoals)
        net.load_state_dict(payload["agent"][role]["online"])
        nets[role] = net.eval()
    return nets


class _Pair:
    """One controller acting twice per decision, torch and ONNX, each carrying its own state."""

    def __init__(self, role, net, policy):
        self.role, self.net, self.policy = role, net, policy
        self.reset()
        self.decisions = 0
        self.max_err = 0.0

    def reset(self):
        self.torch_state = self.net.initial_state(1)
        self.onnx_state = self.policy.initial_state(self.role)
        if self.torch_state is None:
            assert self.onnx_state is None
        else:
            for t, o in zip(self.torch_state, self.onnx_state):
                np.testing.assert_array_equal(t.numpy(), o)

    def act(self, x_torch: np.ndarray, x_onnx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with torch.inference_mode():
            q_t, self.torch_state = self.net.act(torch.tensor(x_torch), self.torch_state)
        q_o, self.onnx_state = self.policy.act(self.role, x_onnx, self.onnx_state)
        q_t = q_t.numpy()
        assert q_o.dtype == np.float32 and q_o.shape == q_t.shape
        err = float(np.abs(q_o - q_t).max())
        if self.torch_state is not None:
            for t, o in zip(self.torch_state, self.onnx_state):
                assert o.dtype == np.float32 and o.shape == tuple(t.shape) == (1, 256)
                err = max(err, float(np.abs(o - t.numpy()).max()))
        assert err <= TOL, f"{self.role} decision {self.decisions}: |onnx - torch| = {err:.3g}"
        self.max_err = max(self.max_err, err)
        self.decisions += 1
        return q_t, q_o


def _greedy(q: np.ndarray, invalid: int = -1) -> int:
    q = q[0].astype(np.float64)
    if invalid >= 0:
        q[invalid] = -np.inf
    return int(q.argmax())


def _play(ckpt: Path, policy: OnnxPolicy, episodes: int, seed: int, explore: float = 0.2) -> dict:
    """Whole episodes of the hierarchical policy (Algorithm 1 acting: a new option when the
    critic ends one, h^S <- 0 per option, h^M <- 0 per episode), torch and ONNX side by
    side on one real environment. ``explore``: share of steps with a random action (the
    same draw for both), so the observations vary; the greedy choices must agree at every
    step whether taken or not."""
    nets = _torch_nets(ckpt)
    batch = make_batch(policy.env, 1, **policy.env_kwargs)
    critic = batch.critic()
    rng = np.random.default_rng(seed)
    sub = _Pair("sub", nets["sub"], policy)
    meta = _Pair("meta", nets["meta"], policy) if "meta" in nets else None
    meta_index = 1 if policy.meta_state == "c" else 0
    obs = batch.reset(seed=seed)
    steps = options = 0
    carried_differs = 0
    for _ in range(episodes):
        sub.reset()
        if meta is not None:
            meta.reset()
        last_torch = last_onnx = np.zeros((1, 256), np.float32)  # hDRQNv2: zeros at the first decision
        need_meta, place, subgoal_image = meta is not None, -1, None
        while True:
            if need_meta:
                if policy.meta_input == "state":
                    q_t, q_o = meta.act(last_torch, last_onnx)
                else:
                    q_t, q_o = meta.act(obs, obs)
                subgoal = _greedy(q_t, place)
                assert _greedy(q_o, place) == subgoal
                if rng.random() < explore:
                    subgoal = int(rng.choice([g for g in range(policy.num_subgoals) if g != place]))
                subgoal_image = batch.subgoal_images(np.array([subgoal]))
                sub.reset()  # a new option
                options += 1
                need_meta = False
            x = stack_subgoal(obs, subgoal_image) if meta is not None else obs
            np.testing.assert_array_equal(policy.sub_input(obs, subgoal_image), x)
            if sub.torch_state is not None and sub.decisions:
                # the carried state matters: from zeros the same input gives other Q-values
                q_fresh, _ = policy.act("sub", x, None)
                q_carried, _ = policy.act("sub", x, sub.onnx_state)
                carried_differs += int(np.abs(q_fresh - q_carried).max() > 1e-4)
            q_t, q_o = sub.act(x, x)
            action = _greedy(q_t)
            assert _greedy(q_o) == action, f"greedy actions differ at step {steps}"
            if rng.random() < explore:
                action = int(rng.integers(policy.num_actions))
            env = batch.step(np.array([action]))
            steps += 1
            if meta is not None:
                option_done = bool(critic.evaluate(env, np.array([subgoal])).option_done[0])
                if option_done and policy.meta_input == "state":
                    last_torch = sub.torch_state[meta_index].numpy().copy()
                    last_onnx = policy.meta_input_from_sub_state(sub.onnx_state).copy()
                need_meta = option_done
                place = int(env.at_subgoal[0])
            if env.done[0]:
                obs = batch.reset_where(np.array([True]))
                break
            obs = env.obs
    return {"steps": steps, "options": options, "sub": sub, "meta": meta, "carried_differs": carried_differs}


# ---- the tables the torch-free module repeats ---------------------------------------

def test_deploy_algo_table_is_algo_specs_and_role_io_fits_the_networks():
    assert set(onnx_policy.ALGOS) == set(ALGO_SPECS)
    for algo, spec in ALGO_SPECS.items():
        assert onnx_policy.ALGOS[algo] == {"hierarchical": spec.hierarchical, "recurrent": spec.recurrent,
                                           "meta_input": spec.meta_input}
        for role in ("meta", "sub") if spec.hierarchical else ("sub",):
            net = make_network(algo, role, 4, 3)
            inputs, outputs = role_io(algo, role, 4, 3)
            assert inputs[0].shape[1:] == net.trunk.input_shape
            assert inputs[0].dtype == ("float32" if len(net.trunk.input_shape) == 1 else "uint8")
            assert outputs[0].shape == (None, net.n_outputs)
            assert (len(inputs) == 3) == net.recurrent
        if not spec.hierarchical:
            with pytest.raises(PolicyError, match="no 'meta' controller"):
                role_io(algo, "meta", 4, 3)
    obs = np.random.default_rng(0).integers(0, 256, (2, 44, 44, 3), dtype=np.uint8)
    goal = np.random.default_rng(1).integers(0, 256, (1, 44, 44, 3), dtype=np.uint8)
    np.testing.assert_array_equal(onnx_policy.stack_subgoal(obs, goal), stack_subgoal(obs, goal))


# ---- export --------------------------------------------------------------------------

@pytest.mark.parametrize("algo", ALGOS)
def test_policy_json_describes_the_models(exported, algo):
    ckpt, policy_dir = exported[algo]
    meta = json.loads((policy_dir / "policy.json").read_text())
    spec = ALGO_SPECS[algo]
    assert meta["format"] == "hdrqn_ros-policy" and meta["version"] == 1
    assert meta["algo"] == algo and meta["package_version"] == hdrqn_ros.__version__
    assert meta["env"] == load_checkpoint(ckpt)["config"]["env"]
    probe = make_batch(meta["env"], 1)
    assert (meta["num_actions"], meta["num_subgoals"]) == (probe.num_actions, probe.num_subgoals)
    assert meta["image_size"] == 44 and meta["meta_input"] == spec.meta_input and meta["meta_state"] == "c"
    assert meta["checkpoint"] == {"file": "last.pt", "episodes": 3, "env_steps": 120}
    assert sorted(meta["roles"]) == (["meta", "sub"] if spec.hierarchical else ["sub"])
    for role, entry in meta["roles"].items():
        path = policy_dir / entry["file"]
        assert entry["file"] == f"{role}.onnx"
        assert entry["sha256"] == file_sha256(path)
        assert entry["verified_max_abs_error"] < 1e-5
        model = onnx.load(str(path))
        onnx.checker.check_model(model)
        names = [i.name for i in model.graph.input]
        assert names == (["x", "h", "c"] if entry["recurrent"] else ["x"])
        x_shape = entry["inputs"][0]["shape"]
        want = [None, 256] if role == "meta" and spec.meta_input == "state" else \
            [None, 44, 44, 6 if spec.hierarchical and role == "sub" else 3]
        assert x_shape == want
        assert entry["inputs"][0]["dtype"] == ("float32" if len(want) == 2 else "uint8")
    policy = OnnxPolicy.load(policy_dir)
    assert policy.roles == tuple(sorted(meta["roles"], key=["meta", "sub"].index))


def test_export_refuses_a_missing_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        export_policy(tmp_path / "nope.pt", tmp_path / "policy")
    assert not (tmp_path / "policy").exists()


def test_the_export_command_writes_a_policy_and_names_a_bad_checkpoint(exported, tmp_path, capsys):
    from hdrqn_ros.cli import main

    ckpt, _ = exported["drqn"]
    assert main(["export", "--checkpoint", str(ckpt), "--out", str(tmp_path / "policy")]) == 0
    assert OnnxPolicy.load(tmp_path / "policy").algo == "drqn"
    assert main(["export", "--checkpoint", str(tmp_path / "nope.pt"), "--out", str(tmp_path / "p2")]) == 2
    assert "nope.pt does not exist" in capsys.readouterr().err


# ---- ONNX Runtime == torch -----------------------------------------------------------

@pytest.mark.parametrize("algo", ALGOS)
def test_onnx_acts_as_torch_over_whole_episodes(exported, algo):
    ckpt, policy_dir = exported[algo]
    policy = OnnxPolicy.load(policy_dir)
    run = _play(ckpt, policy, episodes=4, seed=5)
    assert run["steps"] >= 30 and run["sub"].decisions == run["steps"]
    assert run["sub"].max_err <= TOL
    if ALGO_SPECS[algo].hierarchical:
        assert run["meta"].decisions == run["options"] >= 3
    if policy.recurrent("sub"):
        assert run["carried_differs"] >= run["steps"] // 2  # the LSTM state is really carried


@pytest.mark.parametrize("algo", ["hdrqn-v2", "hdqn", "drqn"])
def test_batch_axis_is_dynamic(exported, algo):
    ckpt, policy_dir = exported[algo]
    policy = OnnxPolicy.load(policy_dir)
    rng = np.random.default_rng(3)
    for role, net in _torch_nets(ckpt).items():
        spec = policy.input_spec(role)
        shape = (5, *spec.shape[1:])
        x = rng.integers(0, 256, shape, dtype=np.uint8) if spec.dtype == "uint8" else \
            rng.standard_normal(shape).astype(np.float32)
        state = None
        if policy.recurrent(role):
            state = tuple(rng.standard_normal((5, 256)).astype(np.float32) for _ in range(2))
        with torch.inference_mode():
            q_t, s_t = net.act(torch.tensor(x), None if state is None else tuple(map(torch.tensor, state)))
        q_o, s_o = policy.act(role, x, state)
        np.testing.assert_allclose(q_o, q_t.numpy(), atol=TOL, rtol=0)
        if state is not None:
            for o, t in zip(s_o, s_t):
                np.testing.assert_allclose(o, t.numpy(), atol=TOL, rtol=0)


def test_act_refuses_inputs_of_the_wrong_shape_or_type(exported):
    policy = OnnxPolicy.load(exported["hdrqn-v2"][1])
    with pytest.raises(ValueError, match=r"sub input must be \(B, 44, 44, 6\)"):
        policy.act("sub", np.zeros((1, 44, 44, 3), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        policy.act("sub", np.zeros((1, 44, 44, 6), np.float32))
    with pytest.raises(ValueError, match="state must be"):
        policy.act("meta", np.zeros((1, 256), np.float32), (np.zeros((1, 128), np.float32),) * 2)
    with pytest.raises(ValueError, match="no 'meta' controller"):
        OnnxPolicy.load(exported["dqn"][1]).act("meta", np.zeros((1, 44, 44, 3), np.uint8))


# ---- the simulator plays an exported policy (hdrqn eval --policy) ----------------------

@pytest.mark.parametrize("algo", ["hdrqn-v2", "hdqn", "drqn"])
def test_an_exported_policy_plays_its_checkpoints_episodes(exported, algo):
    """``play`` with :class:`OnnxAgent` on 3 environments (options start in some rows only;
    epsilon 0.2, the same draws): every episode is the checkpoint's."""
    ckpt, policy_dir = exported[algo]

    def episodes(agent, cfg) -> list[tuple]:
        return [(e.steps, bool(e.success), e.classical, e.options)
                for e in play(agent, cfg, 6, seed=21, epsilon=0.2, num_envs=3)]

    cfg, agent = load_trained_agent(ckpt)
    simulated = episodes(agent, cfg)
    onnx_agent = OnnxAgent(OnnxPolicy.load(policy_dir))
    assert episodes(onnx_agent, onnx_agent.settings()) == simulated
    assert sum(steps for steps, *_ in simulated) >= 30


def test_eval_with_policy_prints_what_eval_with_its_checkpoint_prints(exported, capsys):
    from hdrqn_ros.cli import main

    ckpt, policy_dir = exported["hdrqn-v2"]
    outputs = []
    for source in (["--checkpoint", str(ckpt)], ["--policy", str(policy_dir)]):
        assert main(["eval", *source, "--episodes", "4", "--seed", "7", "--subgoals"]) == 0
        outputs.append(json.loads(capsys.readouterr().out))
    assert outputs[0] == outputs[1]
    assert outputs[0]["episodes"] == 4 and outputs[0]["algo"] == "hdrqn-v2" and outputs[0]["options"]


def test_eval_refuses_a_bad_policy_and_a_policy_with_record(exported, tmp_path, capsys):
    from hdrqn_ros.cli import main

    assert main(["eval", "--policy", str(tmp_path / "nope"), "--episodes", "1"]) == 2
    assert f"policy directory {tmp_path / 'nope'} does not exist" in capsys.readouterr().err
    assert main(["eval", "--policy", str(tmp_path), "--episodes", "1"]) == 2
    assert "policy.json does not exist" in capsys.readouterr().err
    ckpt, policy_dir = exported["dqn"]
    assert main(["eval", "--policy", str(policy_dir), "--record", str(tmp_path / "bag"), "--episodes", "1"]) == 2
    assert "--record needs --checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "bag").exists()
    with pytest.raises(SystemExit) as info:
        main(["eval", "--policy", str(policy_dir), "--checkpoint", str(ckpt)])
    assert info.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


# ---- no torch ------------------------------------------------------------------------

def test_the_deploy_module_acts_without_importing_torch(exported):
    code = textwrap.dedent("""
        import json, sys
        import numpy as np
        from hdrqn_ros.deploy import OnnxPolicy
        out = {}
        for name in sys.argv[1:]:
            policy = OnnxPolicy.load(name)
            for role in policy.roles:
                spec = policy.input_spec(role)
                x = np.zeros((1, *spec.shape[1:]), spec.dtype)
                state = policy.initial_state(role)
                for _ in range(3):
                    q, state = policy.act(role, x, state)
                out[f"{policy.algo}/{role}"] = q.shape
        out["torch"] = "torch" in sys.modules
        out["onnx"] = "onnx" in sys.modules
        print(json.dumps(out))
    """)
    dirs = [str(exported[a][1]) for a in ("hdrqn-v2", "hdqn", "dqn")]
    proc = subprocess.run([sys.executable, "-c", code, *dirs], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.splitlines()[-1])
    assert result.pop("torch") is False and result.pop("onnx") is False
    assert result == {"hdrqn-v2/meta": [1, 3], "hdrqn-v2/sub": [1, 4], "hdqn/meta": [1, 2], "hdqn/sub": [1, 4],
                      "dqn/sub": [1, 4]}


# ---- bad policy directories ----------------------------------------------------------

@pytest.fixture
def policy_copy(exported, tmp_path):
    """A writable copy of the hDRQNv2 policy directory."""
    return Path(shutil.copytree(exported["hdrqn-v2"][1], tmp_path / "policy"))


def _edit_json(policy_dir: Path, edit) -> None:
    path = policy_dir / "policy.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def test_a_directory_without_policy_json_is_refused(tmp_path):
    (tmp_path / "sub.onnx").write_bytes(b"")
    with pytest.raises(PolicyError, match=r"policy\.json does not exist") as info:
        OnnxPolicy.load(tmp_path)
    assert str(tmp_path / "policy.json") in str(info.value)
    with pytest.raises(PolicyError, match="does not exist"):
        OnnxPolicy.load(tmp_path / "missing")
    (tmp_path / "policy.json").write_text("{not json")
    with pytest.raises(PolicyError, match=r"policy\.json is not readable JSON"):
        OnnxPolicy.load(tmp_path)
    (tmp_path / "policy.json").write_text("{}")
    with pytest.raises(PolicyError, match="not an hdrqn_ros policy"):
        OnnxPolicy.load(tmp_path)


def test_a_tampered_model_file_is_refused_by_its_hash(policy_copy):
    path = policy_copy / "sub.onnx"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte inside the weights
    path.write_bytes(bytes(data))
    with pytest.raises(PolicyError, match="sha256") as info:
        OnnxPolicy.load(policy_copy)
    assert str(path) in str(info.value) and "policy.json" in str(info.value)


def test_a_missing_model_file_is_refused(policy_copy):
    (policy_copy / "meta.onnx").unlink()
    with pytest.raises(PolicyError, match=r"meta\.onnx does not exist"):
        OnnxPolicy.load(policy_copy)


def test_a_model_of_the_wrong_shape_is_refused(policy_copy, exported):
    """DQN's sub-controller (3-channel input) put in place of hDRQNv2's (6 channels, LSTM),
    its hash updated so only the graph check can catch it."""
    path = policy_copy / "sub.onnx"
    shutil.copyfile(exported["dqn"][1] / "sub.onnx", path)
    _edit_json(policy_copy, lambda m: m["roles"]["sub"].update(sha256=onnx_policy.file_sha256(path)))
    with pytest.raises(PolicyError) as info:
        OnnxPolicy.load(policy_copy)
    assert str(path) in str(info.value) and "inputs are ['x'], expected ['x', 'h', 'c']" in str(info.value)
    # same names, other shapes: hDRQNv1's meta (44x44x3 images) in place of hDRQNv2's (256 floats)
    path = policy_copy / "meta.onnx"
    shutil.copyfile(exported["hdrqn-v1"][1] / "meta.onnx", path)
    shutil.copyfile(exported["hdrqn-v2"][1] / "sub.onnx", policy_copy / "sub.onnx")
    _edit_json(policy_copy, lambda m: (m["roles"]["meta"].update(sha256=onnx_policy.file_sha256(path)),
                                       m["roles"]["sub"].update(sha256=onnx_policy.file_sha256(policy_copy / "sub.onnx"))))
    with pytest.raises(PolicyError) as info:
        OnnxPolicy.load(policy_copy)
    assert str(path) in str(info.value) and "input 'x' has type uint8, expected float32" in str(info.value)


def test_a_model_with_the_wrong_number_of_subgoals_is_refused(policy_copy):
    """The four-rooms 3-goal policy's json edited to 2 subgoals: meta.onnx's q has 3."""
    _edit_json(policy_copy, lambda m: (m.update(num_subgoals=2),
                                       m["roles"]["meta"]["outputs"][0].update(shape=[None, 2])))
    with pytest.raises(PolicyError) as info:
        OnnxPolicy.load(policy_copy)
    assert str(policy_copy / "meta.onnx") in str(info.value)
    assert "output 'q' has shape ['batch', 3], expected ['batch', 2]" in str(info.value)


def test_declared_shapes_that_do_not_fit_the_algo_are_refused(policy_copy):
    _edit_json(policy_copy, lambda m: m["roles"]["sub"]["inputs"][0].update(shape=[None, 44, 44, 3]))
    with pytest.raises(PolicyError, match=r"policy\.json: sub inputs .* do not fit hdrqn-v2"):
        OnnxPolicy.load(policy_copy)


def test_declared_algo_or_roles_that_do_not_fit_are_refused(policy_copy):
    _edit_json(policy_copy, lambda m: m.update(algo="drqn", meta_input=None))
    with pytest.raises(PolicyError, match=r"policy\.json: roles are \['meta', 'sub'\], but drqn has \['sub'\]"):
        OnnxPolicy.load(policy_copy)
    _edit_json(policy_copy, lambda m: m.update(algo="hdrqn-v1"))
    with pytest.raises(PolicyError, match="meta_input is None, but hdrqn-v1 has 'image'"):
        OnnxPolicy.load(policy_copy)
    _edit_json(policy_copy, lambda m: m.update(algo="hdrqn-v9"))
    with pytest.raises(PolicyError, match="unknown algo 'hdrqn-v9'"):
        OnnxPolicy.load(policy_copy)


def test_a_file_that_is_not_onnx_is_refused(policy_copy):
    path = policy_copy / "meta.onnx"
    path.write_bytes(b"not an onnx model")
    _edit_json(policy_copy, lambda m: m["roles"]["meta"].update(sha256=onnx_policy.file_sha256(path)))
    with pytest.raises(PolicyError, match="not a loadable ONNX model") as info:
        OnnxPolicy.load(policy_copy)
    assert str(path) in str(info.value)


def test_a_model_file_outside_the_directory_is_refused(policy_copy):
    _edit_json(policy_copy, lambda m: m["roles"]["sub"].update(file="../sub.onnx"))
    with pytest.raises(PolicyError, match="must be a plain file name"):
        OnnxPolicy.load(policy_copy)
