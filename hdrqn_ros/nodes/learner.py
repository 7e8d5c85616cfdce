"""``learner`` node: assembles transitions from the graph, owns replay, trains, publishes weights.

For each environment group (a namespace in ``groups``) a :class:`GroupAssembler` joins
the group's messages by step key into the same :class:`StepRecord` rows the in-process
rollout produces, and the same :class:`EpisodeRecorder` turns them into replay episodes.
A training thread runs the :class:`~hdrqn_ros.training.learner.Learner` (one update per
controller every ``update_every`` env steps), publishes weights every ``weights_every``
updates on latched topics, and checkpoints. Each group's environment may run
``credit_window`` steps ahead of what the learner has received, and no further while the
learner owes more than ``max_owed_updates`` updates: so the thesis update ratio holds.
A group that joins late (or a learner that restarts) starts using a group's data at its
next episode boundary.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from collections import deque
from pathlib import Path

import numpy as np

from hdrqn_ros.agents.networks import lstm_state_size
from hdrqn_ros.agents.weights import encode_weights
from hdrqn_ros.config import build_config, parse_set
from hdrqn_ros.envs.domain import OBS_SIZE
from hdrqn_ros.middleware import LATCHED_QOS, Middleware
from hdrqn_ros.nodes import protocol as P
from hdrqn_ros.nodes.common import ENV_DEFAULTS, NodeConfigError, check_algo, env_kwargs, obs_digest, run_node
from hdrqn_ros.nodes.critic import step_batch
from hdrqn_ros.nodes.follower import StepFollower, done
from hdrqn_ros.training.episodes import EpisodeRecorder
from hdrqn_ros.training.learner import EVAL_SEED_OFFSET, Learner, evaluate
from hdrqn_ros.training.rollout import StepRecord

PARAMETERS = {**ENV_DEFAULTS, "config": "", "overrides": [""], "episodes": 1000, "run_dir": "runs/graph",
              "groups": ["/"], "resume": False, "weights_every": 25, "credit_window": 20, "max_owed_updates": 2,
              "status_period": 1.0, "evaluate": True, "transition_log": ""}
"""``config``: a training config YAML (``hdrqn train --config``); ``overrides``:
``key=value`` items like ``hdrqn train --set``; the parameters ``algo``, ``env``, ``view``,
``seed``, ``episodes`` win over both. ``resume``: continue from ``run_dir``'s checkpoint
when there is one. ``transition_log``: append every assembled transition to this JSON-lines
file (keys, action, rewards, flags, observation digests: for checking alignment)."""

EPISODE_QUEUE = 256
"""Finished episodes waiting for the training thread (bounded; the credit keeps it short)."""


class GroupAssembler(StepFollower):
    """One environment group's messages -> :class:`StepRecord` rows -> replay episodes."""

    skip_stale = False  # a transition needs every step of its episode

    def __init__(self, node, namespace: str, learner: Learner, episodes: "queue.Queue", log=None):
        super().__init__(node)
        self.ns = namespace.rstrip("/")
        self.learner, self.episodes = learner, episodes
        self.spec = learner.agent.spec
        self.num_subgoals = learner.agent.num_subgoals
        cfg = learner.cfg
        self.recorder_args = (1, self.spec.hierarchical, cfg.sub.gamma, cfg.meta.gamma, cfg.smdp_discount)
        self.env_steps_seen = 0  # the env's own step count, from its latest env_step
        self.transitions = 0
        self.skipped = 0  # steps seen while waiting for an episode boundary
        self.lost_episodes = 0  # episodes cut short by missing messages or restarts
        self.open = False
        self.last_credit: tuple | None = None
        self.log = log
        t = self.topic
        node.create_subscription(P.FLOATS, t(P.ENV_STEP), self.on_env_step, P.STEP_QOS)
        node.create_subscription(P.IMAGE, t(P.OBSERVATION), lambda m: self._image(P.OBSERVATION, m, 1), P.STEP_QOS)
        node.create_subscription(P.INTS, t(P.ACTION), lambda m: self._ints(P.ACTION, P.ACTION_FIELDS, m), P.STEP_QOS)
        if self.spec.hierarchical:
            node.create_subscription(P.IMAGE, t(P.SUBGOAL_IMAGES),
                                     lambda m: self._image(P.SUBGOAL_IMAGES, m, self.num_subgoals), P.STEP_QOS)
            node.create_subscription(P.INTS, t(P.SUBGOAL), lambda m: self._ints(P.SUBGOAL, P.SUBGOAL_FIELDS, m),
                                     P.STEP_QOS)
            node.create_subscription(P.FLOATS, t(P.CRITIC), self._critic, P.STEP_QOS)
        if self.spec.meta_input == "state":
            node.create_subscription(P.FLOATS, t(P.SUB_STATE), self._sub_state, P.STEP_QOS)
        self.credit_pub = node.create_publisher(P.FLOATS, t(P.CREDIT), LATCHED_QOS)

    def topic(self, name: str) -> str:
        return f"{self.ns}/{name}"

    # -- inputs --------------------------------------------------------------------------------
    def _image(self, topic: str, msg, rows: int) -> None:
        got = self.decode(self.topic(topic), lambda: P.read_image(msg, OBS_SIZE * rows, OBS_SIZE))
        if got is not None:
            self.put(topic, *got)

    def _ints(self, topic: str, fields, msg) -> None:
        rec = self.decode(self.topic(topic), lambda: P.read_record(msg, fields, np.int64))
        if rec is not None:
            self.put(topic, rec["key"], rec)

    def _critic(self, msg) -> None:
        rec = self.decode(self.topic(P.CRITIC), lambda: P.read_record(msg, P.CRITIC_FIELDS))
        if rec is not None:
            self.put(P.CRITIC, rec["key"], rec)

    def _sub_state(self, msg) -> None:
        got = self.decode(self.topic(P.SUB_STATE), lambda: P.read_state(msg, lstm_state_size))
        if got is not None:
            self.put(P.SUB_STATE, *got)

    def received(self, step: dict) -> None:
        self.env_steps_seen = int(step["env_steps"])

    # -- assembly -----------------------------------------------------------------------------------
    def ready(self, step: dict) -> bool:
        key, prev, box = int(step["key"]), int(step["prev_key"]), self.inbox
        if not box.has(P.OBSERVATION, key):
            return False
        if step["t"] == 0 or not self.open:
            return True
        if not box.has(P.ACTION, prev):
            return False
        if not self.spec.hierarchical:
            return True
        critic = box.get(P.CRITIC, key)
        if critic is None:
            return False
        if self.option_next and not (box.has(P.SUBGOAL, prev) and box.has(P.SUBGOAL_IMAGES, prev)):
            return False
        return not (self.spec.meta_input == "state" and critic["option_done"]) or box.has(P.SUB_STATE, prev)

    def process(self, step: dict) -> list:
        key, obs = int(step["key"]), self.inbox.get(P.OBSERVATION, int(step["key"]))
        if step["t"] == 0:
            if self.open:
                self.lost_episodes += 1
            self._begin(key, obs)
        elif not self.open:
            self.skipped += 1
        else:
            self._transition(step, obs)
        return []

    def _begin(self, key: int, obs: np.ndarray) -> None:
        self.open = True
        self.option_next = True  # an option starts at the episode's first step
        self.recorder = EpisodeRecorder(*self.recorder_args)
        self.prev_obs = obs
        self.subgoal_image = np.zeros_like(obs)
        self.option_extrinsic = 0.0
        self.option_steps = 0
        self.last_sub_state = np.zeros(lstm_state_size, np.float32)

    def _transition(self, step: dict, obs: np.ndarray) -> None:
        box, key, prev = self.inbox, int(step["key"]), int(step["prev_key"])
        action = int(box.get(P.ACTION, prev)["action"])
        env = step_batch(step, obs)
        if self.spec.hierarchical:
            critic, new_option = box.get(P.CRITIC, key), self.option_next
            if new_option:  # the meta-controller publishes a subgoal when an option starts
                self.option_subgoal = int(box.get(P.SUBGOAL, prev)["subgoal"])
            subgoal = self.option_subgoal
            intrinsic, reached, option_done = critic["intrinsic"], bool(critic["reached"]), bool(critic["option_done"])
            self.option_next = option_done
            sub_terminal = reached or bool(step["terminated"])
        else:
            subgoal, new_option = -1, step["t"] == 1
            intrinsic, option_done, sub_terminal = 0.0, done(step), bool(step["terminated"])
        meta_input = None
        if new_option:
            if self.spec.hierarchical:
                images = box.get(P.SUBGOAL_IMAGES, prev)
                self.subgoal_image = images[subgoal * OBS_SIZE:(subgoal + 1) * OBS_SIZE]
                meta_input = (self.last_sub_state if self.spec.meta_input == "state" else self.prev_obs)[None].copy()
            self.option_extrinsic, self.option_steps = 0.0, 0
        self.option_extrinsic += float(step["extrinsic"])
        self.option_steps += 1
        meta_next = None
        if self.spec.hierarchical and option_done:
            if self.spec.meta_input == "state":
                self.last_sub_state = box.get(P.SUB_STATE, prev)
                meta_next = self.last_sub_state[None].copy()
            else:
                meta_next = obs[None].copy()
        record = StepRecord(
            obs=self.prev_obs[None], new_option=np.array([new_option]), meta_input=meta_input,
            subgoal=np.array([subgoal]), subgoal_image=self.subgoal_image[None], action=np.array([action]),
            env=env, intrinsic=np.array([intrinsic], np.float32), option_done=np.array([option_done]),
            sub_terminal=np.array([sub_terminal]), option_extrinsic=np.array([self.option_extrinsic], np.float32),
            option_steps=np.array([self.option_steps]), meta_next_input=meta_next)
        self.transitions += 1
        if self.log is not None:
            self._log(step, action, subgoal, intrinsic, obs)
        for _, sub_ep, meta_ep, stats in self.recorder.add(record):
            self.episodes.put((self.ns or "/", sub_ep, meta_ep, stats))
            self.open = False
        self.prev_obs = obs

    def _log(self, step: dict, action: int, subgoal: int, intrinsic: float, obs: np.ndarray) -> None:
        row = {"group": self.ns or "/", **{f: step[f] for f in ("key", "prev_key", "episode", "t", "extrinsic",
                                                                "classical", "terminated", "truncated")},
               "action": action, "subgoal": subgoal, "intrinsic": intrinsic,
               "obs": obs_digest(self.prev_obs), "next_obs": obs_digest(obs)}
        self.log.write(json.dumps(row) + "\n")

    def publish_credit(self, window: int, owed_ok: bool, eps: tuple[float, float], epoch: float,
                       force: bool = False) -> None:
        """Publish ``learner_credit`` when the credit or the epsilons changed (or ``force``)."""
        credit = self.env_steps_seen + window if owed_ok else self.env_steps_seen
        values = (credit, round(eps[0], 4), round(eps[1], 4))
        if values == self.last_credit and not force:
            return
        self.last_credit = values
        self.credit_pub.publish(P.make_record(self.node, P.FLOATS, P.CREDIT_FIELDS, [*values, self.last_key, epoch]))

    def stats(self) -> dict:
        return {"env_steps": self.env_steps_seen, "transitions": self.transitions, "skipped": self.skipped,
                "lost_episodes": self.lost_episodes, "rejected": self.rejected}


