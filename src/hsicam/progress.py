"""Progress of long loops, the one place for it: a tqdm bar on a terminal, INFO log lines elsewhere.

A loop over N items (scenes, tiles, sweep points) wraps itself in :class:`Progress`. On a terminal
(stderr a tty) it shows a tqdm bar; otherwise (CI, ``nohup``, a log file) it logs
``{desc}: k/N {unit} … elapsed, eta`` lines at INFO on the ``hsicam.progress`` logger (stderr
under the CLI, never stdout), the first and the last item always and the others at most every
``every_s`` seconds (0: one line per item, for items that take seconds each). ``show=False``:
nothing at all. (The training loop, :mod:`hsicam.engine.loop`, keeps its own step lines, which
carry the loss.)
"""

from __future__ import annotations

import logging
import math
import sys
import time
from typing import Iterable, Iterator, TypeVar

log = logging.getLogger("hsicam.progress")
T = TypeVar("T")


def format_seconds(s: float) -> str:
    """A duration for a person: ``4.2 s``, ``37 s``, ``3m05s``, ``1h02m``; ``?`` when not finite."""
    s = float(s)
    if not math.isfinite(s):
        return "?"
    s = max(0.0, s)
    if s < 60:
        return f"{s:.1f} s" if s < 10 else f"{s:.0f} s"
    m, sec = divmod(int(round(s)), 60)
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m" if h else f"{m}m{sec:02d}s"


class Progress:
    """Count ``total`` items done: a tqdm bar on a terminal, else throttled INFO lines with k/N and an ETA.

    Args:
        total: the number of items (0: an empty job, one line ``{desc}: 0/0 {unit}s, nothing to do`` and no bar).
        desc: what is done (the line's start, e.g. ``"data synth"``).
        unit: what an item is (``"scene"``, ``"tile"``).
        show: None: a bar on a terminal, lines otherwise; True: the bar; False: nothing.
        every_s: least seconds between two lines (the first and the last item always get one).
        initial: items done before this count began (a resumed job): counted in k/N, left out of the ETA's rate.
    """

    def __init__(self, total: int, desc: str, unit: str = "item", show: bool | None = None, every_s: float = 10.0,
                 initial: int = 0):
        self.total, self.desc, self.unit, self.every_s = int(total), desc, unit, float(every_s)
        if self.total < 0:
            raise ValueError(f"total must be >= 0 (the number of items), got {total}")
        if not 0 <= initial <= self.total:
            raise ValueError(f"initial must be in [0, total={self.total}] (the items done before), got {initial}")
        self.done = self.initial = int(initial)
        self.t0 = self._last = time.perf_counter()
        self._lines = show is None and not sys.stderr.isatty()
        self._bar = None
        if self.total == 0:  # nothing to count: said once (a line would read "1/0", a bar a bare counter)
            if show is not False:
                log.info("%s: 0/0 %ss, nothing to do", desc, unit)
            self._lines = False
            return
        if show is not False and not self._lines:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, dynamic_ncols=True, initial=self.initial)

    def update(self, n: int = 1, note: str = "") -> None:
        """``n`` more items done; ``note`` (e.g. the item's name and time) ends its line."""
        self.done += n
        if self._bar is not None:
            self._bar.update(n)
            return
        if not self._lines:
            return
        now = time.perf_counter()
        if self.done not in (self.initial + 1, self.total) and self.done < self.total and now - self._last < self.every_s:
            return
        self._last = now
        elapsed = now - self.t0
        left, new = self.total - self.done, self.done - self.initial  # the rate: of the items done in this count
        eta = f", eta {format_seconds(elapsed / new * left)}" if 0 < left and new > 0 else ""
        log.info("%s: %d/%d %s%s (%s elapsed%s)", self.desc, self.done, self.total, self.unit + ("" if self.total == 1 else "s"),
                 f" {note}" if note else "", format_seconds(elapsed), eta)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress(items: Iterable[T], total: int, desc: str, unit: str = "item", show: bool | None = None,
             every_s: float = 10.0) -> Iterator[T]:
    """``items`` with a :class:`Progress` counted after each one's body has run."""
    with Progress(total, desc, unit, show, every_s) as p:
        for x in items:
            yield x
            p.update()
