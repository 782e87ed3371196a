"""File output for the whole project: one file atomically, or a set of files all or nothing.

* :func:`write_atomic` writes one file (bytes, or str encoded as UTF-8): a temp file beside it,
  fsync, ``os.replace``; :func:`atomic_path` is the same for writers that want a file name
  (matplotlib, Pillow, ``torch.save``, a compiler's ``-o``); both write through a symbolic link
  (the link stays, the file it leads to is replaced: :func:`through_links`);
* :func:`staged_files` is for a command that writes several files into one directory (the
  exporter's C files and manifest, the simulator's plots and metrics, an evaluation): the files
  are written into a staging directory beside them and published together;
  :func:`write_files_atomic` does it for contents already in memory.

Publishing a set ``[f_1, ..., f_n]`` (``f_n``, the *record*, is the file that describes the set:
the export manifest with the hashes of the files, ``metrics.json``, ...):

1. every file is written and fsynced in the staging directory ``.<f_n>.kf<pid>-<token>.stage``;
2. a journal (names, sizes, sha256) is written and renamed into the staging directory: from
   here on the new set is committed, and SIGINT / SIGTERM are held back until step 5;
3. the old record is removed, 4. ``f_1 .. f_{n-1}`` are renamed into place, then ``f_n``;
5. the staging directory is removed.

A reader that takes the record's presence as "the set is complete" (and can check the hashes it
lists) therefore never sees a mixed set: the record is absent exactly while files change. A
process killed (SIGKILL, power loss) before step 2 leaves the old set untouched; after step 2 the
next :func:`recover` (every publish of the same record runs it first) completes steps 3 to 5.
Temporaries of dead writers (their pid no longer runs, or their lock is free for a minute) are
removed the same way. Failures raise :class:`kiloforge.errors.OutputError` with one line.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
import stat
import time
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Iterator, Mapping, Sequence

from . import interrupts
from .errors import OutputError
from .validate import printable

try:  # POSIX: a writer holds an advisory lock on its temporaries while it runs
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

JOURNAL = "journal.json"
JOURNAL_FORMAT = "kiloforge-publish"
STALE_LOCK_S = 60.0  #: a temporary whose lock is free is stale after this long (covers a reused pid)
_TAG = re.compile(r"\.kf(\d+)-[0-9a-f]{8}\.(tmp|stage)")
_PUBLISHED: list[Path] = []  #: every set published by this process, in order (see :func:`published_since`)
_STAGES: dict[Path, Path] = {}  #: staging directory -> the directory its files are published into


def published_since(mark: int) -> list[Path]:
    """The files of the sets published completely since ``mark`` (a length of :func:`published_count`):
    what an interrupted command really wrote."""
    return list(_PUBLISHED[mark:])


def published_count() -> int:
    return len(_PUBLISHED)


def shown(path: str | os.PathLike) -> str:
    """``path`` for a message: escaped, and a file of a staging directory named where it will be published."""
    path = Path(path)
    return printable(_STAGES[path.parent] / path.name if path.parent in _STAGES else path)


def _dir_of(path: Path) -> Path:
    return path.parent if str(path.parent) else Path(".")


MAX_STEM = 60  #: characters of a file name made from free text (:func:`file_stem`)


def file_stem(text: str) -> str:
    """A file-name stem made from free text (a policy's label): letters, digits, ``-_.`` kept, anything else
    ``_``; at most :data:`MAX_STEM` characters, a cut one ending in 8 hex digits of its text's sha256 (so
    two long labels stay two names).

    >>> file_stem("runs/a b$x")
    'runs_a_b_x'
    >>> len(file_stem("x" * 300))
    60
    """
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in text)
    if len(stem) <= MAX_STEM:
        return stem
    digest = hashlib.sha256(text.encode("utf-8", "surrogateescape")).hexdigest()[:8]
    return f"{stem[:MAX_STEM - 9]}-{digest}"


def _limit(path: Path, name: str, default: int) -> int:
    """``os.pathconf`` of the nearest existing directory of ``path`` (``default`` where it says nothing)."""
    d = Path(os.path.abspath(path))
    while True:
        try:
            value = os.pathconf(d, name)
            return value if value and value > 0 else default
        except (OSError, ValueError):
            if d == d.parent:
                return default
            d = d.parent


def check_name_lengths(path: str | os.PathLike, temp: bool = True) -> None:
    """Raise :class:`OutputError` (one line, before any work) when the file system would refuse ``path``
    as too long: a component over its longest name, the temporary written beside ``path`` first
    (``temp``; :func:`_temp_name`, a few dozen bytes longer than the name), or the whole path over its
    longest path. Names count in bytes as the file system sees them (``os.fsencode``)."""
    path = Path(path)
    name_max = _limit(path.parent, "PC_NAME_MAX", 255)
    for part in path.parts:
        n = len(os.fsencode(part))
        if n > name_max:
            raise OutputError(f"cannot write '{printable(path, 120)}': the name '{printable(part, 60)}' is {n} bytes, "
                              f"more than the {name_max} this file system allows")
    if temp and path.name:
        n = len(os.fsencode(path.name))
        temp = len(os.fsencode(_temp_name(path.name, "stage", path.suffix)))
        if temp > name_max:
            raise OutputError(f"cannot write '{printable(path, 120)}': its name is {n} bytes and the temporary "
                              f"written beside it first {temp}, more than the {name_max} this file system allows; "
                              f"choose a name of at most {name_max - (temp - n)} bytes")
    path_max = _limit(path.parent, "PC_PATH_MAX", 4096)
    full = len(os.fsencode(os.path.abspath(path))) + 64  # room for a temporary beside it or a file in it
    if full > path_max:
        raise OutputError(f"cannot write '{printable(path, 120)}': the path is {full - 64} bytes, too long for the "
                          f"{path_max} this file system allows")


def _special_kind(path: Path) -> str:
    """'' when ``path`` does not exist or is a regular file or a symbolic link, else what it is (a device, ...)."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return ""
    for test, kind in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a named pipe"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return ""