class LearnerNode:
    def __init__(self, mw: Middleware):
        node = self.node = mw.create_node("learner")
        p = self.params = node.declare_parameters(PARAMETERS)
        check_algo(p["algo"])
        overrides = parse_set([item for item in p["overrides"] if item])
        overrides.setdefault("env_kwargs", {}).update(env_kwargs(p["env"], p["view"]))
        cfg = build_config([p["config"]] if p["config"] else [],
                           **{**overrides, "algo": p["algo"], "env": p["env"], "seed": p["seed"],
                              "episodes": p["episodes"]})
        run_dir = Path(p["run_dir"])
        resume = p["resume"] and (run_dir / "checkpoints" / "last.pt").exists()
        self.learner = Learner(cfg, run_dir, resume=resume, progress=False)
        if resume:
            node.logger.info("resumed from %s at episode %d", run_dir, self.learner.episodes)
        for key in ("weights_every", "credit_window", "max_owed_updates"):
            if p[key] < 1:
                raise NodeConfigError(f"{key} must be >= 1, got {p[key]}")
        self.episodes: queue.Queue = queue.Queue(EPISODE_QUEUE)
        self.transition_log = open(p["transition_log"], "a", buffering=1) if p["transition_log"] else None
        self.groups = [GroupAssembler(node, ns, self.learner, self.episodes, self.transition_log)
                       for ns in p["groups"]]
        self.weight_pubs = {c.name: node.create_publisher(P.BYTES, P.WEIGHTS[c.name], LATCHED_QOS)
                            for c in self.learner.agent.controllers}
        self.status_pub = node.create_publisher(P.STRING, P.STATUS, LATCHED_QOS)
        self.epoch = time.time()
        self.recent: deque = deque(maxlen=100)
        self.start = time.perf_counter()
        self.start_steps = self.learner.env_steps
        self.finished = False
        self.exit_code = 0
        self.summary: dict | None = None
        self._credit_lock = threading.Lock()
        self._stop = threading.Event()
        self._publish_weights()
        node.create_timer(p["status_period"], self._status)
        node.create_timer(1.0, lambda: self._grant_credit(force=True))  # also reaches late joiners
        self.thread = threading.Thread(target=self._train, name="learner-train", daemon=True)
        self.thread.start()

    # -- the training thread ---------------------------------------------------------------------
    def _train(self) -> None:
        learner, cfg = self.learner, self.learner.cfg
        counted = {id(g): g.transitions for g in self.groups}
        next_ckpt = learner._next_multiple(cfg.checkpoint_every)
        try:
            while not self._stop.is_set() and learner.episodes < cfg.episodes:
                for g in self.groups:
                    learner.add_steps(g.transitions - counted[id(g)])
                    counted[id(g)] = g.transitions
                self._store_episodes()
                if learner.episodes >= next_ckpt:
                    learner.save()
                    next_ckpt = learner._next_multiple(cfg.checkpoint_every)
                if learner.owed_updates:
                    before = learner.agent.sub.updates
                    learner.run_owed_updates(limit=1)
                    if learner.agent.sub.updates // self.params["weights_every"] > before // self.params["weights_every"]:
                        self._publish_weights()
                self._grant_credit()
                if not learner.owed_updates:
                    time.sleep(0.001)
            if learner.episodes >= cfg.episodes:
                self._finish()
        except Exception as exc:  # TrainingDiverged and friends: keep the last good checkpoint
            self.node.logger.error("training stopped: %s: %s", type(exc).__name__, exc)
            self.exit_code = 1
        finally:
            self.finished = True

    def _store_episodes(self) -> None:
        learner = self.learner
        while learner.episodes < learner.cfg.episodes:
            try:
                _, sub_ep, meta_ep, stats = self.episodes.get_nowait()
            except queue.Empty:
                return
            eps = learner.epsilons()
            learner.add_episode(sub_ep, meta_ep)
            learner.log_episode(stats, *eps, time.perf_counter() - self.start)
            self.recent.append(stats)

    def _grant_credit(self, force: bool = False) -> None:
        learner = self.learner
        owed_ok = learner.owed_updates <= self.params["max_owed_updates"] and not self.episodes.full()
        with self._credit_lock:
            for g in self.groups:
                g.publish_credit(self.params["credit_window"], owed_ok, learner.epsilons(), self.epoch, force)

    def _publish_weights(self) -> None:
        updates = self.learner.agent.sub.updates
        for c in self.learner.agent.controllers:
            self.weight_pubs[c.name].publish(P.make_weights(self.node, encode_weights(c.online), updates))

    def _finish(self) -> None:
        learner, cfg = self.learner, self.learner.cfg
        learner.save()
        wall = time.perf_counter() - self.start
        final = None
        if self.params["evaluate"] and cfg.eval_every:
            final = evaluate(learner.agent, cfg, cfg.eval_episodes, cfg.seed + EVAL_SEED_OFFSET)
        steps = learner.env_steps - self.start_steps
        self.summary = {"algo": cfg.algo, "env": cfg.env, "episodes": learner.episodes,
                        "env_steps": learner.env_steps, "wall_s": round(wall, 1),
                        "env_steps_per_s": round(steps / max(wall, 1e-9), 1),
                        "updates": learner.agent.sub.updates,
                        "train_success_last100": float(np.mean([s.success for s in self.recent])) if self.recent
                        else None, "final_eval": final, "groups": {g.ns or "/": g.stats() for g in self.groups}}
        (learner.run_dir / "summary.json").write_text(json.dumps(self.summary, indent=2))
        self._status()
        self.node.logger.info("done: %s", json.dumps(self.summary))

    # -- status ------------------------------------------------------------------------------------
    def status(self) -> dict:
        learner = self.learner
        wall = time.perf_counter() - self.start
        eps = learner.epsilons()
        return {"episodes": learner.episodes, "target_episodes": learner.cfg.episodes,
                "env_steps": learner.env_steps, "updates": learner.agent.sub.updates,
                "steps_per_s": round((learner.env_steps - self.start_steps) / max(wall, 1e-9), 1),
                "success_last100": round(float(np.mean([s.success for s in self.recent])), 3) if self.recent else None,
                "eps_sub": round(eps[0], 3), "eps_meta": round(eps[1], 3), "finished": self.summary is not None,
                "groups": {g.ns or "/": g.stats() for g in self.groups}}

    def _status(self) -> None:
        text = json.dumps(self.status())
        self.status_pub.publish(self.node.msg(P.STRING)(data=text))
        path = self.learner.run_dir / "status.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(text)
        tmp.replace(path)

    def close(self) -> None:
        """Stop training; keep what was learned (a checkpoint unless training just finished)."""
        self._stop.set()
        self.thread.join(timeout=30)
        if self.summary is None and self.exit_code == 0:
            self.learner.save()
        self.learner.log.close()
        if self.transition_log is not None:
            self.transition_log.close()


def main(argv: list[str] | None = None) -> int:
    return run_node(lambda mw: LearnerNode(mw), argv)


if __name__ == "__main__":
    raise SystemExit(main())
