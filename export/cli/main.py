"""``python -m export [budget | verify | rehash] ...``: dispatch to the sub-commands and keep the error contract.

Exit status: 0 done / fits; 1 does not fit (or a verification failed); 2 bad input (a missing or
corrupt policy, an unwritable output path, ...); 130 / 143 interrupted by SIGINT / SIGTERM (with
what was written, if anything). Errors are one line on stderr, never a traceback.
"""
from __future__ import annotations

import sys
from typing import Sequence

from kiloforge import io
from kiloforge.cliparse import error_line, program
from kiloforge.errors import KiloforgeError
from kiloforge.interrupts import exit_status, terminate_raises

from ..errors import BudgetError, VerifyError
from .budget import run_budget
from .common import EXIT_FAIL, EXIT_USER_ERROR
from .firmware import run_export
from .rehash import run_rehash
from .verify import run_verify

COMMANDS = {"budget": run_budget, "verify": run_verify, "rehash": run_rehash}


def _err(argv: Sequence[str], msg: str) -> None:
    """``<program>: error: <msg>``, the program being the sub-command (``python -m export verify``)."""
    name = "python -m export" + (f" {argv[0]}" if argv and argv[0] in COMMANDS else "")
    print(error_line(program(name), msg), file=sys.stderr)


def interrupted_message(written: list) -> str:
    """What an interrupted command really left: the sets it had published completely, or nothing."""
    if written:
        return (f"interrupted after writing {', '.join(str(p) for p in written)} (complete); "
                "nothing else was changed")
    return "interrupted; nothing written (files from an earlier run are unchanged)"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m export`` / ``kiloforge-export``; returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    mark = io.published_count()
    try:
        with terminate_raises():
            if argv and argv[0] in COMMANDS:
                return COMMANDS[argv[0]](argv[1:])
            return run_export(argv)
    except (BudgetError, VerifyError) as e:
        _err(argv, str(e))
        return EXIT_FAIL
    except KiloforgeError as e:
        _err(argv, str(e))
        return EXIT_USER_ERROR
    except KeyboardInterrupt as e:
        _err(argv, interrupted_message(io.published_since(mark)))
        return exit_status(e)
