"""Stopping cleanly on SIGINT and SIGTERM: the loops that train (one run, or a study's runner)
note the signal, finish the unit of work they are in, write a checkpoint and raise
:class:`~imagine.errors.Interrupted`, which the command line turns into exit status 128 + n."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
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


def die_with_parent(parent: int) -> None:
    """For a study's worker processes, at their start (Linux): SIGKILL this process when the
    study's process ``parent`` dies. The study holds its folders' lock
    (:func:`imagine.study.experiments.folder_lock`), which the kernel releases when it dies,
    however it dies; a worker left running after a ``kill -9`` of the study would go on writing
    run folders that a second study may then take over, two writers on one run. Killed with
    its study, the worker leaves its runs at their last checkpoint (every file is written
    atomically), from which the next study resumes them. Elsewhere a no-op."""
    if not sys.platform.startswith("linux"):
        return
    pr_set_pdeathsig = 1
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(pr_set_pdeathsig, signal.SIGKILL, 0, 0, 0) != 0:
        return  # not allowed here: keep the old behaviour rather than fail the study
    if os.getppid() != parent:  # the parent died before prctl took effect
        os.kill(os.getpid(), signal.SIGKILL)


def start_study_worker(parent: int) -> None:
    """The initializer of a study's worker processes: :func:`note_signals_when_idle` and
    :func:`die_with_parent`."""
    note_signals_when_idle()
    die_with_parent(parent)


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
