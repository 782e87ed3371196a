"""``python -m export`` / ``kiloforge-export``: see :mod:`export.cli.main`."""

from kiloforge.sighold import hold, release  # first: a Ctrl-C or SIGTERM while the imports below load is held

_held, _previous = hold()
try:
    import sys
    from typing import Sequence

    from kiloforge.cli import run_guarded
    from kiloforge.interrupts import run_entry_point
finally:
    release(_previous, program=__name__ == "__main__")


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
