"""Stop signals wait for the training loop's step boundary (hdrqn_ros.training.interrupts)."""
import os
import signal

import pytest

from hdrqn_ros.training.interrupts import stop_between_steps


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_raises_only_at_the_step_boundary(signum):
    steps_done = 0
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(KeyboardInterrupt):
        with stop_between_steps() as check:
            for _ in range(5):
                os.kill(os.getpid(), signum)  # lands inside the "step"
                steps_done += 1  # the rest of the step still runs
                check()
    assert steps_done == 1
    assert {s: signal.getsignal(s) for s in before} == before  # the previous handlers are back


def test_a_second_signal_stops_at_once():
    reached = []
    with pytest.raises(KeyboardInterrupt):
        with stop_between_steps():
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGTERM)
            reached.append("after the second signal")
    assert not reached


def test_sigterm_during_an_offline_update_stops_after_it_with_a_checkpoint(tmp_path):
    """The offline trainer finishes the update a SIGTERM lands in, then saves and stops
    (under `hdrqn train`'s own SIGTERM handler, which raises KeyboardInterrupt)."""
    from pathlib import Path

    from hdrqn_ros.cli import _interrupt
    from hdrqn_ros.config import build_config
    from hdrqn_ros.recording.transitions import bag_config, read_episodes
    from hdrqn_ros.training.checkpoint import load_checkpoint
    from hdrqn_ros.training.offline import OfflineTrainer

    sample = Path(__file__).resolve().parents[1] / "bags" / "hdrqn-v2_gridworld-2goals"
    cfg = build_config([], base=bag_config(sample))
    trainer = OfflineTrainer(cfg, tmp_path / "offline", progress=False, tensorboard=False)
    trainer.fill(read_episodes([sample], cfg, trainer.agent.num_subgoals))
    update = trainer.update_once

    def update_hit_by_sigterm_on_the_third(offline):
        if trainer.agent.sub.updates == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # lands before this update's work
        update(offline=offline)

    trainer.update_once = update_hit_by_sigterm_on_the_third
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        with pytest.raises(KeyboardInterrupt):
            trainer.run(updates=10, evaluations=0)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert trainer.agent.sub.updates == 3
    assert load_checkpoint(tmp_path / "offline" / "checkpoints" / "last.pt")["agent"]["sub"]["updates"] == 3