def _check_dir(path: Path) -> None:
    check_name_lengths(path)
    d = _dir_of(path)
    if not d.exists():
        raise OutputError(f"cannot write '{path}': directory '{d}' does not exist")
    if not d.is_dir():
        raise OutputError(f"cannot write '{path}': '{d}' is not a directory")
    if path.is_dir():
        raise OutputError(f"cannot write '{path}': it is a directory")
    kind = _special_kind(path)
    if kind:  # replacing it would turn e.g. /dev/null (run as root) into a regular file
        raise OutputError(f"cannot write '{printable(path)}': it is {kind}, not a regular file")
    if not os.access(d, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write '{path}': directory '{d}' is not writable")


def check_writable(paths: Sequence[str | os.PathLike]) -> None:
    """Raise :class:`OutputError` unless every path's directory exists and is writable."""
    for p in paths:
        _check_dir(Path(p))


def new_file_mode(executable: bool = False) -> int:
    """The mode ``open()`` would give a new file: 0o666 (0o777 for an executable) less the process
    umask (temp files get 0o600)."""
    mask = os.umask(0o077)  # the umask can only be read by setting it; restored at once
    os.umask(mask)
    return (0o777 if executable else 0o666) & ~mask


# --- temporaries and their owners ----------------------------------------------------------------
def _temp_name(target: str, kind: str, suffix: str = "") -> str:
    return f".{target}.kf{os.getpid()}-{secrets.token_hex(4)}.{kind}{suffix}"


def _lock(f: IO[bytes] | int) -> None:
    if fcntl is not None:
        fcntl.flock(f if isinstance(f, int) else f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError, AttributeError):
        return True
    return True


def _lock_free(path: Path) -> bool:
    """Nobody holds the advisory lock on ``path`` (a temp file, or a staging directory's lock file)."""
    if fcntl is None:
        return False
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def _stale(entry: Path, pid: int, lock_file: Path) -> bool:
    if not _pid_alive(pid):
        return True
    try:
        old = time.time() - entry.lstat().st_mtime > STALE_LOCK_S
    except OSError:
        return False
    return old and pid != os.getpid() and _lock_free(lock_file)


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def recover(directory: str | os.PathLike, names: Sequence[str] | None = None) -> list[Path]:
    """Finish or remove what dead writers left in ``directory`` (for the targets ``names``, or all):
    a committed staging directory is published (steps 3 to 5), an uncommitted one and temp files
    are removed. Returns the entries handled. Never touches the temporaries of a live writer."""
    d = Path(directory)
    try:
        entries = sorted(d.iterdir())
    except OSError:
        return []
    wanted = None if names is None else {f".{n}" for n in names}
    done = []
    for e in entries:
        m = _TAG.search(e.name)
        if not m or not e.name.startswith("."):
            continue
        if wanted is not None and e.name[:m.start()] not in wanted:
            continue
        pid, kind = int(m.group(1)), m.group(2)
        if kind == "stage" and e.is_dir() and not e.is_symlink():
            if _stale(e, pid, e / "lock"):
                journal = _read_journal(e)
                if journal is not None:
                    try:
                        _apply(d, e, journal)
                    except OSError:
                        pass
                shutil.rmtree(e, ignore_errors=True)
                done.append(e)
        elif kind == "tmp" and e.is_file() and not e.is_symlink():
            if _stale(e, pid, e):
                e.unlink(missing_ok=True)
                done.append(e)
    return done


# --- one file ------------------------------------------------------------------------------------
@contextmanager
def _temp_beside(path: Path, suffix: str) -> Iterator[tuple[Path, int]]:
    """A new locked temp file beside ``path``: (its path, an open fd holding the lock)."""
    d = _dir_of(path)
    for _ in range(16):
        tmp = d / _temp_name(path.name, "tmp", suffix)
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
            break
        except FileExistsError:
            continue
        except OSError as e:
            raise OutputError(f"cannot write '{shown(path)}': {printable(e.strerror or e)}") from None
    else:  # pragma: no cover - 16 collisions of a random 32-bit token
        raise OutputError(f"cannot write '{path}': no free temporary name")
    try:
        _lock(fd)
        yield tmp, fd
    finally:
        os.close(fd)
        tmp.unlink(missing_ok=True)


def through_links(path: Path) -> Path:
    """The file a one-file write to ``path`` replaces: ``path``, or, when it is a symbolic link, the file it
    leads to (through every link; it may not exist yet), so the link stays and its target is replaced
    atomically, as an editor saving through a link does. A loop of links is an OutputError."""
    check_name_lengths(path)
    if not path.is_symlink():
        return path
    target = Path(os.path.realpath(path))
    if target.is_symlink():
        raise OutputError(f"cannot write '{printable(path)}': a loop of symbolic links")
    return target


def write_atomic(path: str | os.PathLike, data: bytes | str, executable: bool = False, *,
                 mode: int | None = None) -> Path:
    """Write one file atomically (str is UTF-8 encoded), through a symbolic link (:func:`through_links`);
    returns ``path``. ``mode``: its permission bits (default: those of a new file, :func:`new_file_mode`)."""
    given = Path(path)
    path = through_links(given)
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    _check_dir(path)
    recover(_dir_of(path), [path.name])
    try:
        with _temp_beside(path, "") as (tmp, fd):
            view = memoryview(raw)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
            os.chmod(tmp, new_file_mode(executable) if mode is None else mode)
            os.replace(tmp, path)
    except OSError as e:
        raise OutputError(f"cannot write '{shown(path)}': {printable(e.strerror or e)}") from None
    return given


@contextmanager
def atomic_path(path: str | os.PathLike, executable: bool = False, *, mode: int | None = None) -> Iterator[Path]:
    """Yield a temp sibling of ``path`` (same suffix) to write by name; on success it is fsynced, given
    ``mode`` (default: the mode of a new file, :func:`new_file_mode`) and moved onto ``path`` (through a
    symbolic link: :func:`through_links`), on an exception removed (``path`` is left as it was)."""
    path = through_links(Path(path))
    _check_dir(path)
    recover(_dir_of(path), [path.name])
    with _temp_beside(path, path.suffix) as (tmp, _):
        try:
            yield tmp
        except BrokenPipeError:  # standard output's reader went away: not this file's failure
            raise
        except OSError as e:  # the writer's (a full disk): one line naming the file, not the temporary
            raise OutputError(f"cannot write '{shown(path)}': {printable(e.strerror or e)}") from None
        try:
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
            os.chmod(tmp, new_file_mode(executable) if mode is None else mode)
            os.replace(tmp, path)
        except OSError as e:
            raise OutputError(f"cannot write '{shown(path)}': {printable(e.strerror or e)}") from None


# --- a set of files ------------------------------------------------------------------------------
def _sha256_file(path: Path) -> tuple[str, int]:
    h = hashlib.sha256()
    n = 0
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
            n += len(chunk)
        os.fsync(f.fileno())
    return h.hexdigest(), n


def _read_journal(stage: Path) -> list[str] | None:
    """The file names of a staging directory's journal, in publish order (None: not committed)."""
    try:
        doc = json.loads((stage / JOURNAL).read_text(encoding="utf-8"))
        names = [f["name"] for f in doc["files"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if doc.get("format") != JOURNAL_FORMAT or not names or not all(_simple_name(n) for n in names):
        return None
    return names


def _simple_name(name: object) -> bool:
    """A name inside one directory: no separator of this system (a backslash is a plain character on POSIX)."""
    return isinstance(name, str) and name not in ("", ".", "..") and os.sep not in name \
        and (os.altsep is None or os.altsep not in name) and "\0" not in name and name != JOURNAL


def _apply(directory: Path, stage: Path, names: Sequence[str]) -> None:
    """Steps 3 and 4 (idempotent: a recovery may repeat them): remove the old record, move the
    files, the record last."""
    record = names[-1]
    if (stage / record).exists():
        (directory / record).unlink(missing_ok=True)
        _fsync_dir(directory)
    for n in names[:-1]:
        if (stage / n).exists():
            os.replace(stage / n, directory / n)
    if (stage / record).exists():
        os.replace(stage / record, directory / record)
    _fsync_dir(directory)


def _publish(directory: Path, stage: Path, names: Sequence[str]) -> None:
    files = []
    for n in names:
        if not (stage / n).is_file():
            raise OutputError(f"cannot write '{directory / n}': it was not produced")
        digest, size = _sha256_file(stage / n)
        files.append({"name": n, "sha256": digest, "bytes": size})
    tmp = stage / "journal.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump({"format": JOURNAL_FORMAT, "version": 1, "files": files}, f)
        f.flush()
        os.fsync(f.fileno())
    with interrupts.deferred():
        os.replace(tmp, stage / JOURNAL)  # the commit point
        _fsync_dir(stage)
        try:
            try:
                _apply(directory, stage, names)
            except OSError:
                _apply(directory, stage, names)  # once more (idempotent)
        except OSError as e:
            # abandon the set rather than let a later recovery publish it over newer files: the
            # record is gone, so readers see an incomplete set, which is what it is
            shutil.rmtree(stage, ignore_errors=True)
            raise OutputError(f"cannot write '{directory / names[-1]}' and the files beside it: "
                              f"{printable(e.strerror or e)}; the set in '{directory}' is incomplete "
                              f"(no {names[-1]}): write it again") from None
        _PUBLISHED.extend(directory / n for n in names)
        shutil.rmtree(stage, ignore_errors=True)


@contextmanager
def staged_files(directory: str | os.PathLike, names: Sequence[str] | None = None, *, record: str | None = None,
                 create: bool = False) -> Iterator[Path]:
    """Yield a staging directory beside ``directory``'s files; write every one of ``names`` into it.
    On leaving the block they are published together (the last name is the set's record, see the
    module doc); on an exception nothing changes (and ``directory``, when ``create`` made it, is
    removed again). Stale temporaries of the same set are recovered first.

    ``names=None, record=R``: the set is whatever files the block wrote (in name order), ``R`` last
    (for writers whose file names depend on their options, such as an evaluation's plots)."""
    directory = Path(directory)
    check_name_lengths(directory, temp=False)
    names = [record] if names is None and record is not None else list(names or ())
    if not names or len(set(names)) != len(names) or not all(_simple_name(n) for n in names):
        raise ValueError(f"staged_files needs distinct plain file names, got {names}")
    created: list[Path] = []
    if create:
        p = directory
        while not p.exists() and p != p.parent:
            created.append(p)
            p = p.parent
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OutputError(f"cannot create '{directory}': {printable(e.strerror or e)}") from None
    try:
        check_writable([directory / n for n in names])
        recover(directory, names)
        stage = directory / _temp_name(names[-1], "stage")
        try:
            stage.mkdir(mode=0o700)
            lock = os.open(stage / "lock", os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as e:
            raise OutputError(f"cannot write into '{directory}': {printable(e.strerror or e)}") from None
        _STAGES[stage] = directory
        try:
            _lock(lock)
            try:
                yield stage
            except OSError as e:
                if e.filename is None or not os.fspath(e.filename).startswith(os.fspath(stage)):
                    raise
                raise OutputError(f"cannot write into '{printable(directory)}': "
                                  f"{printable(e.strerror or e)}") from None
            if record is not None:  # what the block wrote, the record last
                wrote = sorted(p.name for p in stage.iterdir() if p.is_file() and p.name != "lock"
                               and not p.name.startswith("."))
                names = [n for n in wrote if n != record] + [record]
                if not all(_simple_name(n) for n in names):
                    raise OutputError(f"cannot write into '{directory}': unexpected file names {names}")
            try:
                _publish(directory, stage, names)
            except OSError as e:
                raise OutputError(f"cannot write into '{directory}': {printable(e.strerror or e)}") from None
        finally:
            _STAGES.pop(stage, None)
            os.close(lock)
            if stage.exists() and _read_journal(stage) is None:
                shutil.rmtree(stage, ignore_errors=True)
    except BaseException:
        for p in created:  # innermost first; only if still empty
            try:
                p.rmdir()
            except OSError:
                break
        raise


def write_files_atomic(files: Mapping[str | os.PathLike, bytes | str], *, create: bool = False) -> list[Path]:
    """Write every ``path -> content`` (str is UTF-8 encoded) as one set, all or nothing
    (:func:`staged_files`); the paths share one directory and the last one is the set's record."""
    items = [(Path(p), c.encode("utf-8") if isinstance(c, str) else bytes(c)) for p, c in files.items()]
    if not items:
        return []
    dirs = {_dir_of(p).resolve() if _dir_of(p).exists() else _dir_of(p) for p, _ in items}
    if len(dirs) != 1:
        raise ValueError(f"write_files_atomic writes into one directory, got {sorted(map(str, dirs))}")
    directory = _dir_of(items[0][0])
    with staged_files(directory, [p.name for p, _ in items], create=create) as stage:
        for p, data in items:
            try:
                with open(stage / p.name, "wb") as f:
                    f.write(data)
            except OSError as e:
                raise OutputError(f"cannot write '{p}': {printable(e.strerror or e)}") from None
    return [p for p, _ in items]
