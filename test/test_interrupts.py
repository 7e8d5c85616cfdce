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
