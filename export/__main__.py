"""``python -m export`` / ``kiloforge-export``: see :mod:`export.cli.main`."""
from __future__ import annotations

import sys
from typing import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """:func:`export.cli.main.main`, with a Ctrl-C while its modules load ending in the same one line."""
    try:
        from .cli.main import main as run
    except KeyboardInterrupt:
        print("error: interrupted; nothing written (files from an earlier run are unchanged)", file=sys.stderr)
        return 130
    return run(argv)


if __name__ == "__main__":
    sys.exit(main())
