"""Ctrl-C and SIGTERM stop a training loop between two steps, never inside one.

A signal that lands inside a step (between counting a finished episode and writing its
``train.csv`` row) would leave a checkpoint that counts an episode the metrics never got.
Inside :func:`stop_between_steps` the first SIGINT or SIGTERM only raises a flag; the loop
calls the yielded ``check()`` at its step boundary, which raises ``KeyboardInterrupt``
there. A second signal raises at once (for a step that takes too long).
"""
from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def stop_between_steps() -> Iterator[Callable[[], None]]:
    """Defer SIGINT/SIGTERM to the loop's ``check()`` calls (main thread only; elsewhere
    ``check()`` does nothing and signals behave as before)."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    received: list[int] = []

    def defer(signum, frame):
        if received:
            raise KeyboardInterrupt(f"signal {signum}")
        received.append(signum)
        print(f"signal {signum}: stopping after this step (again to stop at once)", file=sys.stderr)

    def check() -> None:
        if received:
            raise KeyboardInterrupt(f"signal {received[0]}")

    previous = {s: signal.signal(s, defer) for s in STOP_SIGNALS}
    try:
        yield check
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
