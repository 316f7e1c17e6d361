"""Stopping a training cleanly before its end: on SIGTERM or SIGINT (a job scheduler's notice before
its time limit, ``kill``, Ctrl-C) or at a wall-clock budget (``train.max_minutes``).

The loop (:func:`hsicam.engine.loop.fit`) asks :meth:`StopRequests.reason` after every step (and
after fine-tuning's validation of its starting weights). A stop saves the ``last`` checkpoint of that
step and raises :class:`hsicam.errors.TrainingStopped` (the budget) or
:class:`hsicam.errors.TrainingInterrupted` (a signal; a ``KeyboardInterrupt``), so the same command
with ``--resume`` goes on from that step exactly (the loop's determinism). A signal during the last
step or the files written after it (final record, linear step) lets them finish first. A second
signal acts as it would without this module: Ctrl-C raises ``KeyboardInterrupt`` at once, a second
SIGTERM ends the process. Handlers are installed only in the main thread, for the loop's duration, and
only for signals not ignored (a job started with ``&`` ignores SIGINT, and keeps ignoring it).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time

log = logging.getLogger(__name__)

#: The signals that ask for a clean stop.
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)

#: Exit code of a training stopped by its time budget: EX_TEMPFAIL (sysexits.h), "try again later".
BUDGET_EXIT_CODE = 75


def _under_torchrun() -> bool:
    """Whether this process is a worker that torchrun started (it forwards the signals it receives to them)."""
    from hsicam.devices import dist_env

    return "TORCHELASTIC_RUN_ID" in os.environ or dist_env()[1] > 1


class StopRequests:
    """What asks a training to stop early: a signal received, or the budget of ``max_minutes``
    (minutes of wall-clock time since ``start``, a :func:`time.monotonic` value; default: now).

    A context manager: its handlers of :data:`STOP_SIGNALS` are in place inside the ``with`` block
    (when ``signals`` and in the main thread), the previous ones restored on exit."""

    def __init__(self, max_minutes: float | None = None, start: float | None = None, signals: bool = True) -> None:
        self.max_minutes = max_minutes
        self.start = time.monotonic() if start is None else start
        self.signals = signals
        self.armed = False  # the loop is between steps it can stop at; before and after, signals act as usual
        self.received: str | None = None  # the name of the first stop signal received while armed
        self._previous: dict[int, object] = {}

    # -- signals --------------------------------------------------------------------------------
    def __enter__(self) -> "StopRequests":
        if self.signals and threading.current_thread() is threading.main_thread():
            for s in STOP_SIGNALS:
                if signal.getsignal(s) is not signal.SIG_IGN:  # ignored (e.g. SIGINT of a job started with &): stays so
                    self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        self.armed = False
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame) -> None:
        if self.armed and self.received is None:
            self.received = signal.Signals(signum).name
            again = ("Ctrl-C again stops at once" if signum == signal.SIGINT else
                     "under torchrun, its SIGKILL after the grace period stops at once" if _under_torchrun() else
                     f"{self.received} again stops at once")
            log.warning("%s: stopping after this step and saving its checkpoint (%s)", self.received, again)
            return
        if self.armed and signum == signal.SIGTERM and _under_torchrun():
            # a scheduler's SIGTERM reaches the workers and torchrun, which forwards one more to each: the second, a
            # few ms later, killed a worker mid-step before it saved the step it stopped at. Under torchrun a repeated
            # SIGTERM is that echo; torchrun's SIGKILL after its grace period stays the hard stop (Ctrl-C still
            # stops at once)
            return
        previous = self._previous.get(signum, signal.SIG_DFL)  # not armed, or a second signal: as without us
        if callable(previous):
            previous(signum, frame)  # Ctrl-C: Python's default handler raises KeyboardInterrupt
        elif previous == signal.SIG_DFL:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)

    # -- the question the loop asks -------------------------------------------------------------
    def elapsed_s(self) -> float:
        return time.monotonic() - self.start

    def reason(self, next_step_s: float = 0.0) -> str | None:
        """Why to stop now, or None: the signal received, or the budget, which one more step of
        ``next_step_s`` seconds would overrun."""
        over = self.max_minutes is not None and self.elapsed_s() + next_step_s > 60.0 * self.max_minutes
        return self.describe(self.exit_code()) if self.received is not None or over else None

    def exit_code(self) -> int:
        """The exit code of a stop for :meth:`reason`: 128 + the signal's number, else the budget's."""
        if self.received is not None:
            return 128 + int(signal.Signals[self.received])
        return BUDGET_EXIT_CODE

    def describe(self, exit_code: int) -> str:
        """The reason for a stop of ``exit_code`` (another process's, in a DDP group)."""
        if exit_code > 128:
            return signal.Signals(exit_code - 128).name
        return f"train.max_minutes={self.max_minutes:g} reached, the budget of each session"
