"""The one progress bar of the project: tqdm on a terminal, plain lines in a log.

:func:`progress_bar` takes tqdm's arguments. When stderr is not a terminal (redirected to a file, a
CI log) the bar writes whole lines, at most one every :data:`LINE_INTERVAL_S` seconds and a last one
when a kept bar closes, instead of ``\\r``-redrawn updates and cursor moves.
"""
from __future__ import annotations

import re
import sys
from typing import Any, TextIO

LINE_INTERVAL_S = 30.0  #: the least time between two lines of a bar in a log
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


def progress_bar(**kwargs: Any):
    """A ``tqdm(**kwargs)`` bar on stderr; plain lines when stderr is not a terminal."""
    from tqdm import tqdm

    stream = kwargs.get("file") or sys.stderr
    isatty = getattr(stream, "isatty", None)
    if isatty is None or not isatty():
        kwargs.update(file=_Lines(stream), dynamic_ncols=False, ncols=kwargs.get("ncols") or 100,
                      mininterval=max(kwargs.get("mininterval", 0.0), LINE_INTERVAL_S))
    return tqdm(**kwargs)
