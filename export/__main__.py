"""``python -m export`` / ``kiloforge-export``: see :mod:`export.cli.main`."""
from __future__ import annotations

import sys
from typing import Sequence

from kiloforge.interrupts import run_entry_point


def _load():
    from .cli.main import main

    return main


def main(argv: Sequence[str] | None = None) -> int:
    """:func:`export.cli.main.main`, with a Ctrl-C while its modules load ending in the same one line."""
    return run_entry_point(_load, argv, "error: interrupted; nothing written (files from an earlier run are unchanged)")


if __name__ == "__main__":
    from kiloforge.cli import run_guarded

    sys.exit(run_guarded("python -m export", lambda: main, sys.argv[1:]))
