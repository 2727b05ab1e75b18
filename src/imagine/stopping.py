"""Stopping cleanly on SIGINT and SIGTERM: the loops that train (one run, or a study's runner)
note the signal, finish the unit of work they are in, write a checkpoint and raise
:class:`~imagine.errors.Interrupted`, which the command line turns into exit status 128 + n."""

from __future__ import annotations

import signal
import threading
from typing import Any

_pending = 0
"""A signal that reached this process while no :class:`StopSignals` was active (set only in a
study's worker processes, see :func:`note_signals_when_idle`)."""


def _note(number: int, frame: Any) -> None:
    global _pending
    _pending = number


def note_signals_when_idle() -> None:
    """For a study's worker processes, at their start: SIGINT and SIGTERM between jobs are noted
    instead of killing the worker. Ctrl-C (or ``timeout``) signals the whole process group, and
    the study forwards the signal to its workers as well, so a worker whose job has just
    stopped gets a second one while idle; left to the default action it dies and takes the
    process pool with it. A noted signal stops the next job before it trains."""
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, _note)


class StopSignals:
    """While active, SIGINT and SIGTERM only set ``signal`` (the training loop checkpoints and
    stops at the end of the episode); outside the main thread it does nothing. It starts with
    a signal a worker noted while idle (:func:`note_signals_when_idle`)."""

    def __init__(self) -> None:
        self.signal = _pending
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def _handle(self, number: int, frame: Any) -> None:
        self.signal = number

    def __exit__(self, *exc: object) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)
