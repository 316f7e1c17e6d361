"""A call that fails the test instead of hanging (SIGALRM): :func:`guarded`."""

from __future__ import annotations

import signal

import pytest


class Hung(AssertionError):
    """Raised by :func:`guarded`'s alarm (the command's error boundary re-raises it, as any bug)."""


def guarded(fn, *args, seconds: int = 30):
    """``fn(*args)``, failing the test instead of hanging when it runs past ``seconds`` (far above what it takes when
    it works)."""

    def hung(signum, frame):
        raise Hung()

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        return fn(*args)
    except Hung:
        pass  # failed below, outside this handler: pytest cannot show the frame a signal interrupted
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    pytest.fail(f"{getattr(fn, '__name__', fn)} still running after {seconds} s")
