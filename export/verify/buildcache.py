"""The build cache: programs kiloforge compiles once and runs many times (the simavr runner).

A cached program is only ever run from a *private* directory and only after it is verified:

* the directory is ``$KILOFORGE_CACHE`` when set, else ``<tempdir>/kiloforge-<euid>``; it is created
  with mode 0700 and checked on every use with ``lstat``: a directory, not a symbolic link, owned by
  the effective uid, no permission bits for group or others (an own directory without group/other
  *write* bits, such as one made 0755 by an older kiloforge, is tightened to 0700: nobody else could
  have written into it). ``$KILOFORGE_CACHE`` failing the check is refused with one line
  (:class:`CacheError`); the default location failing it (in a shared temp directory anybody can
  create that name first) is left alone and a fresh private directory (``tempfile.mkdtemp``) serves
  this process and is removed at exit. A temp directory that others may write without the sticky bit
  (so they could rename our directory and put theirs in its place) is refused.
* a program ``NAME-KEY`` (KEY: a hash of its source and flags) has a sidecar ``NAME-KEY.sha256``
  holding the sha256 of its bytes, written when it was built, before the program is renamed into
  place. Before it is returned the program is opened without following links and must be a regular
  file owned by the effective uid, executable by its owner, not writable by group or others, with
  contents hashing to the sidecar. Anything else (missing, a link, a directory, changed bytes, a
  wrong mode) is removed and built again; builds are serialised by a lock file in the directory.

Who may write what, and what this promises: ``docs/hardening.md`` (threat model).
"""
from __future__ import annotations

import atexit
import hashlib
import hmac
import os
import shutil
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from kiloforge.errors import printable
from kiloforge.io import atomic_path, write_atomic

from ..errors import ExportError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

CACHE_ENV = "KILOFORGE_CACHE"
DIR_MODE = 0o700
PROGRAM_MODE = 0o700
SIDECAR_SUFFIX = ".sha256"
LOCK_NAME = ".lock"
_FRESH: list[Path] = []  #: the per-process private directory used when the default one is not private


class CacheError(ExportError):
    """The build cache directory is not private (one line; says which check failed)."""


def default_location() -> Path:
    """``<tempdir>/kiloforge-<euid>``: the cache when ``$KILOFORGE_CACHE`` is unset."""
    return Path(tempfile.gettempdir()) / f"kiloforge-{os.geteuid()}"


def not_private(d: Path) -> str | None:
    """None when ``d`` is a private directory of this user (lstat: a directory, no link, owned by the
    effective uid, no group/other permission bits), else what is wrong."""
    try:
        st = os.lstat(d)
    except FileNotFoundError:
        return "does not exist"
    except OSError as e:
        return f"cannot be examined ({printable(e.strerror or e)})"
    if stat.S_ISLNK(st.st_mode):
        return "is a symbolic link"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    if st.st_uid != os.geteuid():
        return f"is owned by uid {st.st_uid}, not by you (uid {os.geteuid()})"
    if st.st_mode & 0o077:
        return f"has mode {stat.S_IMODE(st.st_mode):03o}: group or others may use it (it must be 700)"
    return None


def _make_private(d: Path, parents: bool) -> str | None:
    """Create ``d`` with mode 0700 when it is missing, tighten an own 0755-like one; None when it is
    then private, else why not."""
    try:
        if parents:
            d.parent.mkdir(parents=True, exist_ok=True)
        os.mkdir(d, DIR_MODE)
        os.chmod(d, DIR_MODE)  # the umask may have taken the owner's bits
    except FileExistsError:
        pass
    except OSError as e:
        return f"cannot be created ({printable(e.strerror or e)})"
    try:
        st = os.lstat(d)
        if (stat.S_ISDIR(st.st_mode) and st.st_uid == os.geteuid() and st.st_mode & 0o077
                and not st.st_mode & 0o022):
            os.chmod(d, DIR_MODE)  # nobody else could write into it: safe to keep
    except OSError:
        pass
    return not_private(d)


