"""The one progress bar of the project: tqdm on a terminal, plain lines in a log.

:func:`progress_bar` takes tqdm's arguments. When stderr is not a terminal (redirected to a file, a
CI log) the bar writes whole lines, at most one every :data:`LINE_INTERVAL_S` seconds and a last one
when it closes (a transient bar too: a log keeps what was done), instead of ``\\r``-redrawn updates and
cursor moves. With ``max_seconds``
(a run with a time budget as well as ``total`` units of work) the bar measures whichever budget runs
out first (:class:`BudgetBar`), so its percentage and ETA are those of the run that will happen.
"""
from __future__ import annotations

import re
import sys
import time
from typing import Any, TextIO

LINE_INTERVAL_S = 10.0  #: the least time between two lines of a bar in a log
_CONTROL = re.compile(r"\r|\x1b\[[0-9;]*[A-Za-z]")  #: tqdm's redraw: carriage returns, cursor moves


class _Lines:
    """A stream for tqdm that turns each redraw into one line and drops blank ones and cursor moves."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = _CONTROL.sub("", text).strip()
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


class BudgetBar:
    """A bar over two budgets, ``total`` units of work and ``max_seconds`` of wall time (``elapsed`` of
    it already spent, e.g. by an earlier session of a resumed run): it stands at the larger of the two
    fractions spent, in seconds of the time budget, so its ETA is when the first budget runs out. The
    work done shows as ``work/total unit`` before the caller's postfix. Same methods as a tqdm bar."""

    def __init__(self, bar: Any, total: int, max_seconds: float, initial: int, elapsed: float, unit: str) -> None:
        self.bar, self.total, self.max_seconds, self.unit = bar, total, max_seconds, unit
        self.work, self.postfix = initial, ""
        self.start = time.perf_counter() - elapsed
        self._advance()

    def fraction(self) -> float:
        """The share of the run done: the larger of work and time spent over their budgets, at most 1."""
        spent = (time.perf_counter() - self.start) / self.max_seconds
        return min(1.0, max(self.work / self.total if self.total else 1.0, spent))

    def _advance(self) -> None:
        self.bar.update(self.fraction() * self.max_seconds - self.bar.n)
        self.bar.set_postfix_str(f"{self.work:,}/{self.total:,} {self.unit}" + (f"  {self.postfix}" if self.postfix
                                                                                  else ""), refresh=False)

    def update(self, n: int = 1) -> None:
        self.work += n
        self._advance()

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        self.postfix = s
        self._advance()
        if refresh:
            self.bar.refresh()

    def write(self, s: str) -> None:
        self.bar.write(s)

    def close(self) -> None:
        self.bar.close()


def progress_bar(*, max_seconds: float | None = None, elapsed: float = 0.0, **kwargs: Any):
    """A ``tqdm(**kwargs)`` bar on stderr; plain lines when stderr is not a terminal; a :class:`BudgetBar`
    over ``total`` and a time budget when ``max_seconds`` is given (> 0)."""
    from tqdm import tqdm

    if max_seconds:
        total, initial, unit = kwargs.pop("total"), kwargs.pop("initial", 0), kwargs.pop("unit", "it")
        spent = min(1.0, max(initial / total if total else 1.0, elapsed / max_seconds))
        kwargs.update(total=max_seconds, initial=spent * max_seconds,  # the rate (ETA) counts this session only
                      bar_format="{l_bar}{bar}| {elapsed}<{remaining}{postfix}")
        return BudgetBar(progress_bar(**kwargs), total, max_seconds, initial, elapsed, unit)
    stream = kwargs.get("file") or sys.stderr
    isatty = getattr(stream, "isatty", None)
    if isatty is None or not isatty():
        kwargs.update(file=_Lines(stream), dynamic_ncols=False, ncols=kwargs.get("ncols") or 100, leave=True,
                      mininterval=max(kwargs.get("mininterval", 0.0), LINE_INTERVAL_S))
    return tqdm(**kwargs)
