"""Signals in in-process tests: run the handler the code under test installed, at a chosen moment."""
from __future__ import annotations

import signal


def deliver(signum: int) -> None:
    """Run the handler installed for ``signum`` here and now, as the interpreter would on delivery. A raised
    signal is handled at the interpreter's next check, which can fall inside a finalizer run by the garbage
    collector, where CPython prints and drops the exception: the test would then be about that timing."""
    handler = signal.getsignal(signum)
    assert callable(handler), f"no Python handler for {signal.Signals(signum).name}: {handler!r}"
    handler(signum, None)
