"""SIGINT and SIGTERM held back while a command line's modules load (:mod:`kiloforge.interrupts` takes over).

The ``__main__`` modules and :mod:`kiloforge.scripts` call :func:`hold` in their first lines, before any other
import (this module imports only the built-in ``_signal``), and :func:`release` after their imports. Run as
the program they go on holding until :func:`kiloforge.interrupts.run_entry_point` installs its own handler and
looks at the list; imported by anything else they give the previous handlers back.
"""
import _signal

SIGNALS = (_signal.SIGINT, _signal.SIGTERM)


def hold() -> tuple[list[int], dict]:
    """Handlers that append each signal's number to a list: (that list, the handlers they replaced)."""
    held: list[int] = []
    previous = {s: _signal.signal(s, lambda signum, frame: held.append(signum)) for s in SIGNALS}
    return held, previous


def release(previous: dict, program: bool) -> None:
    """Put the ``previous`` handlers back, unless this is the program (which holds on)."""
    if not program:
        for s, h in previous.items():
            _signal.signal(s, _signal.default_int_handler if h is None else h)
