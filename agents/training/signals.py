"""Stopping a training run on SIGINT or SIGTERM: the first signal asks for a stop
(:class:`StopRequest`; SB3 training then ends at its next step with a checkpoint), a second stops
at once; the run ends with :class:`TrainingInterrupted`."""
from __future__ import annotations

import contextlib
import signal
import sys
import threading
from typing import Any


class StopRequest:
    """A request to stop training: the name of the signal that asked (None: none yet)."""

    def __init__(self) -> None:
        self.signal: str | None = None


class TrainingInterrupted(KeyboardInterrupt):
    """Training stopped by a signal (or Ctrl-C); ``run.json`` records ``status: "interrupted"``
    and the last checkpoint, from which ``--resume`` continues."""

    def __init__(self, signal_name: str, timesteps_done: int, run: dict[str, Any] | None = None):
        super().__init__(f"training interrupted by {signal_name} after {timesteps_done} "
                         f"timesteps")
        self.signal_name, self.timesteps_done, self.run = signal_name, timesteps_done, run

    def __reduce__(self):  # back from a worker process of a sweep
        return type(self), (self.signal_name, self.timesteps_done, self.run)


@contextlib.contextmanager
def stop_on_signals(stop: StopRequest, graceful: bool = True):
    """SIGINT and SIGTERM, while the block runs, request a stop (``stop.signal``): with
    ``graceful`` the first only sets it (training ends at its next step and checkpoints), a
    second raises KeyboardInterrupt; without, the first raises it. The previous handlers are
    restored after the block (handlers exist only in the main thread: elsewhere, a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum: int, frame: Any) -> None:
        name = signal.Signals(signum).name
        first = stop.signal is None
        stop.signal = stop.signal or name
        if graceful and first:
            print(f"\n{name}: stopping at the next step and saving a checkpoint (send it again to "
                  f"stop at once)", file=sys.stderr, flush=True)
            return
        raise KeyboardInterrupt(name)

    sigs = (signal.SIGINT, signal.SIGTERM)
    old = {s: signal.getsignal(s) for s in sigs}
    try:
        for s in sigs:
            signal.signal(s, handler)
        yield stop
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)
