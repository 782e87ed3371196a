"""``python -m sim`` / ``kiloforge-sim``: see :mod:`kiloforge.sim_cli`.

The command plays policy artifacts (:mod:`kiloforge.policies`), which build on the simulator, so it lives on
the floor above ``sim``; this module, the program, only starts it (docs/design.md, "Dependencies run one way").
"""

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
    from kiloforge.sim_cli import main

    return main


def main(argv: Sequence[str] | None = None) -> int:
    """:func:`kiloforge.sim_cli.main`, with a Ctrl-C or SIGTERM while its modules load ending in one line (130 / 143)."""
    from kiloforge.cliparse import program

    return run_entry_point(_load, argv, f"{program('python -m sim')}: interrupted while starting; nothing written",
                           _held if argv is None else ())


if __name__ == "__main__":
    sys.exit(run_guarded("python -m sim", lambda: main, None))
