"""The console scripts of ``[project.scripts]``: ``kiloforge``, ``kiloforge-sim``, ``kiloforge-export``,
``kiloforge-learn`` (the commands are :mod:`kiloforge.cli`).

Imported by a script wrapper (the program's name, ``sys.argv[0]``, starts with ``kiloforge``), its first
lines hold a Ctrl-C or SIGTERM back for the rest of the process, as a ``__main__`` module run as the program
does, until :func:`kiloforge.interrupts.run_entry_point` takes over and looks at what they held: without them a
Ctrl-C while :mod:`kiloforge.cli` loads (tens of milliseconds) would end in a traceback. Imported by anything
else (a test), it leaves the handlers alone.
"""

import sys  # built in, loaded at start-up

from .sighold import hold

_WRAPPER = bool(sys.argv) and sys.argv[0].replace("\\", "/").rpartition("/")[2].startswith("kiloforge")
_held: list[int] = hold()[0] if _WRAPPER else []

from . import cli  # noqa: E402  (after the holders)


def kiloforge() -> int:
    """``kiloforge``."""
    return cli.main(held=_held)


def sim() -> int:
    """``kiloforge-sim``."""
    return cli.sim_script(_held)


def export() -> int:
    """``kiloforge-export``."""
    return cli.export_script(_held)


def learn() -> int:
    """``kiloforge-learn``."""
    return cli.learn_script(_held)