def cache_dir() -> Path:
    """The private cache directory, checked now (see the module doc); :class:`CacheError` when
    ``$KILOFORGE_CACHE`` names one that is not private."""
    explicit = os.environ.get(CACHE_ENV)
    if explicit:
        d = Path(explicit).absolute()
        why = _make_private(d, parents=True)
        if why:
            raise CacheError(f"the build cache {CACHE_ENV}={printable(d)} {why}; point {CACHE_ENV} at a "
                             f"private directory of yours (mode 700) or unset it")
        return d
    try:
        d = default_location()
        st = os.stat(d.parent)
        if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
            raise CacheError(f"the temp directory {printable(d.parent)} is writable by others and not sticky: anybody "
                             f"could swap the build cache inside it; set {CACHE_ENV} to a private directory of yours")
        if _make_private(d, parents=False) is None:
            return d
        if not _FRESH or not_private(_FRESH[0]) is not None:
            fresh = Path(tempfile.mkdtemp(prefix=f"kiloforge-{os.geteuid()}-"))
            atexit.register(shutil.rmtree, fresh, ignore_errors=True)
            _FRESH[:] = [fresh]
    except OSError as e:  # no usable temp directory (gettempdir, mkdtemp)
        raise CacheError(f"no private build cache can be made in the temp directory ({printable(e.strerror or e)}); "
                         f"set {CACHE_ENV} to a private directory of yours") from None
    why = not_private(_FRESH[0])
    if why:  # pragma: no cover - mkdtemp makes a 0700 directory of ours
        raise CacheError(f"the build cache {printable(_FRESH[0])} {why}")
    return _FRESH[0]


def _sha256_fd(fd: int) -> str:
    h = hashlib.sha256()
    while chunk := os.read(fd, 1 << 20):
        h.update(chunk)
    return h.hexdigest()


def _read_own_file(path: Path, *, program: bool) -> tuple[os.stat_result, str] | None:
    """(fstat, sha256) of ``path`` opened without following a link, when it is a regular file of ours
    that group and others cannot write (and, with ``program``, that its owner can execute); else None.
    A sidecar's sha256 is replaced by its text."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid() or st.st_mode & 0o022:
            return None
        if program and not st.st_mode & stat.S_IXUSR:
            return None
        if program:
            return st, _sha256_fd(fd)
        if st.st_size > 256:
            return None
        return st, os.read(fd, 256).decode("ascii", "replace").strip()
    except OSError:
        return None
    finally:
        os.close(fd)


def verified(program: Path) -> bool:
    """``program`` may be run: see the module doc (owner, mode, no link, sha256 equal to its sidecar's)."""
    found = _read_own_file(program, program=True)
    recorded = _read_own_file(program.with_name(program.name + SIDECAR_SUFFIX), program=False)
    return found is not None and recorded is not None and hmac.compare_digest(found[1], recorded[1])


def _remove(path: Path) -> None:
    """Remove whatever is at ``path`` inside the private directory (a link itself, not its target)."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
    except OSError as e:
        raise CacheError(f"cannot replace {printable(path)} in the build cache: {printable(e.strerror or e)}") from None


@contextmanager
def _locked(d: Path) -> Iterator[None]:
    """Serialise builds in ``d`` between processes (an advisory lock on ``d/.lock``)."""
    lock = d / LOCK_NAME
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o600)
    except OSError as e:
        raise CacheError(f"cannot lock the build cache {printable(d)}: {printable(e.strerror or e)}") from None
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def private_dir(directory: str | os.PathLike) -> Path:
    """``directory`` (created 0700 when missing) if it is private (:func:`not_private`), else :class:`CacheError`."""
    d = Path(directory).absolute()
    why = _make_private(d, parents=True)
    if why:
        raise CacheError(f"the build directory {printable(d)} {why}; build into a private directory of yours")
    return d


def cached_program(name: str, key: str, build: Callable[[Path], None], directory: str | os.PathLike | None = None) -> Path:
    """The verified program ``NAME-KEY`` of the private cache (or of the private ``directory``: a caller's
    own build directory, checked like the cache); ``build(path)`` writes it (e.g. a compiler's ``-o path``)
    when it is missing or fails verification. Never returns an unverified path."""
    d = cache_dir() if directory is None else private_dir(directory)
    program = d / f"{name}-{key}"
    if verified(program):
        return program
    sidecar = program.with_name(program.name + SIDECAR_SUFFIX)
    with _locked(d):
        if verified(program):  # another process built it meanwhile
            return program
        _remove(program)
        _remove(sidecar)
        with atomic_path(program, mode=PROGRAM_MODE) as tmp:
            build(tmp)
            fd = os.open(tmp, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
            try:
                digest = _sha256_fd(fd)
            finally:
                os.close(fd)
            write_atomic(sidecar, digest + "\n", mode=0o600)
    if not verified(program):
        raise CacheError(f"the program just built, {printable(program)}, does not verify (changed while it was built)")
    return program
