"""The console scripts of ``[project.scripts]``: ``kiloforge``, ``kiloforge-sim``, ``kiloforge-export``,
``kiloforge-learn`` (the commands are :mod:`kiloforge.cli`).

Imported by a script wrapper (the program's name, ``sys.argv[0]``, starts with ``kiloforge``), its first
lines hold a Ctrl-C or SIGTERM back for the rest of the process, as a ``__main__`` module run as the program
does, until :func:`kiloforge.interrupts.run_entry_point` takes over and looks at what they held: without them a
Ctrl-C while :mod:`kiloforge.cli` loads (tens of milliseconds) would end in a traceback. Imported by anything
else (a test), it leaves the handlers alone.
"""

import _signal  # built in: loads before anything that could be interrupted
import sys  # built in, loaded at start-up

_held: list[int] = []
if sys.argv and sys.argv[0].replace("\\", "/").rpartition("/")[2].startswith("kiloforge"):
    for _s in (_signal.SIGINT, _signal.SIGTERM):
        _signal.signal(_s, lambda signum, frame: _held.append(signum))

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
