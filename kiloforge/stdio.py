"""Standard output and error that cannot fail a command: every program runs under :func:`guarded_output`.

* **text the terminal's encoding lacks** (a world name in another script under ``LC_ALL=C`` or
  ``PYTHONIOENCODING=ascii``, a file name that is not UTF-8, held as ``\\udcff`` by surrogateescape) is
  printed with backslash escapes instead of ending in a ``UnicodeEncodeError``;
* **a reader that went away** (``| head -c1``): the command stops quietly with :data:`EXIT_BROKEN_PIPE`,
  128 + SIGPIPE, as a program killed by SIGPIPE would (what it had published stays complete);
* **standard output that cannot be written** (``>/dev/full``) and any other ``OSError`` that reaches the
  program (a file name too long, a full disk, an unreadable directory) end in the one line
  ``<program>: error: ...`` with exit status 2; when standard output failed after the command had
  published files (:func:`kiloforge.io.published_since`) or completed, the line says so (those files are
  complete sets).
"""
from __future__ import annotations

import errno
import io
import os
import sys
from typing import Any, Callable

from .cliparse import EXIT_USAGE, error_line
from .errors import os_error_text, printable
from .io import published_count, published_since

EXIT_BROKEN_PIPE = 141  #: 128 + SIGPIPE: the reader of standard output went away


class _Closed(io.TextIOBase):
    """A standard stream whose descriptor was closed when the program started (``>&-``, ``2>&-``): Python sets it
    to None. Standard output fails every write as a closed descriptor does (one line, exit 2, as ``>/dev/full``);
    standard error, where nothing can be said, takes what is written and drops it."""

    def __init__(self, fails: bool) -> None:
        super().__init__()
        self._fails = fails

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        if self._fails and text:
            raise OSError(errno.EBADF, "it was closed")
        return len(text)


def closed_streams() -> None:
    """Standard streams closed by the caller: their descriptors 0-2 are held on the null device, so no file a
    command opens takes their number (a tool run later would write its output into it), and None streams become
    :class:`_Closed`."""
    for fd in (0, 1, 2):
        try:
            os.fstat(fd)
        except OSError:
            try:
                null = os.open(os.devnull, os.O_RDWR)
                if null != fd:
                    os.dup2(null, fd)
                    os.close(null)
            except OSError:
                pass
    if sys.stdout is None:
        sys.stdout = _Closed(fails=True)
    if sys.stderr is None:
        sys.stderr = _Closed(fails=False)


def tolerant_streams() -> None:
    """Standard output and error escape what their encoding cannot hold (``\\xe9``, ``\\udcff``)."""
    for stream in (sys.stdout, sys.stderr):
        if isinstance(stream, io.TextIOWrapper) and stream.errors != "backslashreplace":
            try:
                stream.reconfigure(errors="backslashreplace")
            except (ValueError, OSError):  # closed, or its buffer refuses: leave it
                pass


def _drop_stdout() -> None:
    """Send what is left of standard output nowhere, so the interpreter's last flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):  # not a file: nothing at exit either
        pass


def _flushed(prog: str, status: int) -> int:
    """``status`` after flushing standard output; a failure there is reported only if nothing else was."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        _drop_stdout()
        return status or EXIT_BROKEN_PIPE
    except OSError as e:
        _drop_stdout()
        if status == 0:
            print(error_line(prog, f"cannot write standard output ({os_error_text(e, name=False)}); "
                                   "the command itself completed"), file=sys.stderr)
            return EXIT_USAGE
    except ValueError:  # closed by the command
        pass
    return status


class _Watched:
    """Standard output as the command sees it: the same stream, remembering the error a write raised."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.failed: BaseException | None = None

    def write(self, text: str) -> int:
        try:
            return self.inner.write(text)
        except OSError as e:
            self.failed = e
            raise

    def flush(self) -> None:
        try:
            self.inner.flush()
        except OSError as e:
            self.failed = e
            raise

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def guarded_output(prog: str, run: Callable[[], int]) -> int:
    """``run()``'s exit status, with the streams and errors of the module doc handled for ``prog`` (a
    ``SystemExit`` of a parser's ``--help`` goes on, after standard output was flushed)."""
    closed_streams()
    tolerant_streams()
    watched = sys.stdout = _Watched(sys.stdout)
    try:
        status = _run(prog, run, watched, published_count())
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) or e.code is None else EXIT_USAGE
        if sys.stdout is watched:
            sys.stdout = watched.inner
        flushed = _flushed(prog, code or 0)
        raise SystemExit(e.code if flushed == (code or 0) else flushed) from None
    finally:
        if sys.stdout is watched:
            sys.stdout = watched.inner
    return _flushed(prog, status)


def _run(prog: str, run: Callable[[], int], watched: _Watched, mark: int) -> int:
    try:
        return run()
    except BrokenPipeError:
        _drop_stdout()
        return EXIT_BROKEN_PIPE
    except OSError as e:
        if e is watched.failed:  # a print of the command
            _drop_stdout()
            written = published_since(mark)
            text = f"cannot write standard output ({os_error_text(e, name=False)})" + (
                f"; {', '.join(printable(p) for p in written)} had been written completely" if written else "")
        else:
            text = os_error_text(e)
        print(error_line(prog, text), file=sys.stderr)
        return EXIT_USAGE
