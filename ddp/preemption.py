"""Stopping signals during training: SIGTERM and SIGHUP end a run like Ctrl-C, with a checkpoint.

A cluster scheduler sends SIGTERM (or SIGHUP) before it preempts a job.
:func:`stop_signals` turns them into :class:`Preempted`, a ``KeyboardInterrupt``
subclass, so the trainer's Ctrl-C path writes its checkpoint. Inside the
training loop :func:`stop_requests` only records them: the trainer stops at the
next step boundary, where weights, optimiser, EMA, noise streams and step
counter agree (a signal raised in the middle of an update would checkpoint a
step half-applied), and under torchrun every rank stops at the same step. While a
checkpoint is being written, :func:`signals_deferred` holds SIGINT, SIGTERM
and SIGHUP back (a second Ctrl-C during the save is noted, not raised into the
middle of the write) and reports what arrived once the file is complete.
"""

from __future__ import annotations

import contextlib
import signal
import threading

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


class Preempted(KeyboardInterrupt):
    """Training was stopped by a signal (SIGTERM, SIGHUP); a checkpoint was written."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")

    def __reduce__(self):  # a pool worker sends it back to the suite pickled: rebuild it from the signal
        return type(self), (self.signum,)


def resume_hint(no_resume: bool) -> str:
    """How a stopped command goes on: run again with ``--no-resume`` it would set the checkpoint just saved aside."""
    return "rerun without --no-resume to resume" if no_resume else "the same command resumes"


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_preempted(signum, frame):
    raise Preempted(signum)


@contextlib.contextmanager
def stop_signals():
    """Within the block, SIGTERM and SIGHUP raise :class:`Preempted` (main thread only)."""
    if not _main_thread():
        yield
        return
    # a signal set to be ignored (SIGHUP under nohup) stays ignored
    previous = {s: signal.signal(s, _raise_preempted) for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def signals_deferred(received: list[int] | None = None):
    """Within the block, SIGINT / SIGTERM / SIGHUP are recorded in ``received`` instead of acting."""
    received = [] if received is None else received
    if not _main_thread():
        yield received
        return
    signals = [s for s in (signal.SIGINT, *STOP_SIGNALS) if signal.getsignal(s) is not signal.SIG_IGN]
    previous = {s: signal.signal(s, lambda signum, frame: received.append(signum)) for s in signals}
    try:
        yield received
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def interruption(signum: int) -> KeyboardInterrupt:
    """The exception a deferred signal stands for."""
    return KeyboardInterrupt() if signum == signal.SIGINT else Preempted(signum)


@contextlib.contextmanager
def stop_requests(requested: list[int] | None = None):
    """Within the block, SIGINT / SIGTERM / SIGHUP are recorded in the yielded list for the caller to act on
    at a point of its choosing; a second SIGINT (Ctrl-C pressed again) raises ``KeyboardInterrupt`` at once."""
    requested = [] if requested is None else requested
    if not _main_thread():
        yield requested
        return

    def record(signum, frame):
        if signum == signal.SIGINT and signal.SIGINT in requested:
            raise KeyboardInterrupt
        requested.append(signum)

    signals = [s for s in (signal.SIGINT, *STOP_SIGNALS) if signal.getsignal(s) is not signal.SIG_IGN]
    previous = {s: signal.signal(s, record) for s in signals}
    try:
        yield requested
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
