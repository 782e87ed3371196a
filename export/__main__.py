"""``python -m export`` / ``kiloforge-export``: see :mod:`export.cli.main`."""

import _signal  # built in: a Ctrl-C or SIGTERM while the imports below load is held back (kiloforge.interrupts)

_held: list[int] = []
_previous = {_s: _signal.signal(_s, lambda signum, frame: _held.append(signum))
             for _s in (_signal.SIGINT, _signal.SIGTERM)}
try:
    import sys
    from typing import Sequence

    from kiloforge.cli import run_guarded
    from kiloforge.interrupts import run_entry_point
finally:
    if __name__ != "__main__":  # run as the program: held until kiloforge.interrupts.run_entry_point takes over
        for _s, _h in _previous.items():
            _signal.signal(_s, _signal.default_int_handler if _h is None else _h)


def _load():
    from .cli.main import main

    return main


def main(argv: Sequence[str] | None = None) -> int:
    """:func:`export.cli.main.main`, with a Ctrl-C while its modules load ending in the same one line."""
    from kiloforge.cliparse import error_line, program

    return run_entry_point(_load, argv, error_line(program("python -m export"), "interrupted; nothing written (files "
                                                   "from an earlier run are unchanged)"), _held)


if __name__ == "__main__":
    sys.exit(run_guarded("python -m export", lambda: main, None))
