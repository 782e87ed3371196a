"""Atomic file output for the whole project: temp file in the target directory, fsync, ``os.replace``.

* :func:`write_atomic` writes one file (bytes, or str encoded as UTF-8);
* :func:`write_files_atomic` writes several files all-or-nothing: every temp file is written first;
  only when all succeeded are they renamed into place, and if a rename fails the files already
  renamed are put back as they were (restored from a backup, or removed when they did not exist);
* :func:`atomic_path` is for writers that want a file name (matplotlib, Pillow, ``torch.save``, a
  compiler's ``-o``): it yields a temp sibling and moves it onto the target only on success.

Failures raise :class:`kiloforge.errors.OutputError` with a one-line message.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Mapping

from .errors import OutputError


def _check_dir(path: Path) -> None:
    d = path.parent if str(path.parent) else Path(".")
    if not d.exists():
        raise OutputError(f"cannot write '{path}': directory '{d}' does not exist")
    if not d.is_dir():
        raise OutputError(f"cannot write '{path}': '{d}' is not a directory")
    if path.is_dir():
        raise OutputError(f"cannot write '{path}': it is a directory")
    if not os.access(d, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write '{path}': directory '{d}' is not writable")


def check_writable(paths: list[Path]) -> None:
    """Raise :class:`OutputError` unless every path's directory exists and is writable."""
    for p in paths:
        _check_dir(Path(p))


def new_file_mode(executable: bool = False) -> int:
    """The mode ``open()`` would give a new file: 0o666 (0o777 for an executable) less the process
    umask (temp files get 0o600)."""
    mask = os.umask(0o077)  # the umask can only be read by setting it; restored at once
    os.umask(mask)
    return (0o777 if executable else 0o666) & ~mask


def _temp_sibling(path: Path) -> Path:
    """A new empty file beside ``path`` (same directory, so that ``os.replace`` is atomic)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}",
                               dir=path.parent if str(path.parent) else ".")
    os.close(fd)
    return Path(tmp)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _write_temp(path: Path, data: bytes) -> Path:
    tmp = _temp_sibling(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, new_file_mode())
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def write_files_atomic(files: Mapping[str | os.PathLike, bytes | str]) -> list[Path]:
    """Write every ``path -> content`` (str is UTF-8 encoded) all-or-nothing; returns the paths."""
    items = [(Path(p), c.encode("utf-8") if isinstance(c, str) else bytes(c)) for p, c in files.items()]
    check_writable([p for p, _ in items])
    temps: list[tuple[Path, Path]] = []
    try:
        for p, data in items:
            temps.append((_write_temp(p, data), p))
    except OSError as e:
        for t, _ in temps:
            t.unlink(missing_ok=True)
        raise OutputError(f"cannot write '{items[len(temps)][0]}': {e.strerror or e}") from None
    done: list[tuple[Path, Path | None]] = []  # (target, backup or None)
    try:
        for t, p in temps:
            backup = None
            if p.exists():
                backup = p.with_name(f".{p.name}.bak")
                os.replace(p, backup)
            done.append((p, backup))
            os.replace(t, p)
    except OSError as e:
        for p, backup in reversed(done):
            try:
                if backup is not None:
                    os.replace(backup, p)
                else:
                    p.unlink(missing_ok=True)
            except OSError:
                pass
        for t, _ in temps:
            t.unlink(missing_ok=True)
        raise OutputError(f"cannot write '{p}': {e.strerror or e}") from None
    for _, backup in done:
        if backup is not None:
            backup.unlink(missing_ok=True)
    return [p for p, _ in items]


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write one file atomically (str is UTF-8 encoded); returns its path."""
    return write_files_atomic({path: data})[0]


@contextmanager
def atomic_path(path: str | os.PathLike, executable: bool = False) -> Iterator[Path]:
    """Yield a temp sibling of ``path`` (same suffix) to write by name; on success it is fsynced, given
    the mode of a new file (:func:`new_file_mode`) and moved onto ``path``, on an exception removed
    (``path`` is left as it was)."""
    path = Path(path)
    _check_dir(path)
    tmp = _temp_sibling(path)
    try:
        yield tmp
        _fsync_file(tmp)
        os.chmod(tmp, new_file_mode(executable))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
