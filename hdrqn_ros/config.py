"""Training configuration: thesis Table 4.7 defaults, validated with pydantic.

A YAML file given with ``--config`` is checked against these models: an unknown key or a
wrong type is a :class:`ConfigError` naming the key.
"""
from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from hdrqn_ros.agents.specs import ALGO_SPECS, ALGOS
from hdrqn_ros.yaml_files import read_mapping, safe_load

Algo = Literal[ALGOS]


class ConfigError(ValueError):
    """A configuration file or override is invalid; the message names the problem."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class EpsilonSchedule(_Strict):
    """Linear annealing from ``start`` to ``end`` over ``steps`` env steps (after warm-up)."""

    start: float = Field(1.0, ge=0.0, le=1.0)
    end: float = Field(0.1, ge=0.0, le=1.0)
    steps: int = Field(50_000, ge=1)

    def value(self, step: int) -> float:
        frac = min(max(step, 0) / self.steps, 1.0)
        return self.start + frac * (self.end - self.start)


THESIS_LR = 1e-4
"""Table 4.7's learning rate, for every controller but one (below)."""
STATE_META_LR = 1e-3
"""The author's code's learning rate for hDRQNv2's meta MLP on the sub-controller's LSTM state."""


class ControllerConfig(_Strict):
    """Hyper-parameters of one controller (thesis Table 4.7)."""

    lr: float | None = Field(THESIS_LR, gt=0.0, description="Adam's learning rate; null: the algorithm's "
                             "(meta-controller: 1e-3 for hDRQNv2's MLP, else 1e-4)")
    gamma: float = Field(0.99, ge=0.0, le=1.0)
    tau: float = Field(0.001, gt=0.0, le=1.0)
    batch_size: int = Field(4, ge=1)
    seq_len: int = Field(8, ge=1, description="n: length of the sampled windows")
    replay_episodes: int = Field(5000, ge=1)
    replay_bytes: int | None = Field(None, ge=1, description="optional bound on replay memory")
    loss: Literal["mse", "huber"] = "mse"
    grad_clip: float | None = Field(10.0, gt=0.0)
    sampling: Literal["windows", "whole"] = Field("windows", description="windows: the thesis's bootstrapped "
                                                  "random updates, zero-state windows of seq_len; whole: whole "
                                                  "segments from their start (an episode of options for the "
                                                  "meta-controller, an option for the sub-controller), as acting "
                                                  "unrolls them, loss on every step (docs/training.md)")
    time_limit: Literal["bootstrap", "terminal"] = Field("bootstrap", description="an episode cut by the step "
                                                         "limit: bootstrap its last step, or treat it as terminal "
                                                         "(for a controller that cannot see the time left)")
    window_history: bool = Field(False, description="windows begin up to n/2 steps before their first loss "
                                 "step (inside the option), so every loss step has history (docs/training.md)")
    epsilon: EpsilonSchedule = EpsilonSchedule()


def _sub_defaults() -> ControllerConfig:
    # gamma 0.9 instead of Table 4.7's 0.99: with one +1 at the subgoal, 0.99 leaves the
    # actions' values a few percent apart and the greedy sub-controller loops (docs/results.md)
    return ControllerConfig(batch_size=4, seq_len=8, replay_episodes=5000, gamma=0.9,
                            epsilon=EpsilonSchedule(start=1.0, end=0.1, steps=50_000))


def _meta_defaults() -> ControllerConfig:
    # whole episodes of options with the step limit terminal, not the thesis's zero-state
    # windows with the limit bootstrapped: on three goals the thesis's way learned the order on
    # one seed of three, its Q-values diverging (docs/training.md, "Where this differs")
    return ControllerConfig(batch_size=12, seq_len=2, replay_episodes=1000, lr=None, sampling="whole",
                            time_limit="terminal", epsilon=EpsilonSchedule(start=1.0, end=0.05, steps=150_000))


