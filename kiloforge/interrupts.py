"""Ctrl-C and SIGTERM for the command lines: an honest stop with exit status 128 + signal.

* :class:`Interrupted` is the ``KeyboardInterrupt`` a SIGTERM raises under :func:`terminate_raises`
  (a SIGINT raises Python's own ``KeyboardInterrupt``); :func:`exit_status` maps either to 130 / 143;
* :func:`deferred` holds SIGINT and SIGTERM back while a block that must not be cut in two runs
  (:mod:`kiloforge.io` publishing a set of files), and raises :class:`Interrupted` after it;
* :func:`run_entry_point` is what a ``__main__`` module runs: it loads the command's modules with
  Ctrl-C (or SIGTERM) ending in one line (NumPy and torch turn an interrupted import into an ImportError), runs
  the command, and ignores signals once the program (``argv`` None) has returned (nothing is left to
  interrupt). A ``__main__`` module's first lines hold a Ctrl-C or SIGTERM back (with the built-in ``_signal``,
  before this module and its imports load) and pass what they held as ``held``.

Handlers can only be installed from the main thread; elsewhere both are no-ops (Python delivers
``KeyboardInterrupt`` to the main thread only).
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A stop requested by a signal (``signum``)."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = signum


def exit_status(exc: BaseException) -> int:
    """128 + the signal number: 130 for SIGINT (a plain KeyboardInterrupt), 143 for SIGTERM."""
    return 128 + int(getattr(exc, "signum", signal.SIGINT))


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _restore(signum: int, handler: Any) -> None:
    signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: set outside Python


@contextmanager
def terminate_raises() -> Iterator[None]:
    """Within the block a SIGTERM raises :class:`Interrupted` (so the same clean-up runs as for Ctrl-C)."""
    if not _main_thread():
        yield
        return

    def on_term(signum: int, frame: Any) -> None:
        raise Interrupted(signum)

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        yield
    finally:
        _restore(signal.SIGTERM, previous)


@contextmanager
def deferred() -> Iterator[None]:
    """Run the block with SIGINT / SIGTERM held back; if one came, raise :class:`Interrupted` after it."""
    if not _main_thread():
        yield
        return
    got: list[int] = []
    previous = {s: signal.signal(s, lambda signum, frame: got.append(signum)) for s in SIGNALS}
    try:
        yield
    finally:
        for s, h in previous.items():
            _restore(s, h)
    if got:
        raise Interrupted(got[0])


def run_entry_point(load: Callable[[], Callable[[Sequence[str] | None], int]], argv: Sequence[str] | None,
                    message: str, held: Sequence[int] = ()) -> int:
    """``load()`` (the imports of a command, returning its ``main``), then ``main(argv)``; a SIGINT or SIGTERM
    while loading, or one already ``held`` back by the ``__main__`` module's first lines, prints ``message``
    and returns 128 + the signal (130 / 143)."""
    import sys

    if held:
        print(message, file=sys.stderr)
        return 128 + held[0]
    got: list[int] = []

    def on_signal(signum: int, frame: Any) -> None:
        got.append(signum)
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in SIGNALS} if _main_thread() else {}
    try:
        main = load()
    except BaseException:
        if not got:
            raise
    finally:
        for s, h in previous.items():
            _restore(s, h)
    if got:
        print(message, file=sys.stderr)
        return 128 + got[0]
    status = main(argv)
    if argv is None and _main_thread():  # the program (argv from sys.argv) has finished: only the exit is left
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
    return status
