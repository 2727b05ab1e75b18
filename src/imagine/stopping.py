"""Stopping cleanly on SIGINT and SIGTERM: the loops that train (one run, or a study's runner)
note the signal, finish the unit of work they are in, write a checkpoint and raise
:class:`~imagine.errors.Interrupted`, which the command line turns into exit status 128 + n."""

from __future__ import annotations

import signal
import threading
from typing import Any


class StopSignals:
    """While active, SIGINT and SIGTERM only set ``signal`` (the training loop checkpoints and
    stops at the end of the episode); outside the main thread it does nothing."""

    def __init__(self) -> None:
        self.signal = 0
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
