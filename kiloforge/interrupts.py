"""Ctrl-C and SIGTERM for the command lines: an honest stop with exit status 128 + signal.

* :class:`Interrupted` is the ``KeyboardInterrupt`` a SIGTERM raises under :func:`terminate_raises`
  (a SIGINT raises Python's own ``KeyboardInterrupt``); :func:`exit_status` maps either to 130 / 143;
* :func:`deferred` holds SIGINT and SIGTERM back while a block that must not be cut in two runs
  (:mod:`kiloforge.io` publishing a set of files), and raises :class:`Interrupted` after it;
* :func:`run_entry_point` is what a ``__main__`` module runs: it loads the command's modules with
  Ctrl-C (or SIGTERM) ending in one line (NumPy and torch turn an interrupted import into an ImportError), runs
  the command, and ignores signals once the program (``argv`` None, or :func:`as_program`) has returned
  (nothing is left to interrupt). A ``__main__`` module's first lines hold a Ctrl-C or SIGTERM back
  (:mod:`kiloforge.sighold`, before this module and its imports load) and pass what they held as ``held``;
  run as the program they keep holding until :func:`run_entry_point` takes over, so no moment is left to
  Python's default handler (a traceback).

Handlers can only be installed from the main thread; elsewhere both are no-ops (Python delivers
``KeyboardInterrupt`` to the main thread only).
"""
from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

from .sighold import SIGNALS


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


_program = False  #: set by :func:`as_program`: the command run is this process's own command line
_held_before: Sequence[int] = ()  #: what an outer ``__main__`` module (``python -m kiloforge``) holds back


@contextmanager
def as_program(held: Sequence[int] = ()) -> Iterator[None]:
    """Within the block the command run is this process's own command line: once :func:`run_entry_point` has
    run it, only the exit is left, and signals are ignored (in-process callers, tests, keep their handlers).
    ``held``: the list an outer ``__main__`` module's holders append to, looked at with its own."""
    global _program, _held_before
    before = _program, _held_before
    _program, _held_before = True, held
    try:
        yield
    finally:
        _program, _held_before = before


def run_entry_point(load: Callable[[], Callable[[Sequence[str] | None], int]], argv: Sequence[str] | None,
                    message: str, held: Sequence[int] = ()) -> int:
    """``load()`` (the imports of a command, returning its ``main``), then ``main(argv)``; a SIGINT or SIGTERM
    while loading, one already ``held`` back by the ``__main__`` module's first lines, or one that leaves
    ``main`` before its own handling began, prints ``message`` and returns 128 + the signal (130 / 143).

    One handler covers the whole call, so no moment is left to Python's default: a signal inside the command
    (or its imports) raises there (``KeyboardInterrupt`` / :class:`Interrupted`), one between the steps of this
    function is held and looked at. Once ``main`` has returned, a program (``argv`` None or :func:`as_program`)
    ignores signals; an in-process caller gets its handlers back."""
    import sys

    here = sys._getframe().f_code
    got: list[int] = []

    def on_signal(signum: int, frame: Any) -> None:
        got.append(signum)
        if frame is None or frame.f_code is not here:
            raise KeyboardInterrupt if signum == signal.SIGINT else Interrupted(signum)

    main_thread = _main_thread()
    finishing = main_thread and (argv is None or _program)
    previous = {s: signal.signal(s, on_signal) for s in SIGNALS} if main_thread else {}
    try:
        main = None
        held = [*held, *_held_before]
        if not held:
            try:
                main = load()
            except BaseException:
                if not got:
                    raise
        if held or got:
            print(message, file=sys.stderr)
            return 128 + (held or got)[0]
        try:
            return main(argv)
        except KeyboardInterrupt as e:  # before the command's own handling of a Ctrl-C began: nothing done
            print(message, file=sys.stderr)
            return exit_status(e)
    except BaseException:  # an error on its way to the caller, who reports it: the handlers go back
        finishing = False
        raise
    finally:
        for s, h in previous.items():
            if finishing:
                signal.signal(s, signal.SIG_IGN)
            else:
                _restore(s, h)
