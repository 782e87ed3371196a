"""Run ``python -m PACKAGE ARGS...`` with a signal raised at the N-th line executed in the traced functions.

    python signal_at_line.py SIGNAL N TRACED PACKAGE [ARGS...]

PACKAGE ``module:function`` runs ``sys.exit(function())`` instead, as a console-script wrapper does.
TRACED is a comma-separated list of ``path`` (every function of a file) or ``path:function``, paths relative
to the repository. Lines are counted from the moment both SIGINT and SIGTERM have Python handlers (the
``__main__`` module's first lines installed its holders; before that, CPython's default is all there is).
N = 0 raises nothing and prints the number of lines counted to stderr as ``lines: K`` when the program exits.
"""
from __future__ import annotations

import atexit
import importlib
import os
import runpy
import signal
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def main() -> None:
    signum, n, traced, package, args = signal.Signals[sys.argv[1]], int(sys.argv[2]), sys.argv[3], sys.argv[4], sys.argv[5:]
    targets = [(os.path.join(ROOT, path), function or None)
               for path, _, function in (t.partition(":") for t in traced.split(","))]
    count = 0

    def held() -> bool:
        return (signal.getsignal(signal.SIGINT) is not signal.default_int_handler
                and callable(signal.getsignal(signal.SIGTERM)))

    def tracer(frame, event, arg):
        nonlocal count
        if event == "call":
            code = frame.f_code
            wanted = any(code.co_filename == path and function in (None, code.co_name) for path, function in targets)
            return tracer if wanted else None
        if event == "line" and (count or held()):
            count += 1
            if count == n:
                sys.settrace(None)
                signal.raise_signal(signum)
                return None
        return tracer

    if n == 0:
        atexit.register(lambda: print(f"lines: {count}", file=sys.stderr))
    sys.argv = ["kiloforge-script" if ":" in package else package, *args]  # a script wrapper's argv[0]
    sys.settrace(tracer)
    if ":" in package:
        module, _, function = package.partition(":")
        sys.exit(getattr(importlib.import_module(module), function)())
    runpy.run_module(package, run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    main()
