"""``python -m export`` / ``kiloforge-export``: see :mod:`export.cli.main`."""
from __future__ import annotations

import signal
import sys
from typing import Any, Sequence

INTERRUPTED = "error: interrupted; nothing written (files from an earlier run are unchanged)"


def main(argv: Sequence[str] | None = None) -> int:
    """:func:`export.cli.main.main`; a Ctrl-C while its modules load ends in the same one line (NumPy turns an
    interrupted import into an ImportError, hence the flag), and one after the work is done cannot undo it."""
    got: list[int] = []

    def on_sigint(signum: int, frame: Any) -> None:
        got.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        from .cli.main import main as run
    except BaseException:
        if got:
            print(INTERRUPTED, file=sys.stderr)
            return 130
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
    if got:
        print(INTERRUPTED, file=sys.stderr)
        return 130
    status = run(argv)
    for s in (signal.SIGINT, signal.SIGTERM):  # finished: only the exit is left
        signal.signal(s, signal.SIG_IGN)
    return status


if __name__ == "__main__":
    sys.exit(main())