def _flat_defaults() -> ControllerConfig:
    # Table 4.7's gamma and epsilon end; a flat agent faces the whole task, as the meta-controller
    # does, so it anneals over the meta's 150,000 steps (the thesis gives no length)
    return ControllerConfig(batch_size=4, seq_len=8, replay_episodes=5000, gamma=0.99,
                            epsilon=EpsilonSchedule(start=1.0, end=0.1, steps=150_000))


BEFORE_SAMPLING = {"sampling": "windows", "time_limit": "bootstrap"}
"""How every controller learned before ``sampling`` and ``time_limit`` existed (a checkpoint's
config without them: :meth:`TrainConfig.changes_since` names the switch to today's defaults)."""

MAX_ENVS = 4096
"""Most environments one batch steps (a bigger batch is a typo, not a plan: it would fill memory)."""


class TrainConfig(_Strict):
    """Everything one training run needs. Units: env steps unless stated."""

    algo: Algo = "hdrqn-v2"
    env: str = "hdrqn/GridWorld-2Goals-v0"
    env_kwargs: dict[str, Any] = Field(default_factory=dict, description="environment options, e.g. {view: 3}")
    episodes: int = Field(10_000, ge=1, description="training episodes")
    num_envs: int = Field(16, ge=1, le=MAX_ENVS, description="environments stepped together")
    seed: int = 0
    device: str = "cpu"
    update_every: int = Field(5, ge=1, description="env steps per update of each controller")
    learning_starts: int = Field(10_000, ge=0, description="random-policy env steps before updates")
    sub_only_episodes: int = Field(0, ge=0, description="phase 1 of two-phase training: meta acts randomly and is not trained")
    meta_state: Literal["c", "h"] = Field("c", description="hDRQNv2 meta input: sub LSTM cell (c) or hidden (h) state")
    smdp_discount: bool = Field(False, description="meta target uses gamma**k for a k-step option (eq. 3.5) instead of gamma")
    eval_every: int = Field(500, ge=0, description="episodes between greedy evaluations (0: never)")
    eval_episodes: int = Field(100, ge=1, le=100_000)
    checkpoint_every: int = Field(1000, ge=1, description="episodes between checkpoints")
    log_every_updates: int = Field(100, ge=1, description="updates of a controller per row of losses.csv "
                                   "(the means of its TD loss, Q, target and gradient norm over them)")
    save_replay: bool = Field(True, description="write the replay memory beside each checkpoint "
                              "(checkpoints/replay-*.safetensors) and restore it on --resume; false for huge "
                              "replays (a resumed run then starts with an empty replay)")
    torch_threads: int = Field(1, ge=1, description="torch intra-op threads; 1 is fastest for these small networks on a CPU")
    parallel_updates: bool = Field(True, description="run the meta and sub updates in two threads at once (they share nothing)")
    sub: ControllerConfig = Field(default_factory=_sub_defaults, description="hierarchical agents' sub-controller")
    meta: ControllerConfig = Field(default_factory=_meta_defaults, description="hierarchical agents' meta-controller")
    flat: ControllerConfig = Field(default_factory=_flat_defaults, description="DQN's and DRQN's one controller")

    def controller(self, role: str) -> ControllerConfig:
        """What ``role``'s controller learns with, its learning rate resolved: ``"sub"`` is the
        sub-controller of a hierarchical agent or the one controller of a flat one (``flat``),
        ``"meta"`` the meta-controller."""
        spec = ALGO_SPECS[self.algo]
        if role == "sub":
            section = self.sub if spec.hierarchical else self.flat
        elif role == "meta":
            section = self.meta
        else:
            raise ValueError(f"controller role must be 'sub' or 'meta', got {role!r}")
        if section.lr is not None:
            return section
        lr = STATE_META_LR if role == "meta" and spec.meta_input == "state" else THESIS_LR
        return section.model_copy(update={"lr": lr})

    def changes_since(self, saved: dict) -> list[str]:
        """``"key: old -> new"`` for each setting (dotted, e.g. ``flat.gamma``) this config sets
        differently from ``saved`` (a checkpoint's config), leaving out the budget (``episodes``)
        and the controller sections this agent does not use (``flat`` for a hierarchical agent,
        ``sub`` and ``meta`` for a flat one)."""
        unused = {"flat"} if ALGO_SPECS[self.algo].hierarchical else {"sub", "meta"}
        changes: list[str] = []
        saved = {**saved, **{section: {**BEFORE_SAMPLING, **saved[section]} for section in ("sub", "meta", "flat")
                             if isinstance(saved.get(section), dict)}}

        def walk(old: Any, new: Any, key: str) -> None:
            if isinstance(old, dict) and isinstance(new, dict):
                for name in sorted(set(old) | set(new)):
                    walk(old.get(name), new.get(name), f"{key}.{name}" if key else name)
            elif old != new and key != "episodes" and key.split(".")[0] not in unused:
                changes.append(f"{key}: {old!r} -> {new!r}")

        walk(saved, self.model_dump(), "")
        return changes

    @field_validator("device")
    @classmethod
    def _device(cls, device: str) -> str:
        """A device string torch understands ("cpu", "cuda", "cuda:1"...); availability is checked when used."""
        if device != "cpu":
            import torch

            try:
                torch.device(device)
            except RuntimeError:
                raise ValueError(f"not a torch device: {device!r} (e.g. cpu, cuda, cuda:1)") from None
        return device

    @model_validator(mode="after")
    def _check(self) -> "TrainConfig":
        from hdrqn_ros.envs.registration import ENV_IDS

        if self.env not in ENV_IDS:
            raise ValueError(f"unknown env {self.env!r}; known: {', '.join(ENV_IDS)}")
        options = set(inspect.signature(batch_class(self.env)).parameters) - {"num_envs"}
        if unknown := sorted(map(str, set(self.env_kwargs) - options)):
            raise ValueError(f"env_kwargs {unknown} are not options of {self.env}; its options: {sorted(options)}")
        return self


