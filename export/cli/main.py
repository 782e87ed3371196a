"""``python -m export [budget | verify] ...``: dispatch to the sub-commands and keep the error contract.

Exit status: 0 done / fits; 1 does not fit (or a verification failed); 2 bad input (a missing or
corrupt policy, an unwritable output path, ...). Errors are one line on stderr, never a traceback.
"""
from __future__ import annotations

import sys
from typing import Sequence

from kiloforge.errors import KiloforgeError

from ..errors import BudgetError, VerifyError
from .budget import run_budget
from .common import EXIT_FAIL, EXIT_USER_ERROR
from .firmware import run_export
from .verify import run_verify

COMMANDS = {"budget": run_budget, "verify": run_verify}


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m export`` / ``kiloforge-export``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in COMMANDS:
            return COMMANDS[argv[0]](argv[1:])
        return run_export(argv)
    except (BudgetError, VerifyError) as e:
        _err(str(e))
        return EXIT_FAIL
    except KiloforgeError as e:
        _err(str(e))
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        _err("interrupted; nothing written")
        return 130
