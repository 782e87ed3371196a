"""The external programs the verification ladder runs, resolved in one place.

* the host C compiler: ``$CC`` split with :func:`shlex.split` (``CC="gcc -O2"`` is the program ``gcc`` with
  the flag ``-O2``; unset or empty: ``gcc``), its program found on ``PATH`` and probed once per process
  by compiling and linking a one-line C program: a ``CC`` that is not a working C compiler
  (``/bin/true``, a text file, a script that writes nothing) is reported in one line
  (:func:`host_cc`, :func:`host_cc_problem`), never run on the real sources;
* the AVR toolchain (:data:`AVR_TOOLS`) and simavr's headers (:func:`avr_problem`);
* :func:`run` runs any of them (and the programs built with them: the harness, the simavr runner) with
  their failures to start (not found, not executable, ``Exec format error``) and timeouts as one-line
  :class:`ToolError`; the simavr runner itself comes from the private build cache
  (:mod:`export.verify.buildcache`).
"""
from __future__ import annotations

import functools
import os
import shlex
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Sequence

from kiloforge.errors import printable

from ..errors import ExportError

CC_ENV = "CC"
DEFAULT_CC = "gcc"
AVR_TOOLS = ("avr-gcc", "avr-size", "avr-nm", "avr-objcopy")
SIMAVR_INCLUDE = Path("/usr/include/simavr")
PROBE_TIMEOUT_S = 60.0
_PROBE_SOURCE = "int main(void) { return 0; }\n"


class ToolError(ExportError):
    """An external program is missing, cannot be started or is not what it claims (one line)."""


def _cc_words() -> tuple[list[str] | None, str]:
    """(argv words of the host compiler, how to name it in a message); words None when CC cannot be parsed."""
    raw = os.environ.get(CC_ENV, "")
    shown = f"{CC_ENV}={printable(shlex.quote(raw))}" if raw.strip() else DEFAULT_CC
    try:
        words = shlex.split(raw) if raw.strip() else [DEFAULT_CC]
    except ValueError as e:
        return None, f"{shown} cannot be parsed ({e})"
    return (words or [DEFAULT_CC]), shown


@functools.lru_cache(maxsize=16)
def _probe(argv: tuple[str, ...]) -> str | None:
    """None when ``argv`` compiles and links a one-line C program into an executable, else why not."""
    with tempfile.TemporaryDirectory(prefix="kf_cc_probe_") as td:
        src, exe = Path(td) / "probe.c", Path(td) / "probe"
        src.write_text(_PROBE_SOURCE)
        try:
            p = subprocess.run([*argv, "-o", str(exe), str(src)], capture_output=True, text=True,
                               timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL)
        except OSError as e:
            return f"cannot be run ({printable(e.strerror or e)})"
        except subprocess.TimeoutExpired:
            return f"did not compile a one-line C program within {PROBE_TIMEOUT_S:g} s"
        if p.returncode != 0:
            first = next((line for line in (p.stderr or p.stdout).splitlines() if line.strip()), "")
            return f"failed to compile a one-line C program (exit {p.returncode}{': ' + printable(first, 200) if first else ''})"
        if not exe.is_file() or exe.stat().st_size == 0:
            return "produced no executable from a one-line C program: not a C compiler"
    return None


def host_cc_problem() -> str | None:
    """None when the host C compiler works, else a one-line reason naming ``$CC``."""
    try:
        host_cc()
    except ToolError as e:
        return str(e)
    return None


def host_cc() -> list[str]:
    """The host C compiler's argv (program resolved on PATH, then CC's flags); :class:`ToolError` otherwise."""
    words, shown = _cc_words()
    if words is None:
        raise ToolError(shown)
    exe = shutil.which(words[0])
    if exe is None:
        raise ToolError(f"no host C compiler: {shown} ({printable(words[0])} not found or not executable; "
                        f"install gcc or set {CC_ENV})")
    why = _probe((exe, *words[1:]))
    if why:
        raise ToolError(f"the host C compiler {shown} {why}; set {CC_ENV} to a C compiler such as gcc")
    return [exe, *words[1:]]


def avr_problem(simulate: bool = False) -> str | None:
    """None when the AVR toolchain (and, with ``simulate``, a host compiler and simavr's headers for the
    simavr runner) is usable, else why not."""
    gone = [t for t in AVR_TOOLS if shutil.which(t) is None]
    if gone:
        return f"missing {', '.join(gone)} (Debian: apt-get install gcc-avr binutils-avr avr-libc)"
    if simulate:
        why = host_cc_problem()
        if why:
            return f"{why} (needed to build the simavr runner)"
        if not (SIMAVR_INCLUDE / "sim_avr.h").exists():
            return "missing simavr headers (Debian: apt-get install simavr libsimavr-dev)"
    return None


def run(cmd: Sequence[str | os.PathLike], what: str, **kw) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, **kw)``; a program that cannot be started or that times out is a one-line
    :class:`ToolError` saying ``what`` it was for."""
    argv = [os.fspath(c) for c in cmd]
    try:
        return subprocess.run(argv, **kw)
    except OSError as e:
        raise ToolError(f"{what}: cannot run {printable(argv[0])} ({printable(e.strerror or e)})") from None
    except subprocess.TimeoutExpired as e:
        raise ToolError(f"{what}: {printable(Path(argv[0]).name)} did not finish within {e.timeout:g} s") from None