def batch_class(env_id: str) -> type:
    """The batch core class of a registered ``env_id`` (without building one)."""
    from hdrqn_ros.envs.registration import MONTEZUMA_IDS

    if env_id in MONTEZUMA_IDS:
        from hdrqn_ros.envs.montezuma import MontezumaBatch

        return MontezumaBatch
    from hdrqn_ros.envs.gridworld import GridWorldBatch

    return GridWorldBatch


def _merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def parse_set(items: list[str]) -> dict[str, Any]:
    """``["sub.seq_len=12", "env_kwargs.view=3"]`` -> nested dict; values parsed as YAML.

    Raises :class:`ConfigError` for an item without ``=`` or whose first key is not a
    :class:`TrainConfig` field.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE (e.g. sub.seq_len=12), got {item!r}")
        if (root := key.strip().split(".")[0]) not in TrainConfig.model_fields:
            raise ConfigError(f"--set {item!r}: unknown config key {root!r}; "
                              f"known: {', '.join(TrainConfig.model_fields)}")
        try:
            value = safe_load(raw)
        except yaml.YAMLError:
            value = raw
        node = out
        *parents, leaf = key.strip().split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r} conflicts with an earlier --set of {part!r}")
        node[leaf] = value
    return out


def build_config(files: list[str | Path] = (), base: dict | None = None, **overrides: Any) -> TrainConfig:
    """Defaults, then ``base`` (e.g. a recording's config), then each YAML file in order,
    then ``overrides`` (``None`` values skipped; nested dicts merge key by key).

    Raises :class:`ConfigError` naming the file and the bad key or value.
    """
    data: dict[str, Any] = TrainConfig().model_dump()  # nested sections merge onto the defaults
    if base:
        data = _merge(data, base)
    for file in files:
        data = _merge(data, read_mapping(file, ConfigError, "config ", empty_ok=True))
    data = _merge(data, {k: v for k, v in overrides.items() if v is not None})
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as exc:
        where = f" in {', '.join(map(str, files))}" if files else ""
        lines = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
            got = repr(err.get("input"))
            got = got if len(got) <= 80 else got[:77] + "..."
            lines.append(f"  {loc}: {err['msg']} (got {got})")
        raise ConfigError(f"invalid configuration{where}:\n" + "\n".join(lines)) from None
